"""The hot standby fuser (services/leader.py): a live run with ``--standby``, kill -9 of
the leading fuser, and the fused output goes on from the standby under the same
identity, the same track ids, without a gap or a jump; the killed fuser, restarted,
rebuilds the leader's track from its picture and takes over in turn."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import threading
import time
from contextlib import contextmanager
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import psutil
import pytest
import zenoh
from scipy.stats import chi2

from _runs import child, run_cmd
from conftest import ROOT
from schemas import KeySpace, decode, to_estimate
from services.launcher import free_port
from services.node import ZenohOptions

pytestmark = pytest.mark.slow
LONG = "ZFUSION_LONG_TESTS"  # set: the long live tests run too
RECOVERY_S = 10.0  # the runs' recovery window: the sources' caches hold 2 x 10 s of stream, not 2 x 30 s
REBUILD_RECOVERY_S = 5.0  # the one-track rebuild test's: its sources' caches hold 2 x 5 s of stream


def _short_recovery(tmp_path: Path, scenario: str, recovery_s: float = RECOVERY_S) -> str:
    """A copy of the built-in ``scenario`` with ``recovery_s``: a run is past its
    sources' caches after ``2 x recovery_s`` of stream (20 s by default) instead of 60 s."""
    path = tmp_path / f"{scenario}.toml"
    text = (ROOT / "sensors_sim" / "scenarios" / f"{scenario}.toml").read_text(encoding="utf-8")
    path.write_text(f"recovery_s = {recovery_s}\n{text}", encoding="utf-8")
    return str(path)


class Fused:
    """Every fused estimate as it arrives, with its arrival time (monotonic)."""

    def __init__(self, deployment: str):
        self.deployment = deployment
        self.endpoint = f"tcp/127.0.0.1:{free_port()}"
        self.session = zenoh.open(ZenohOptions(listen=[self.endpoint]).to_config())
        self.got: list[tuple[float, object]] = []
        self._lock = threading.Lock()
        self._sub = self.session.declare_subscriber(KeySpace(deployment).fused("fuser"), self._on)

    def _on(self, sample) -> None:
        msg = decode(sample.payload.to_bytes())
        with self._lock:
            self.got.append((time.monotonic(), msg))

    def wait(self, predicate, proc, timeout: float = 90.0) -> None:
        deadline = time.monotonic() + timeout
        while not predicate():
            assert proc.poll() is None, "the run ended early"
            assert time.monotonic() < deadline, "timed out"
            time.sleep(0.02)

    def pictures(self, fuser: str = "fuser") -> dict:
        """Each answering process's picture of ``fuser`` (by Zenoh id): its replies' bytes."""
        out: dict[str, list[bytes]] = {}
        for reply in self.session.get(KeySpace(self.deployment).picture(fuser), timeout=1.0,
                                      consolidation=zenoh.ConsolidationMode.NONE):
            if reply.ok is not None:
                out.setdefault(str(reply.replier_id), []).append(reply.ok.payload.to_bytes())
        return out

    def close(self) -> None:
        self._sub.undeclare()
        self.session.close()


def test_kill_of_the_leading_fuser_is_no_gap_same_ids_no_jump(tmp_path, deployment):
    """Live patent-3d-orbit with ``--standby``: once the fuser has published for 5 s it is
    killed -9. The standby publishes within a second (no gap in ``fused`` longer than one
    update period plus 1 s), under the fuser's identity, with the same track ids, and its
    first estimate is where the last one before the kill, moved along its velocity, says
    within 3σ. The launcher restarts the killed fuser, which finds a leader and stands by
    (it says so), and the run ends with every process exit 0 but the killed one."""
    watch = Fused(deployment)  # (--for is a cap: the test ends the run once it has what it checks)
    proc = subprocess.Popen(run_cmd(tmp_path, "patent-3d-orbit", deployment, "--live", "--for", "120", "--standby",
                                    "--connect", watch.endpoint), stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)
    try:
        launcher = psutil.Process(proc.pid)
        fuser = child(launcher, "fuser", "fuser")
        child(launcher, "fuser", "fuser-standby")
        watch.wait(lambda: len(watch.got) >= 6, proc)
        killed_at = time.monotonic()
        fuser.kill()
        watch.wait(lambda: sum(a > killed_at + 0.5 for a, _ in watch.got) >= 6, proc, timeout=60)
        proc.send_signal(signal.SIGINT)  # ends a live run as --for would: in order, with its summary
        _, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGINT)
            proc.wait(30)
        watch.close()
    assert proc.returncode == 0, err[-3000:]
    doc = json.loads((tmp_path / "out.json").read_text())
    assert doc["exit_codes"]["fuser"] == -9 and doc["exit_codes"]["fuser-standby"] == 0, doc["exit_codes"]
    assert "fuser-standby: the leader is gone: taking over" in err and "fuser: an older member" in err, err[-3000:]
    arrivals = np.array([a for a, _ in watch.got])
    msgs = [m for _, m in watch.got]
    assert {m.src for m in msgs} == {"fuser"}  # one identity
    period = 1.0  # patent-3d-orbit's sensors scan once a second
    assert np.max(np.diff(arrivals)) <= period + 1.0, np.diff(arrivals)
    before = [to_estimate(m) for a, m in watch.got if a < killed_at]
    after = [to_estimate(m) for a, m in watch.got if a > killed_at + 0.5]
    assert {e.track for e in after} == {e.track for e in before}, ({e.track for e in before}, {e.track for e in after})
    last, first = before[-1], after[0]
    dt = first.t - last.t
    assert 0.0 < dt <= period + 1.0 + 1e-6
    predicted = last.x[:3] + dt * last.x[3:6]
    d2 = (first.x[:3] - predicted) @ np.linalg.solve(first.P[:3, :3] + last.P[:3, :3], first.x[:3] - predicted)
    assert d2 <= chi2.ppf(0.9973, 3), d2  # within 3σ (the 3-D equivalent)


