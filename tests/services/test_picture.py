"""The current picture: a real fuser process answers ``zfusion picture`` with the last
``fused`` message of each live track, and a recorder started mid-session draws those
tracks from its first row."""

from __future__ import annotations

import json
import math
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
import zenoh

from schemas import KeySpace, decode, encode, encode_measurement
from sensors_sim import load_scenario, sensor_events
from services.launcher import free_port
from services.node import ZenohOptions
from services.picture import Picture, Reports, query

from conftest import zfusion
from _recording import read_rrd, verify

pytestmark = pytest.mark.slow


class Feed:
    """The test's Zenoh peer: plays patent-3d's sensors by hand (watermarks never final,
    so the fuser runs on) and follows ``fused``."""

    def __init__(self, deployment: str):
        self.keys = KeySpace(deployment)
        self.endpoint = f"tcp/127.0.0.1:{free_port()}"
        self.session = zenoh.open(ZenohOptions(listen=[self.endpoint]).to_config())
        self.fused: dict[str, bytes] = {}  # track -> its last fused message
        self.n_fused = 0  # fused messages heard
        self.sent = 0  # messages played
        self.t = -1.0
        self.ready: set[str] = set()
        self.counters: dict[str, tuple[float, dict]] = {}  # process -> (when heard, its last status counters)
        self._subs = [self.session.declare_subscriber(self.keys.fused("fuser"), self._on_fused),
                      self.session.declare_subscriber(self.keys.all("status"), self._on_status)]
        sc = load_scenario("patent-3d")
        self.events = {s: [e for e in sensor_events(sc, s) if e.measurement is not None] for s in sc.sensors}
        self.pubs = {s: self.session.declare_publisher(self.keys.meas(s), congestion_control=zenoh.CongestionControl.BLOCK,
                                                       reliability=zenoh.Reliability.RELIABLE) for s in sc.sensors}
        self.wm = 0

    def _on_fused(self, sample) -> None:
        data = sample.payload.to_bytes()
        msg = decode(data)
        self.fused[msg.body["track"]] = data
        self.n_fused += 1
        self.t = max(self.t, msg.t)

    def _on_status(self, sample) -> None:
        msg = decode(sample.payload.to_bytes())
        if msg.body["state"] in ("ready", "running"):
            self.ready.add(msg.src)
        self.counters[msg.src] = (time.monotonic(), msg.body["counters"])

    def counter(self, src: str, name: str) -> float | None:
        """``name`` in ``src``'s last status (None before it has one)."""
        return self.counters.get(src, (-math.inf, {}))[1].get(name)

    def caught_up(self, src: str, since: float) -> bool:
        """``src`` said, in a status sent after ``since`` (plus a margin for delivery), that
        nothing waits in its inbox."""
        return self.counters.get(src, (-math.inf, {}))[0] > since + 0.3 and self.counter(src, "backlog") == 0

    def wait(self, cond, what: str, timeout: float = 30.0) -> None:
        deadline = time.monotonic() + timeout
        while not cond():
            assert time.monotonic() < deadline, what
            time.sleep(0.05)

    def play(self, t0: float, t1: float) -> None:
        """Every scan in [t0, t1], then a watermark at t1 from each sensor."""
        for s, evs in self.events.items():
            for e in evs:
                if t0 <= e.t <= t1:
                    self.pubs[s].put(encode_measurement(e.measurement, s))
                    self.sent += 1
            self.wm += 1
            self.pubs[s].put(encode("watermark", s, self.wm, t1, final=False))
            self.sent += 1
        self.wait(lambda: self.t >= math.floor(t1), f"fused output up to {t1} (last {self.t})")

    def close(self) -> None:
        for d in [*self._subs, *self.pubs.values()]:
            d.undeclare()
        self.session.close()


def _stop(p: subprocess.Popen) -> None:
    if p.poll() is None:
        p.send_signal(signal.SIGTERM)
        p.wait(20)


