"""Support for the tests of recordings: read an ``.rrd`` back from the file (never from
the recorder's own bookkeeping), verify it with ``rerun rrd verify``, feed a recorder like
its process does, and build the encoded messages a session carries."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pyarrow as pa

from fusion.links import Feedback, Gaussian, Init, LocalReport, PredictionReport
from fusion.types import Estimate, Measurement
from schemas import KeySpace, encode, encode_estimate, encode_measurement, tracker_id
from schemas.links import encode_downlink, encode_uplink
from services.node import RejectLog
from services.recording.recorder import Recorder
from services.recording.stream import open_recording


KEYS = KeySpace("rtest")


def rerun_exe() -> str:
    return shutil.which("rerun") or str(Path(sys.executable).with_name("rerun"))


def read_rrd(path: Path) -> dict[str, list[dict]]:
    """Temporal rows per entity path, in time order, each as {column: value} (sim_time in s)."""
    from rerun.chunk import RrdReader

    out: dict[str, list[dict]] = {}
    for chunk in RrdReader(path).stream():
        if chunk.is_static:
            continue
        rb = chunk.to_record_batch()
        cols = {n: rb.column(n).to_pylist() for n in rb.schema.names if ":" in n}  # archetype components
        ns = rb.column("sim_time").cast(pa.int64()).to_pylist()
        for i in range(rb.num_rows):
            row = {n: v[i] for n, v in cols.items()}
            row["t"] = ns[i] / 1e9
            out.setdefault(chunk.entity_path, []).append(row)
    for rows in out.values():
        rows.sort(key=lambda r: r["t"])  # stable: rows of one time keep their logged order
    return out


def row_times(path: Path, timeline: str = "utc") -> dict[str, list[float]]:
    """Per entity path, the times (s; POSIX seconds on a timestamp timeline) of its
    temporal rows on ``timeline``, sorted."""
    from rerun.chunk import RrdReader

    out: dict[str, list[float]] = {}
    for chunk in RrdReader(path).stream():
        if chunk.is_static or timeline not in chunk.timeline_names:
            continue
        ns = chunk.to_record_batch().column(timeline).cast(pa.int64()).to_pylist()
        out.setdefault(chunk.entity_path, []).extend(t / 1e9 for t in ns)
    for times in out.values():
        times.sort()
    return out


def static_paths(path: Path) -> set[str]:
    from rerun.chunk import RrdReader

    return {c.entity_path for c in RrdReader(path).stream() if c.is_static}


def verify(path: Path) -> None:
    v = subprocess.run([rerun_exe(), "rrd", "verify", str(path)], capture_output=True, text=True, timeout=60)
    assert v.returncode == 0, v.stderr[-2000:]


class Session:
    """A recorder writing to a file, fed like the process feeds it."""

    def __init__(self, tmp_path: Path, scenario=None, name: str = "r.rrd"):
        self.path = tmp_path / name
        self.rec, live = open_recording(str(self.path))
        assert not live
        self.reject = RejectLog("recorder")
        self.r = Recorder(self.rec, KEYS, self.reject, scenario)

    def put(self, key: str, data: bytes):
        return self.r.offer(key, data)

    def close(self) -> dict[str, list[dict]]:
        self.r.finish()
        self.rec.flush()
        self.rec.disconnect()
        verify(self.path)
        return read_rrd(self.path)


def truth_msg(k: int, t: float, target: str = "T1", x=None) -> bytes:
    x = [6000.0 + 100 * t, 8000.0, 2000.0, 100.0, 0, 0, 0, 0, 0] if x is None else x
    return encode("truth", "truth", k, t, target=target, x=x)


def meas_msg(sensor: str, kind: str, z, std, t: float, seq: int, site=(0.0, 0.0, 0.0)) -> bytes:
    m = Measurement(t, sensor, kind, np.array(z, float), np.array(std, float), np.array(site, float), seq)
    return encode_measurement(m, sensor)


def est_msg(t: float, x, P, method="SS", node="centre", track="T1", nis=None, dof=None, seq=1,
            src="fuser") -> bytes:
    return encode_estimate(Estimate(t, np.asarray(x, float), np.asarray(P, float), method, node, track, nis, dof),
                           src, seq)


def report_of(e: Estimate, seq: int, measurement: Measurement | None = None) -> LocalReport | PredictionReport:
    """A local tracker's report of its track's estimate ``e`` (its prior ``e`` itself), or
    with ``measurement`` its prediction and that measurement (two-stage)."""
    if measurement is not None:
        return PredictionReport(e.t, e.node, seq, e, measurement)
    return LocalReport(e.t, e.node, seq, e, Gaussian(e.x, e.P), np.zeros_like(e.P))


def uplink_msg(t: float, x, P, method="HNV", node="radar2d", track="T1", nis=None, dof=None, seq=1,
               measurement: Measurement | None = None) -> bytes:
    """A local tracker's report on ``local/trk-<node>`` (:func:`report_of`)."""
    e = Estimate(t, np.asarray(x, float), np.asarray(P, float), method, node, track, nis, dof)
    return encode_uplink(report_of(e, seq, measurement), tracker_id(node), seq)


def downlink_msg(t: float, x, P, method="HNV", node="radar2d", track="T1", seq=1, init=False) -> bytes:
    """The fuser's init or feedback to ``node``'s tracker on ``feedback/trk-<node>``."""
    e = Estimate(t, np.asarray(x, float), np.asarray(P, float), method, "centre", track)
    return encode_downlink(Init(node, e) if init else Feedback(node, e), "fuser", seq)


def status_msg(src: str, seq: int, t: float, state="running", role="sensor", counters=None, events=None) -> bytes:
    return encode("status", src, seq, t, state=state, role=role, counters=counters or {}, events=events or [])
