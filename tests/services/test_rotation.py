"""Recording rotation: ``--rotate-s N`` gives ``<stem>.<k>.rrd`` files, each verified by
``rerun rrd verify`` and complete on its own (blueprint, static entities, sites), one
recording id across them, and together every fused update exactly once."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from services.rotation import Rotation, rotated_files, rotated_path

from _runs import run_cmd
from _recording import read_rrd, static_paths, verify


def test_windows_are_aligned_and_empty_ones_make_no_file(tmp_path):
    r = Rotation(tmp_path / "s.rrd", 10.0)
    assert r.first() == tmp_path / "s.0.rrd"
    assert [r.due(t) for t in (3.0, 9.99)] == [None, None]  # the first row fixes the window [0, 10)
    assert r.due(10.0) == 10.0 and r.next() == tmp_path / "s.1.rrd"
    assert r.due(19.0) is None
    assert r.due(47.5) == 40.0 and r.next() == tmp_path / "s.2.rrd"  # [20, 40) had no data: no file
    assert r.due(49.9) is None and r.due(50.0) == 50.0
    live = Rotation(tmp_path / "l.rrd", 3600.0)
    assert live.due(1_764_620_000.0) is None and live.end == 1_764_622_800.0  # UTC: files start on the hour
    with pytest.raises(ValueError):
        Rotation(tmp_path / "x.rrd", 0.0)


def test_rotated_files_in_order(tmp_path):
    for k in (0, 1, 2, 10):
        rotated_path(tmp_path / "a.rrd", k).write_bytes(b"")
    (tmp_path / "a.rrd").write_bytes(b"")
    (tmp_path / "a.2.0.rrd").write_bytes(b"")  # a restarted recorder's own rotation
    assert [f.name for f in rotated_files(tmp_path / "a.rrd")] == ["a.0.rrd", "a.1.rrd", "a.2.rrd", "a.10.rrd"]


@pytest.mark.slow
def test_run_with_rotation(tmp_path, deployment):
    from rerun.chunk import RrdReader

    p = subprocess.run(run_cmd(tmp_path, "patent-3d", deployment, "--speed", "max", "--rotate-s", "10"),
                       capture_output=True, text=True, timeout=180)
    assert p.returncode == 0, p.stderr[-3000:]
    doc = json.loads((tmp_path / "out.json").read_text())
    files = [tmp_path / f"out.{k}.rrd" for k in range(4)]  # fused times 0..30: windows [0,10) ... [30,40)
    assert doc["recordings"] == [str(f) for f in files] and not (tmp_path / "out.rrd").exists()
    assert doc["recording"] == str(files[0])  # a file there is, not the stem of their names
    fused_t: list[float] = []
    ids = set()
    for k, f in enumerate(files):
        verify(f)
        reader = RrdReader(f)
        assert [b.kind for b in reader.blueprints()] == ["blueprint"]
        (store,) = reader.recordings()
        ids.add(store.recording_id)
        assert {"/world", "/__properties"} <= static_paths(f)  # view coordinates, recording name
        rows = read_rrd(f)
        for site in ("radar2d", "angle"):  # every file draws the sites from its window's start
            assert rows[f"/world/sites/{site}"][0]["t"] == (0.0 if k == 0 else 10.0 * k)
        track = [r["t"] for r in rows.get("/world/tracks/centre/T1", [])]
        assert track and all(10.0 * k <= t < 10.0 * (k + 1) for t in track), (k, track)
        fused_t += track
    assert len(ids) == 1  # one recording, in four files
    assert sorted(fused_t) == doc["methods"]["SS"]["series"]["t"] and len(fused_t) == doc["methods"]["SS"]["n_updates"]


def test_rotate_s_must_be_positive(tmp_path):
    p = subprocess.run([sys.executable, "-m", "services.cli", "record", "--rrd", str(tmp_path / "x.rrd"),
                        "--rotate-s", "0"], capture_output=True, text=True, timeout=30)
    assert p.returncode == 2 and "--rotate-s" in p.stderr.splitlines()[-1]
