"""A live session's recording read back with the Rerun SDK: its ``utc`` timeline starts
at the session, not in 1970, and its map panel opens on what it draws."""

from __future__ import annotations

import json
import subprocess
import time
from pathlib import Path

import numpy as np
import pyarrow as pa
import pytest

from conftest import zfusion
from _recording import row_times, verify

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def live(tmp_path_factory):
    """patent-3d live for 12 s: (the wall time just before it started, the recording, the
    summary, its stderr)."""
    tmp = tmp_path_factory.mktemp("live")
    t0 = time.time()
    p = zfusion("run", "--scenario", "patent-3d", "--live", "--for", "12", "--rrd", str(tmp / "live.rrd"),
                "--json", str(tmp / "live.json"), "--deployment", f"live{int(t0 * 1000) % 10**9}",
                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    out, err = p.communicate(timeout=240)
    assert p.returncode == 0, err[-3000:]
    verify(tmp / "live.rrd")
    return t0, tmp / "live.rrd", json.loads((tmp / "live.json").read_text()), err


def test_no_row_of_a_live_recording_is_before_the_session(live):
    t0, rrd, doc, _ = live
    rows = row_times(rrd, "utc")
    assert rows, "no row on the utc timeline"
    early = {path: times[0] for path, times in rows.items() if times[0] < t0}
    assert not early, early  # status events were stamped 1970-01-01 (t = 0)
    last = max(times[-1] for times in rows.values())
    assert last <= time.time() and last - t0 < 600
    assert doc["epoch_utc"] > t0


def _map_zoom(rrd: Path) -> float | None:
    """The zoom the recording's blueprint gives its map panel (None: Rerun chooses)."""
    from rerun.chunk import RrdReader

    reader = RrdReader(rrd)
    for chunk in reader.store(store=reader.blueprints()[0]).stream():
        rb = chunk.to_record_batch()
        if "MapZoom:zoom" in rb.schema.names:
            return float(rb.column("MapZoom:zoom").to_pylist()[-1][0])
    return None


def _latest_map_points(rrd: Path) -> dict[str, np.ndarray]:
    """Per map entity, the [lat, lon] of its latest row (what the panel shows at the end)."""
    from rerun.chunk import RrdReader

    latest: dict[str, tuple[int, np.ndarray]] = {}
    for chunk in RrdReader(rrd).stream():
        if chunk.is_static or not chunk.entity_path.startswith("/map/"):
            continue
        rb = chunk.to_record_batch()
        ts = rb.column(chunk.timeline_names[0]).cast(pa.int64()).to_pylist()
        cols = [n for n in ("GeoPoints:positions", "GeoLineStrings:line_strings") if n in rb.schema.names]
        for i, t in enumerate(ts):
            rows = [rb.column(n)[i].as_py() for n in cols]
            pts = [np.asarray(r, dtype=float).reshape(-1, 2) for r in rows if r]
            if pts and t >= latest.get(chunk.entity_path, (-1, None))[0]:
                latest[chunk.entity_path] = (t, np.vstack(pts))
    return {path: pts for path, (_, pts) in latest.items()}


def _mercator(lat_lon: np.ndarray, zoom: float) -> np.ndarray:
    """Web Mercator in UI points at ``zoom`` (the world 256·2^zoom wide), as the map view draws."""
    world = 256.0 * 2.0 ** zoom
    x = (lat_lon[:, 1] / 360.0 + 0.5) * world
    y = (0.5 - np.arcsinh(np.tan(np.radians(lat_lon[:, 0]))) / (2 * np.pi)) * world
    return np.column_stack([x, y])


def test_the_map_panel_opens_on_the_sites_track_and_truth(live):
    """The map view of Rerun 0.41 centres on the middle of what it draws, and without a
    zoom in the blueprint keeps the one its first frame fitted: patent-3d's two sensors
    share one site, a single point, so it kept zoom 16 (1 km across) at the middle of a
    track 10 km out, and drew nothing. The blueprint now gives the zoom of the session's
    area: what the recording holds at its end lies inside a map panel of 440 x 640 points."""
    _, rrd, _, _ = live
    zoom = _map_zoom(rrd)
    assert zoom is not None and 8.0 < zoom < 16.0, zoom
    shown = _latest_map_points(rrd)
    assert {"/map/sites/radar2d", "/map/sites/angle", "/map/truth/T1", "/map/tracks/centre/T1"} <= set(shown)
    xy = _mercator(np.vstack(list(shown.values())), zoom)
    centre = (xy.min(axis=0) + xy.max(axis=0)) / 2  # the centre of the span, as the view pans
    half = np.abs(xy - centre).max(axis=0)
    assert half[0] <= 220 and half[1] <= 320, half  # within the panel
    assert max(half) > 40, half  # and not a dot in its middle: the zoom fits the area


def test_the_live_log_says_utc_times_as_iso(live):
    """The fuser's first input time was printed as an epoch number, 1.79632e+09 s."""
    t0, _, _, err = live
    line = next(ln for ln in err.splitlines() if "fuser: input starts at " in ln)
    day = time.strftime("%Y-%m-%dT", time.gmtime(t0))
    assert f"fuser: input starts at {day}" in line and line.endswith("Z") and "e+09" not in err, line