def test_picture_is_the_last_fused_message_and_a_late_recorder_starts_from_it(tmp_path, deployment):
    feed = Feed(deployment)
    fabric = ["--deployment", deployment, "--connect", feed.endpoint]
    # The feed pauses while the recorder starts: a long source timeout keeps the sensors alive.
    fuser = zfusion("fuser", "--scenario", "patent-3d", "--source-timeout", "120", *fabric)
    rec = None
    try:
        feed.wait(lambda: "fuser" in feed.ready, "the fuser came up")
        empty = subprocess.run([sys.executable, "-m", "services.cli", "picture", *fabric],
                               capture_output=True, text=True, timeout=30)
        assert empty.returncode == 0, empty.stderr
        assert json.loads(empty.stdout)["tracks"] == []  # nothing fused yet: an answer all the same
        feed.play(0.0, 10.0)
        # Nothing more is coming: the fuser has taken all that was played, and every estimate
        # it published has been heard (its status counts them after the step that made them).
        feed.wait(lambda: feed.counter("fuser", "received") == feed.sent
                  and feed.counter("fuser", "published") == feed.n_fused, "the fuser took all that was played")
        got = subprocess.run([sys.executable, "-m", "services.cli", "picture", *fabric],
                             capture_output=True, text=True, timeout=30)
        assert got.returncode == 0, got.stderr
        doc = json.loads(got.stdout)
        last = decode(feed.fused["T1"])
        assert doc["t"] == last.t == 10.0
        (track,) = doc["tracks"]
        assert track["id"] == "T1" and track["method"] == "SS" and track["seq"] == last.seq
        np.testing.assert_array_equal(track["x"], last.body["x"])
        np.testing.assert_array_equal(track["P"], last.body["P"])
        # The answer itself within 2 s (the CLI's wall time is mostly the interpreter's start,
        # seconds on a loaded machine): the same query from the test's own session.
        t0 = time.monotonic()
        again = query(feed.session, feed.keys, timeout=2.0)
        assert time.monotonic() - t0 < 2.0 and again == doc

        # A recorder started now: its first fused row is the picture's, before any new data.
        path = tmp_path / "late.rrd"
        rec = zfusion("record", "--rrd", str(path), *fabric, stderr=subprocess.DEVNULL)
        feed.wait(lambda: (feed.counter("recorder", "picture") or 0) >= 1, "the recorder took the picture")
        feed.play(10.5, 15.0)
        played = time.monotonic()
        feed.wait(lambda: feed.caught_up("recorder", played), "the recorder recorded what was played")
        _stop(rec)
        assert rec.returncode == 0
        verify(path)
        rows = [r["t"] for r in read_rrd(path)["/world/tracks/centre/T1"]]
        assert rows[0] == 10.0 and rows[1:] == [float(t) for t in range(11, 16)], rows
    finally:
        for p in (rec, fuser):
            if p is not None:
                _stop(p)
        feed.close()
    assert fuser.returncode == 0


def test_no_fuser_is_one_line_and_exit_1(deployment):
    port = free_port()
    p = subprocess.run([sys.executable, "-m", "services.cli", "picture", "--deployment", deployment,
                        "--connect", f"tcp/127.0.0.1:{port}", "--timeout", "0.5"], capture_output=True, text=True,
                       timeout=30)
    assert p.returncode == 1 and p.stdout == ""
    assert p.stderr.count("\n") == 1 and p.stderr.startswith("zfusion picture: no fuser answered"), p.stderr


def _est(t: float, track: str):
    from fusion.types import Estimate

    return Estimate(t, np.full(9, t), np.eye(9), "SS", "centre", track)


def test_a_track_leaves_the_picture_after_delete_misses_frames():
    pic = Picture("fuser", delete_misses=2)
    for t in (1.0, 2.0):
        pic.published(_est(t, "T1"), b"T1@%g" % t)
        pic.published(_est(t, "T2"), b"T2@%g" % t)
    for t in (3.0, 4.0):  # T2 is no longer reported
        pic.published(_est(t, "T1"), b"T1@%g" % t)
    assert pic.replies()[:-1] == [b"T1@4", b"T2@2"]  # missed frames 3 and 4, not yet seen as gone
    pic.published(_est(5.0, "T1"), b"T1@5")
    replies = pic.replies()
    assert replies[:-1] == [b"T1@5"]
    wm = decode(replies[-1])
    assert wm.kind == "watermark" and wm.t == 5.0 and wm.src == "fuser"


def test_reports_forget():
    r = Reports()
    r.report("a", 1.0, 3)
    assert r.forget("a") and not r.forget("a")