def _continuous(before, after, period: float) -> None:
    """The first estimate of ``after`` is where the last of ``before``, moved along its
    velocity, says, within 3σ (the 3-D equivalent)."""
    last, first = to_estimate(before[-1]), to_estimate(after[0])
    dt = first.t - last.t
    assert 0.0 < dt <= period + 1.0 + 1e-6
    predicted = last.x[:3] + dt * last.x[3:6]
    d2 = (first.x[:3] - predicted) @ np.linalg.solve(first.P[:3, :3] + last.P[:3, :3], first.x[:3] - predicted)
    assert d2 <= chi2.ppf(0.9973, 3), d2


@contextmanager
def _standby_run(tmp_path, deployment: str, scenario: str, seconds: float):
    """A live run of ``scenario`` with ``--standby`` that a :class:`Fused` watch follows:
    yields ``run`` (``watch``, ``proc``: the launcher, ``launcher``: it as psutil sees it,
    ``first`` and ``standby``: its two fusers); on leaving, the run is stopped (SIGINT),
    must exit 0, and its stderr is ``run.err``."""
    watch = Fused(deployment)
    proc = subprocess.Popen(run_cmd(tmp_path, scenario, deployment, "--live", "--for", str(seconds), "--standby",
                                    "--connect", watch.endpoint), stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)
    run = SimpleNamespace(watch=watch, proc=proc, err="")
    try:
        run.launcher = psutil.Process(proc.pid)
        run.first = child(run.launcher, "fuser", "fuser")
        run.standby = child(run.launcher, "fuser", "fuser-standby")
        yield run
        proc.send_signal(signal.SIGINT)
        _, run.err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGINT)
            proc.wait(30)
        watch.close()
    assert proc.returncode == 0, run.err[-3000:]


def test_a_restarted_fuser_rebuilds_the_track_and_takes_over_in_turn(tmp_path, deployment):
    """Live patent-3d-orbit (SS) with ``--standby``: kill -9 of the leader; the standby
    leads; the launcher restarts the killed fuser, which joins mid-stream, rebuilds T1
    from the leader's picture and then holds the leader's very track: both processes'
    pictures, at the same time, are the same bytes (state, covariance, seq). Kill -9 of
    the new leader: the restarted fuser leads, under one identity, with the same track
    id, seq numbers going on, no gap in ``fused`` longer than one update period plus
    1 s, and each takeover within 3σ of the estimate before it. Without the rebuild the
    restarted fuser's picture differs (its track started afresh from the 10 s its
    sources' caches give back: the run's recovery window is 5 s) and the test fails."""
    scenario = _short_recovery(tmp_path, "patent-3d-orbit", REBUILD_RECOVERY_S)
    with _standby_run(tmp_path, deployment, scenario, 240) as run:
        watch, proc = run.watch, run.proc
        # Past the sensors' recovery caches (10 s of stream, 1 Hz) by 10 s: the restarted fuser
        # cannot get the track's whole history back from them, only rebuild it from the picture.
        watch.wait(lambda: len(watch.got) >= 2 * REBUILD_RECOVERY_S + 10, proc, timeout=150)
        kills = [time.monotonic()]
        run.first.kill()
        child(run.launcher, "fuser", "fuser", exclude=(run.first.pid,))  # restarted by the launcher
        watch.wait(lambda: sum(a > kills[0] + 0.5 for a, _ in watch.got) >= 6, proc, timeout=60)

        def same_pictures() -> bool:  # the leader's and the restarted fuser's, at one time
            answers = [sorted(r) for r in watch.pictures().values()]
            return len(answers) >= 2 and len(answers[0]) == 2 and all(a == answers[0] for a in answers)
        watch.wait(same_pictures, proc, timeout=60)
        kills.append(time.monotonic())
        run.standby.kill()
        watch.wait(lambda: sum(a > kills[1] + 0.5 for a, _ in watch.got) >= 6, proc, timeout=60)
    err = run.err
    doc = json.loads((tmp_path / "out.json").read_text())
    assert doc["exit_codes"]["fuser"] == -9 and doc["exit_codes"]["fuser-standby"] == -9, doc["exit_codes"]
    assert "fuser: rebuilt T1 from the leader's picture" in err, err[-3000:]
    arrivals = np.array([a for a, _ in watch.got])
    msgs = [m for _, m in watch.got]
    assert {m.src for m in msgs} == {"fuser"} and {m.body["track"] for m in msgs} == {"T1"}
    period = 1.0
    assert np.max(np.diff(arrivals)) <= period + 1.0, np.diff(arrivals)
    seqs = [m.seq for m in msgs]
    assert all(b > a for a, b in zip(seqs, seqs[1:])), seqs  # one numbering across both takeovers
    for killed_at in kills:
        _continuous([m for a, m in watch.got if a < killed_at], [m for a, m in watch.got if a > killed_at + 0.5],
                    period)


@pytest.mark.skipif(not os.environ.get(LONG), reason=f"about 80 s: run with {LONG}=1 (left out of the default suite "
                                                     f"for time)")
def test_many_targets_a_restarted_fuser_rebuilds_the_table_and_takes_over(tmp_path, deployment):
    """Live air-picture-live (SS, GNN, up to 20 aircraft crossing, clutter) with
    ``--standby``: the leader killed once the run is past the sources' caches, the
    restarted fuser rebuilds the table from the standby's picture (it joins as the younger
    member: it does not lead beside the standby), then the standby is killed: the
    restarted fuser leads with the ids of the frame before the kill (those of its tracks
    confirmed at its join; one still tentative then may be numbered anew), each within 3σ
    of where the last frame before the kill, moved along its velocity, put it, no gap in
    ``fused`` longer than one update period plus 1 s. The restarted fuser stood by from
    its start (it never led, so it never yielded)."""
    with _standby_run(tmp_path, deployment, _short_recovery(tmp_path, "air-picture-live"), 300) as run:
        watch, proc = run.watch, run.proc
        frames = lambda: len({m.t for _, m in watch.got})  # noqa: E731
        # Past the sources' caches: sized for max_alive = 20 aircraft at 1 Hz, they span
        # about 30 s of stream at the dozen that usually fly (a recovery window of 10 s).
        watch.wait(lambda: frames() >= 45, proc, timeout=200)
        run.first.kill()
        child(run.launcher, "fuser", "fuser", exclude=(run.first.pid,))
        at = frames()
        watch.wait(lambda: frames() >= at + 15, proc, timeout=90)  # the restarted fuser has joined, and confirmed
        kill = time.monotonic()
        run.standby.kill()
        watch.wait(lambda: len({m.t for a, m in watch.got if a > kill + 0.5}) >= 5, proc, timeout=90)
    err = run.err
    assert "fuser: rebuilt T" in err, err[-3000:]
    assert "fuser: an older member" in err and "yielded to" not in err, err[-3000:]  # it never led beside it
    arrivals = np.array([a for a, _ in watch.got])
    assert np.max(np.diff(arrivals)) <= 2.0, np.diff(arrivals)
    before = [m for a, m in watch.got if a < kill]
    after = [m for a, m in watch.got if a > kill + 0.5]
    last = {m.body["track"]: m for m in before if m.t == before[-1].t}
    t_next = min(m.t for m in after)
    nxt = {m.body["track"]: m for m in after if m.t == t_next}
    common = set(last) & set(nxt)
    assert len(common) >= len(last) - 1 and len(common) >= 3, (sorted(last), sorted(nxt))
    for tid in common:
        _continuous([last[tid]], [nxt[tid]], 1.0)
