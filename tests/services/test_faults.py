"""Faults during a run: kill -9 of a local tracker, the fuser and the recorder (the
launcher restarts them), and a restart of the Zenoh router the processes are clients
of. Each run completes, reports the outage in its summary, and its accuracy after the
recovery is back to that of the undisturbed run (the in-process evaluation)."""

from __future__ import annotations

import json
import math
import re
import signal
import socket
import subprocess
import sys
import threading
import time
from collections import Counter

import numpy as np
import psutil
import pyarrow as pa
import pytest
import zenoh

from _ingest_helpers import site_toml
from conftest import CROSSING
from schemas import decode
from sensors_sim import load_scenario
from _runs import FusedWatch, Hold, child, disturb, in_process, run_cmd
from services.evaluation import merged_measurements, run_method
from services.launcher import free_port
from services.plan import source_timeout
from services.scoring import GOSPA_CUTOFF, score_tracks_of, truth_function
from services.summary import method_summary, tracks_summary

pytestmark = [pytest.mark.slow, pytest.mark.spread]


def _outage(doc: dict, name: str, t_kill: float) -> dict:
    """The one outage of ``name``, killed once the fused output reached ``t_kill`` − 1 s.
    The launcher's times are its clock's (wall time × speed), which the fused output lags:
    by 16 s at speed 3 when the fuser was killed in CI's load (ci127), after a tracker's
    kill at 8 s had held the fuser's merge back."""
    (out,) = doc["outages"][name]
    assert out["exit_code"] == -signal.SIGKILL and doc["exit_codes"][name] == -signal.SIGKILL
    assert t_kill - 2 <= out["t_down"] <= t_kill + 20 and out["t_up"] > out["t_down"], out
    return out


def _recovered(got: dict, ref: dict, since: float, until: float = np.inf) -> None:
    """From ``since`` to ``until`` the position error is that of the undisturbed run."""
    err, ref_err = dict(zip(got["t"], got["rmse_pos"])), dict(zip(ref["t"], ref["rmse_pos"]))
    times = [s for s in ref_err if since <= s <= until]
    assert len(times) >= 6 and set(times) <= set(err), (since, until, sorted(err))
    rms = np.sqrt(np.mean([err[s] ** 2 for s in times]))
    assert rms < 1.5 * np.sqrt(np.mean([ref_err[s] ** 2 for s in times])), (rms, since, until)


def test_tracker_then_fuser_killed_in_the_feedback_topology(tmp_path, deployment):
    """Feedback (PHHNV): kill -9 of the angle sensor's tracker, later of the fuser. The
    fuser carries on with the radar's node while the tracker is away; the restarted
    tracker joins from the latest fused state, and accuracy is back. The restarted fuser
    knows nothing; both trackers drop their tracks and re-run the initialisation
    handshake, each at the first scan it sends after it has seen the new fuser (under
    load not the same scan: the other node's reports up to its own are refused as
    not joined). From there the output is the in-process run on each sensor's data from
    its node's join on. (Compared with the undisturbed run instead, the bound failed
    under load: the join scans move with the load, and the error after them with the
    manoeuvre at 48–60 s.)

    Each restart must be back while the sources still send: at speed 1.5 the tracker has
    20 s of scenario (13 s of wall time) to be back for the 6 s checked before the fuser's
    kill, and the fuser 24 s (16 s of wall time) to be back before the sources end. (At
    speed 3 with the fuser killed at 40 s, a restart under load once took 9 s of wall
    time, 26 s of scenario, and came back after the sources had ended: ci116.)"""
    doc, err = disturb(tmp_path, "patent-3d-60", deployment, 1.5,
                        [(4.0, "tracker", "angle"), (36.0, "fuser", "fuser")], "--topology", "feedback")
    trk = _outage(doc, "trk-angle", 4.0)
    fuser = _outage(doc, "fuser", 36.0)
    got = doc["methods"]["PHHNV"]["series"]
    t = np.array(got["t"])
    assert np.all(np.diff(t) > 0) and t[-1] == 60.0
    assert set(np.arange(0.0, 36.0)) <= set(t)  # an estimate every scan through the tracker's outage
    assert err.count("fuser restarted: tracks dropped, asking it for initial states again") == 2
    _recovered(got, in_process("patent-3d-60", "PHHNV")["series"], trk["t_up"] + 5, 35.0)
    rejoined = err[err.index("fuser killed (signal 9)"):]
    joins = {sensor: float(s) for sensor, s in
             re.findall(r"fuser: trk-(\w+) joined with its request at t = ([\d.]+) s", rejoined)}
    assert joins.keys() == {"radar2d", "angle"}, rejoined
    sc = load_scenario("patent-3d-60")
    ref = method_summary([run_method(sc, "PHHNV", measurements=[m for m in merged_measurements(sc)
                                                                if m.t >= joins[m.sensor]])], truth_function(sc))
    n = int(np.searchsorted(t, ref["series"]["t"][0]))
    assert fuser["t_down"] - 1 <= t[n] <= fuser["t_up"] + 5, (t, joins)
    assert list(t[n:]) == ref["series"]["t"]
    if "no init from fuser" not in rejoined:  # (a node that waited for its init longer than its
        # feedback timeout ran alone meanwhile, from its own measurement: no in-process run has that)
        np.testing.assert_allclose(got["rmse_pos"][n:], ref["series"]["rmse_pos"], rtol=0, atol=1e-9)


def test_tracker_stopped_across_a_fuser_restart_in_the_feedback_topology(tmp_path, deployment):
    """Feedback (PHHNV): kill -9 of the fuser, and the angle sensor's tracker stopped
    (SIGSTOP) from then until the restarted fuser's output reaches 26 s (at most 7 s:
    stopped past Zenoh's lease of 10 s, it lost its link to the sensor and what was sent
    meanwhile, and the run wedged in ci72 and ci79: the next test). The resumed
    tracker's request is for a scan the fuser has passed, refused as late; the node asks
    again with each next measurement, once the fuser's horizon (said again each second)
    shows its request passed over, and joins at the first scan the fuser has not passed,
    without running alone. The run ends by itself (it once wedged: the node waited for
    an init that could not come, its watermark holding the fuser's merge back), both
    nodes rejoin and the output goes on every scan. The error after the angle's join is
    not asserted: the fused track it joins was the 2D radar's alone, kilometres off in
    height, and what follows depends on where the load lets it join (at 43 s, quiet: 1830
    m, then 80 m at 48 s and 245 m at 60 s; at 48 s, with a core kept busy: 7719 m, 4964 m
    at 52 s, then growing again to 11.6 km at 56 s)."""
    doc, err = disturb(tmp_path, "patent-3d-60", deployment, 3.0,
                       [(8.0, "tracker", "angle"), (20.0, "fuser", "fuser")], "--topology", "feedback",
                       hold=Hold("tracker", "angle", until=26.0, max_s=7.0))
    fuser = _outage(doc, "fuser", 20.0)
    t = np.array(doc["methods"]["PHHNV"]["series"]["t"])
    rejoined = err[err.index("fuser killed (signal 9)"):]
    joins = {sensor: float(s) for sensor, s in
             re.findall(r"fuser: trk-(\w+) joined with its request at t = ([\d.]+) s", rejoined)}
    assert joins.keys() == {"radar2d", "angle"}, rejoined
    assert "trk-angle: no init from fuser" not in rejoined, rejoined  # it asked again instead
    assert "did not end" not in err and "killed at the end" not in err, err  # each node ended by itself
    assert np.all(np.diff(t) > 0) and t[-1] == 60.0
    assert set(np.arange(joins["radar2d"] + 2, 61.0)) <= set(t), (t, joins)  # every scan after the restart
    assert joins["angle"] <= fuser["t_up"] + 30, (joins, fuser)


def test_a_tracker_stopped_past_the_lease_while_its_sensor_ended_ends_by_itself(tmp_path, deployment):
    """Feedback (PHHNV): the angle sensor's tracker stopped (SIGSTOP) at 20 s until the
    angle sensor has ended (13 s of wall time at speed 3) and for at least 12 s, past
    Zenoh's lease (10 s): the links of the stopped process are closed, and the rest of
    the angle sensor's stream, its end too, is lost to it. Resumed, the tracker sees the sensor gone, takes its
    stream as ended at its last data and ends; the fuser, which went on with the radar
    alone, fuses every scan to 60 s. (Before, the resumed tracker waited for the end
    that could not come: the launcher stopped it 10 s after the fuser was done, and with
    a restarted fuser waiting for it — ci72, ci79 — the run wedged at 43 s until the
    launcher's end-of-sources watch stopped everything.)"""
    doc, err = disturb(tmp_path, "patent-3d-60", deployment, 3.0, [], "--topology", "feedback",
                       hold=Hold("tracker", "angle", at=20.0, exit_of=("sensor", "angle"), min_s=12.0))
    ended = re.findall(r"trk-angle: angle gone for more than [\d.]+ s and the end of its stream not heard: "
                       r"taken as ended at t = ([\d.]+) s", err)
    assert len(ended) == 1 and 20.0 <= float(ended[0]) < 60.0, err
    assert "did not end" not in err and "killed at the end" not in err and "processed nothing" not in err, err
    assert doc["exit_codes"]["trk-angle"] == 0, doc["exit_codes"]
    t = np.array(doc["methods"]["PHHNV"]["series"]["t"])
    assert np.all(np.diff(t) > 0) and set(np.arange(0.0, 61.0)) <= set(t), t  # every scan, with the radar alone


def test_fuser_killed_with_many_targets_in_the_feedback_topology(tmp_path, deployment):
    """Three crossing aircraft in clutter, feedback (PHHNV): kill -9 of the fuser at 8 s,
    before A and B cross (30 s). The restarted fuser's centre knows none of the nodes'
    local tracks: the nodes drop them when they see the new fuser and send their plots
    up as requests from the scan they join with; from there the air picture is the
    in-process run's on each sensor's data from its node's join on, GOSPA to 1e-9 —
    a cold start, whatever scan the load makes it. (With the nodes keeping their tracks,
    the defect this guards — ``MultiTrackNode.centre_restarted`` not dropping them —
    their reports of local ids the new centre never named are dropped and it differs.)

    How soon every aircraft is held again is then the cold start's, not the restart's,
    and it depends on the scan (in-process cold starts, both nodes from one scan: from
    6 s held again at 8 s, 7 → 10, 8 → 29, 9 → 16, 10 → 16, 11–13 → 29, 14 → 17; the
    undisturbed run from 7 s). Joined at 8 s (ci85, and the project's CI on 348df30),
    A's radar plot paired with B's angle ray at 13–14 s, where A and B are within 0.8°
    of each other seen from the angle sensor and that ray meets A's range sphere 0.5σ
    off A's radar azimuth, 1.4 km above A; B's radar plot with A's ray likewise. Two
    sensors cannot tell the two pairings apart while the aircraft stay aligned from
    the angle sensor (10–50 s), and the swapped tracks lived to 41 s: a limit of
    two-sensor initiation, not of the restart (the bound of 14 s from the return this
    test once asserted held only for the scans where the pairing came out right)."""

    path = CROSSING
    # speed 2: the picture is compared with the cold start from the joins, wherever the load puts them (in
    # process, cold starts joined at any scan from 8 to 40 s hold every aircraft at 60 s)
    doc, err = disturb(tmp_path, str(path), deployment, 2.0, [(8.0, "fuser", "fuser")], "--topology", "feedback")
    fuser = _outage(doc, "fuser", 8.0)
    assert err.count("fuser restarted: tracks dropped, asking it for initial states again") == 2
    rejoined = err[err.index("fuser killed (signal 9)"):]
    joins = {sensor: float(s) for sensor, s in
             re.findall(r"fuser: trk-(\w+) joined with its request at t = ([\d.]+) s", rejoined)}
    assert joins.keys() == {"radar", "angle"}, rejoined
    assert all(fuser["t_down"] - 1 <= s <= fuser["t_up"] + 5 for s in joins.values()), (joins, fuser)
    got = doc["methods"]["PHHNV"]
    t, gospa = np.array(got["series"]["t"]), np.array(got["series"]["gospa"])
    assert np.all(np.diff(t) > 0) and t[-1] == 60.0
    sc = load_scenario(path)
    cold = [m for m in merged_measurements(sc) if m.t >= joins[m.sensor]]
    ref = tracks_summary([score_tracks_of(sc, run_method(sc, "PHHNV", measurements=cold))])["series"]
    assert list(t) == ref["t"]
    since = t >= min(joins.values())  # before: the killed fuser's picture, then none
    np.testing.assert_allclose(gospa[since], np.array(ref["gospa"])[since], rtol=0, atol=1e-9)
    # a real air picture after the restart: every aircraft held at the end, where one
    # missed or false target alone costs c/√2 (p = 2)
    assert gospa[-1] < GOSPA_CUTOFF / np.sqrt(2), gospa[-20:]


def test_no_restart_ends_the_run_after_the_sources(tmp_path, deployment):
    """``--no-restart``: a killed fuser stays dead. The run still ends (END_GRACE after
    the last source finished; measured 28 s for the test, 57 s before the recorder was
    stopped as below), exits 0 with the summary of what was fused before the kill, and
    reports the outage as never over."""
    from services.launcher import END_GRACE

    killed: list[float] = []
    duration = 16.0  # the sources go on for 6 s of scenario time after the kill
    doc, err = disturb(tmp_path, "patent-3d", deployment, 3.0, [(10.0, "fuser", "fuser")], "--no-restart",
                        "--duration-s", str(duration), killed_at=killed)
    # from the kill: the sources' last 6 scenario s (2 s), the grace, the stop; timed from the kill, not
    # the start, which a loaded machine can stretch past 30 s
    assert time.monotonic() - killed[0] < (duration - 10.0) / 3.0 + END_GRACE + 15.0
    (out,) = doc["outages"]["fuser"]
    assert out["exit_code"] == -signal.SIGKILL and out["t_up"] is None and 8.0 <= out["t_down"] <= 18.0, out
    assert doc["exit_codes"]["fuser"] == -signal.SIGKILL
    assert "fuser killed (signal 9)" in err and "restarting it" not in err and "is back" not in err
    t = doc["methods"]["SS"]["series"]["t"]
    assert 8.0 <= t[-1] <= out["t_down"] + 1.0 and t == sorted(t)  # nothing fused after the kill
    # the recorder hears no "done" from the dead fuser: it is stopped once it has recorded
    # everything (before, the launcher waited 30 s more for it), and its file is whole
    from _recording import verify

    verify(tmp_path / "out.rrd")


@pytest.mark.parametrize("wakes", [False, True], ids=["stopped-for-good", "woken-at-the-end"])
def test_a_tracker_stopped_until_the_fuser_is_done_does_not_hold_the_run(tmp_path, deployment, wakes):
    """A local tracker stopped (SIGSTOP) at 10 s of a 16 s feedback run; the fuser declares
    it dead and finishes on the other node.

    - Stopped for good: neither its "done" nor its exit comes. The launcher gives it
      END_WAIT after the fuser is done, stops it (killed: a stopped process takes no
      SIGTERM), stops the recorder once its backlog is empty, names the tracker, and exits
      0 with the summary. (It waited for ever: the recorder, waiting for the tracker's
      "done", recorded statuses each second, so it never looked stalled, and the wait did
      not heed SIGINT.)
    - Woken once the fuser is done: it holds its sensor's measurements from 10 s on and
      the fuser's feedback up to the end, applied first; it drops what the fuser passed
      (counted as ``stale``) and ends, by itself or stopped by the launcher. (It died on
      'cannot predict backwards', and the run then waited for ever as above.)"""
    from services.launcher import END_WAIT, STOP_GRACE

    watch = FusedWatch(deployment)
    proc = subprocess.Popen(run_cmd(tmp_path, "patent-3d-60", deployment, "--speed", "3", "--duration-s", "16",
                                    "--topology", "feedback", "--connect", watch.endpoint),
                            stdout=subprocess.DEVNULL, stderr=(tmp_path / "run.log").open("w"))
    try:
        stuck = child(psutil.Process(proc.pid), "tracker", "angle")
        watch.wait_until(10.0, proc)
        stuck.suspend()
        watch.wait_until(16.0, proc)  # the fuser went on without it, to the end
        if wakes:
            stuck.resume()
        ended_at = time.monotonic()
        assert proc.wait(END_WAIT + STOP_GRACE + 20.0) == 0, (tmp_path / "run.log").read_text()
        assert time.monotonic() - ended_at < END_WAIT + STOP_GRACE + 15.0
    finally:
        if proc.poll() is None:
            proc.kill()
        watch.close()
    err = (tmp_path / "run.log").read_text()
    assert "Traceback" not in err and "ended with errors" not in err, err
    assert not psutil.pid_exists(stuck.pid) or stuck.status() == psutil.STATUS_ZOMBIE
    doc = json.loads((tmp_path / "out.json").read_text())
    assert doc["methods"]["PHHNV"]["series"]["t"][-1] == 16.0
    if not wakes:
        assert "trk-angle did not end" in err and "killed at the end: trk-angle" in err, err
        assert doc["exit_codes"]["trk-angle"] == -signal.SIGKILL
    else:
        assert doc["exit_codes"]["trk-angle"] == 0 and "killed at the end" not in err, err


def test_recorder_then_fuser_killed_centralised(tmp_path, deployment):
    """Centralised (SS): kill -9 of the recorder, later of the fuser. The recorder's loss
    changes nothing fused and its restart records the rest of the run in a second,
    verified file; the restarted fuser joins mid-stream (it does not wait for t = 0 data)
    and starts from the first scan it has heard whole: from there its estimates are the
    in-process evaluation's started at that scan. (It started from what it held: when that
    was the radar's plot of a scan without the angle sensor's, a track with no measured
    elevation, e.g. 31.6 m RMSE from t = 37 s against 17.7 m undisturbed.)"""
    from _recording import read_rrd, verify

    # At speed 1.5 the restarted fuser has 23 s of wall time to be back for the last 11 s
    # of scenario this checks: in ci61, at speed 4 with a core kept busy, it took 14 s and
    # came back after its sources had ended (the run then never ended, all of them dead
    # and none final; now the launcher ends such a run: the test below).
    doc, err = disturb(tmp_path, "patent-3d-60", deployment, 1.5,
                        [(6.0, "record", "recorder"), (15.0, "fuser", "fuser")])
    rec = _outage(doc, "recorder", 6.0)
    fuser = _outage(doc, "fuser", 15.0)
    got = doc["methods"]["SS"]["series"]
    ref = in_process("patent-3d-60", "SS")["series"]
    # Up to the fuser's death the output is the undisturbed one, recorder kill or not;
    # then a gap (the restarted fuser's first estimate is at its first scan) and one
    # estimate per scan to the end.
    t = got["t"]
    n = next(i for i in range(1, len(t)) if t[i] - t[i - 1] > 1.0)
    assert t[:n] == ref["t"][:n] and n >= 14
    np.testing.assert_allclose(got["rmse_pos"][:n], ref["rmse_pos"][:n], rtol=0, atol=1e-9)
    after = t[n:]
    assert fuser["t_down"] - 1 <= after[0] <= fuser["t_up"] + 3 and after == list(np.arange(after[0], 61.0))
    assert err.count("fuser: input starts at t = ") == 2 and f"fuser: input starts at t = {after[0]:g} s" in err
    assert "fuser: joined radar2d's stream mid-way" in err and "fuser: joined angle's stream mid-way" in err
    sc = load_scenario("patent-3d-60")
    restarted = method_summary([run_method(sc, "SS", measurements=[m for m in merged_measurements(sc)
                                                                    if m.t >= after[0]])], truth_function(sc))
    assert restarted["series"]["t"] == after
    np.testing.assert_allclose(got["rmse_pos"][n:], restarted["series"]["rmse_pos"], rtol=0, atol=1e-9)
    _recovered(got, ref, after[0] + 5)
    # The recording: the first file up to the kill, the rest of the run in a second one.
    first, second = map(type(tmp_path), doc["recordings"])
    assert first == tmp_path / "out.rrd" and second == tmp_path / "out.2.rrd"
    verify(second)
    tracks = [r["t"] for r in read_rrd(second)["/world/tracks/centre/T1"]]
    assert tracks and rec["t_up"] - 1 <= min(tracks) and max(tracks) == 60.0


def test_a_fuser_that_never_hears_its_sources_end_is_stopped(tmp_path, deployment):
    """A fuser held (SIGSTOP) until every source has ended, then killed: its restart hears
    no source at all, each one dead and none final, and would wait for ever for their
    final watermarks (so would one whose sources' last words went with a router outage).
    The launcher stops it once the sources have all ended and the fuser's statuses show
    no progress for the source timeout and END_STALL s more, says so, and the run ends
    with what was fused."""
    from services.launcher import END_STALL

    stall = source_timeout(load_scenario("patent-3d"), "4") + END_STALL
    watch = FusedWatch(deployment)
    log = tmp_path / "run.log"
    proc = subprocess.Popen(run_cmd(tmp_path, "patent-3d", deployment, "--speed", "4", "--connect", watch.endpoint),
                            stdout=subprocess.DEVNULL, stderr=log.open("w"))
    try:
        launcher = psutil.Process(proc.pid)
        fuser = child(launcher, "fuser", "fuser")
        watch.wait_until(10.0, proc)
        fuser.suspend()
        sensors = [c for c in launcher.children()
                   if (cmd := c.cmdline())[cmd.index("services.cli") + 1] == "sensor"]
        assert sensors
        _, alive = psutil.wait_procs(sensors, timeout=60)
        assert not alive, "the sources did not end"
        ended = time.monotonic()
        fuser.kill()
        proc.wait(stall + 60)
        took = time.monotonic() - ended
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGINT)
            proc.wait(30)
        watch.close()
    err = log.read_text()
    assert proc.returncode == 0, err[-3000:]
    assert re.search(r"every source ended \S+ s ago and the fuser has processed nothing since .*: stopping fuser", err)
    assert took > stall
    doc = json.loads((tmp_path / "out.json").read_text())
    (out,) = doc["outages"]["fuser"]
    assert out["t_up"] is not None
    t = doc["methods"]["SS"]["series"]["t"]
    assert 10.0 <= t[-1] < 30.0  # what was fused before the hold, scored; nothing after it


def _client_config(tmp_path, ep: str):
    """A Zenoh config file making a process a client of the router at ``ep`` only, which
    retries a lost router every 0.2-0.5 s (Zenoh's default backs off to tries 1, 3, 7 and
    11 s after the loss: a new router a few seconds slow to start would cost 4 s more)."""
    config = tmp_path / "client.json5"
    retry = {"period_init_ms": 200, "period_max_ms": 500, "period_increase_factor": 2}
    config.write_text(json.dumps({"mode": "client", "connect": {"endpoints": [ep], "retry": retry},
                                  "scouting": {"multicast": {"enabled": False}}}))
    return config


# ``zfusion router`` in a process that has imported what it runs, and starts it on a line
# of its standard input: a restart's outage is then the test's sleep, not the sleep plus
# an interpreter's start (seconds on a loaded CI host: in ci50 the outage outlasted the
# scenario's sources, whose last words were lost with it).
_ROUTER_ON_CUE = ("import sys\nimport services.router\nfrom services.cli import main\nprint('imported', flush=True)\n"
                  "sys.stdin.readline()\nsys.exit(main(['router', '--listen', sys.argv[1]]))")


def _router_on_cue(ep: str) -> subprocess.Popen:
    """A router for ``ep`` ready to start (:data:`_ROUTER_ON_CUE`): write a line to its stdin."""
    r = subprocess.Popen([sys.executable, "-c", _ROUTER_ON_CUE, ep], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                         stderr=subprocess.DEVNULL, text=True)
    assert r.stdout.readline().strip() == "imported"
    return r


def _start(r: subprocess.Popen) -> subprocess.Popen:
    r.stdin.write("go\n")
    r.stdin.flush()
    assert "listening" in r.stdout.readline()
    return r


def _router(ep: str) -> subprocess.Popen:
    """``zfusion router`` listening on ``ep``, once it says so."""
    return _start(_router_on_cue(ep))


# The router's outage: the fault injected, not a wait for a condition. Longer than the
# fuser's source timeout (patent-3d at speed 1 or 2: 3 s), so that every sensor is
# declared dead whatever the machine's speed: a router that starts in 0.3 s (the light
# command line) and sessions that reconnect at once would otherwise end the outage
# before the timeout on a quiet machine, and on a loaded one after it.
OUTAGE_S = source_timeout(load_scenario("patent-3d"), "1") + 1.5


def _restarted(router: subprocess.Popen, ep: str) -> subprocess.Popen:
    """kill -9 of ``router``, and a new one on the same endpoint :data:`OUTAGE_S` later."""
    new = _router_on_cue(ep)
    try:
        router.kill()
        router.wait()
        time.sleep(OUTAGE_S)
        return _start(new)
    except BaseException:
        new.kill()
        new.wait()
        raise


def _stop(proc: subprocess.Popen, watch: FusedWatch, routers: list[subprocess.Popen]) -> None:
    """Whatever is still running of a router test: the run (SIGINT), the watch, the routers."""
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
        proc.wait(30)
    watch.close()
    for r in routers:
        if r.poll() is None:
            r.send_signal(signal.SIGINT)
            try:
                r.wait(10)
            finally:  # one that does not stop fails the test, and is not left running
                if r.poll() is None:
                    r.kill()
                    r.wait()


def _router_restarted_at_7_s(tmp_path, deployment, *extra: str) -> tuple[dict, str]:
    """patent-3d at speed 1, every process a client of one router, killed -9 once the
    fused output reaches 7 s and restarted on the same port: the summary and stderr."""
    ep = f"tcp/127.0.0.1:{free_port()}"
    config = _client_config(tmp_path, ep)
    routers = [_router(ep)]
    watch = FusedWatch(deployment, connect=ep)
    proc = subprocess.Popen(run_cmd(tmp_path, "patent-3d", deployment, "--speed", "1", "--zenoh-config", str(config),
                                    *extra), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        launcher = psutil.Process(proc.pid)
        assert "--zenoh-config" in child(launcher, "fuser", "fuser").cmdline()  # children are clients too
        watch.wait_until(7.0, proc)
        routers.append(_restarted(routers[0], ep))
        _, err = proc.communicate(timeout=120)
    finally:
        _stop(proc, watch, routers)
    assert proc.returncode == 0, err[-3000:]
    return json.loads((tmp_path / "out.json").read_text()), err


def test_router_restart_in_client_mode(tmp_path, deployment):
    """Every process a Zenoh client of one router; kill -9 of the router mid-run and a
    new one on the same port seconds later. The sessions reconnect by themselves (zenoh
    retries the connect endpoint); what was published during the outage is lost, the
    fuser declares every sensor dead (reported) but does not take that for the end of
    the scenario, and fuses the measurements sent after the reconnection. At speed 1: in
    ci62, at speed 2 with a core kept busy, the fused output came back 6.5 s of wall time
    after the router did, at t = 29 s of the 30."""
    doc, _ = _router_restarted_at_7_s(tmp_path, deployment)
    assert doc["outages"] == {} and set(doc["exit_codes"].values()) == {0}
    t = doc["methods"]["SS"]["series"]["t"]
    n = next(i for i in range(1, len(t)) if t[i] - t[i - 1] > 1.0)
    before, after = t[:n], t[n:]
    assert before == list(np.arange(0.0, before[-1] + 1)) and before[-1] >= 6.0
    # Lost: the scans published while the router was away. Fused: every scan after reconnection.
    assert after == list(np.arange(after[0], 31.0)) and after[0] <= 26.0, t
    for sensor in ("radar2d", "angle"):  # the outage is longer than the source timeout
        (gap,) = doc["sources"][sensor]["dead_intervals"]
        assert before[-1] - 1 <= gap[0] <= before[-1] + 1, (gap, t)


def test_router_restart_under_trackers_ends_no_tracker(tmp_path, deployment):
    """The router restart of the test above under local trackers (``--topology
    distributed``): every liveliness token vanishes with the router, the trackers' sensors'
    too, for longer than their feedback timeout (3 s). A tracker takes its sensor for gone
    (and its stream for ended) only while it sees other processes' tokens, so none ends:
    every one exits 0 after the scenario's end, and the fused output comes back after the
    reconnection and goes on to 30 s. (Judging its sensor's token alone, both trackers
    took their streams as ended at t = 8 s, during the outage.)"""
    doc, err = _router_restarted_at_7_s(tmp_path, deployment, "--topology", "distributed")
    assert "gone for more than" not in err, err
    assert set(doc["exit_codes"].values()) == {0}, doc["exit_codes"]
    t = doc["methods"]["HNV"]["series"]["t"]
    n = next(i for i in range(1, len(t)) if t[i] - t[i - 1] > 1.0)
    # back, and to the end; a scan may still be lost right after (the clients reconnect one
    # by one: a sensor's scan sent before its tracker is back is lost; 13 s of 12–30 once)
    assert t[n] <= 26.0 and t[-1] == 30.0 and len(t[n:]) >= 31.0 - t[n] - 2, t


def test_router_restart_in_a_live_session_loses_nothing(tmp_path, deployment):
    """A live session, every process a Zenoh client of one router; kill -9 of the router
    once the fuser is fusing, and a new one on the same port :data:`OUTAGE_S` later. The sensors'
    publishers keep the last seconds of their streams and give them back on
    reconnection: every scan reaches the fuser (a fused update every second of the run,
    no gap), counted as ``recovered`` per sensor (none ``missed``, none refused). (Every
    sensor was cut off at once, so nothing was released meanwhile: the recovered scans
    come in order.)"""
    ep = f"tcp/127.0.0.1:{free_port()}"
    config = _client_config(tmp_path, ep)
    routers = [_router(ep)]
    watch = FusedWatch(deployment, connect=ep)
    proc = subprocess.Popen(run_cmd(tmp_path, "patent-3d", deployment, "--live", "--for", "30", "--oosm-window", "30",
                                    "--zenoh-config", str(config)),
                            stdout=subprocess.DEVNULL, stderr=(tmp_path / "run.log").open("w"))
    try:
        watch.wait_until(1e9, proc, timeout=90)  # fusing (a UTC time)
        watch.wait_until(watch.t + 4.0, proc)
        routers.append(_restarted(routers[0], ep))
        proc.wait(timeout=150)
    finally:
        _stop(proc, watch, routers)
    err = (tmp_path / "run.log").read_text()
    assert proc.returncode == 0, err[-3000:]
    doc = json.loads((tmp_path / "out.json").read_text())
    t = np.array(doc["methods"]["SS"]["series"]["t"]) - doc["epoch_utc"]
    assert len(t) >= 25 and np.all(np.diff(t) <= 1.0 + 1e-6), t  # no scan lost
    for sensor in ("radar2d", "angle"):
        src = doc["sources"][sensor]
        # The router is away for OUTAGE_S (4.5 s): at least two scans of each 1 Hz sensor are
        # published meanwhile, well within the publishers' 30 s cache.
        assert src["recovered"] >= 2 and src["missed"] == 0 and src["stale"] == 0 and src["rejected"] == 0, src
        assert src["dead_intervals"], src  # cut off for longer than the source timeout
    # The recorder, cut off too, got back what the sensors sent meanwhile (a plain subscriber
    # loses those scans), every fused estimate the fuser published, and says so in its counters.
    rows = _utc_rows(tmp_path / "out.rrd")
    for sensor in ("radar2d", "angle"):
        scans = sorted({r["t"] for p, rs in rows.items() if p.startswith(f"/world/meas/{sensor}") for r in rs})
        assert len(scans) >= 25 and np.all(np.diff(scans) <= 1.0 + 1e-3), (sensor, np.diff(scans))
    recorded = {round(r["t"], 3) for p, rs in rows.items() if p.startswith("/world/tracks/centre/")
                and p.count("/") == 4 for r in rs}
    fused = {round(s, 3) for s in doc["methods"]["SS"]["series"]["t"]}
    assert fused <= recorded, sorted(fused - recorded)
    counter = {name: max(r["Scalars:scalars"][0] for r in rows[f"/status/recorder/counters/{name}"])
               for name in ("recovered", "missed")}
    assert counter["recovered"] >= 1 and counter["missed"] == 0, counter


def test_router_restart_under_gateways_loses_no_reading(tmp_path, deployment):
    """Three ``zfusion ingest jsonl`` gateways (UDP) and a live DF fuser, all clients of
    one router; a device feeds each gateway a bearing every 0.2 s throughout; kill -9 of
    the router and a new one :data:`OUTAGE_S` later. The gateways publish on the
    advanced publisher with a recovery cache (as emulated sensors do): what they published
    while the router was away reaches the fuser on reconnection, counted ``recovered``,
    none ``missed``, and every reading the gateways published is taken by the fuser or
    counted (before: plain publishers, 36 bearings of a 6 s outage lost, ``recovered`` and
    ``missed`` both 0)."""
    ep = f"tcp/127.0.0.1:{free_port()}"
    config = _client_config(tmp_path, ep)
    stations = {"df1": [0.0, 0.0, 0.0], "df2": [10_000.0, 0.0, 0.0], "df3": [0.0, 10_000.0, 0.0]}
    site = tmp_path / "site.toml"
    site.write_text(site_toml({sid: {"pos_m": pos} for sid, pos in stations.items()}))
    ports = {sid: free_port() for sid in stations}
    common = ["--site", str(site), "--deployment", deployment, "--zenoh-config", str(config)]
    routers = [_router(ep)]
    # The source timeout OUTAGE_S is longer than (3 s): the stations are declared dead, and
    # what they sent meanwhile, given back on reconnection, is counted as recovered.
    procs = {"fuser": subprocess.Popen([sys.executable, "-m", "services.cli", "fuser", "--method", "EKF", *common,
                                        "--source-timeout", "3"],
                                       stderr=subprocess.PIPE, text=True)}
    for sid, port in ports.items():
        procs[sid] = subprocess.Popen([sys.executable, "-m", "services.cli", "ingest", "jsonl", "--id", sid,
                                       "--input", f"udp://127.0.0.1:{port}", *common],
                                      stderr=subprocess.PIPE, text=True)
    statuses: dict[str, dict] = {}
    session = zenoh.open(zenoh.Config.from_file(str(config)))
    sub = session.declare_subscriber(f"zf/{deployment}/status/*",
                                     lambda smp: statuses.__setitem__(str(smp.key_expr).split("/")[-1], decode(
                                         smp.payload.to_bytes()).body))
    feeding = threading.Event()
    sent = Counter()

    def feed() -> None:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            while not feeding.wait(0.2):
                t = time.time()
                for sid, pos in stations.items():
                    az = math.degrees(math.atan2(5000.0 - pos[0], 5000.0 - pos[1])) % 360
                    s.sendto(json.dumps({"t": t, "kind": "bearing", "az_deg": az}).encode(), ("127.0.0.1", ports[sid]))
                    sent[sid] += 1

    feeder = threading.Thread(target=feed, daemon=True)

    def wait(pred, timeout: float) -> bool:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline and all(p.poll() is None for p in procs.values()):
            if pred():
                return True
            time.sleep(0.05)
        return False

    def counters(pid: str) -> dict:
        return statuses.get(pid, {}).get("counters", {})

    def exited() -> dict:  # a process that stopped ends every wait: which, and how
        return {n: (p.returncode, p.stderr.read()[-2000:]) for n, p in procs.items() if p.poll() is not None}

    try:
        assert wait(lambda: all(pid in statuses for pid in procs), 60), (statuses.keys(), exited())
        feeder.start()
        assert wait(lambda: counters("fuser").get("processed", 0) >= 15, 60), (counters("fuser"), exited())
        routers.append(_restarted(routers[0], ep))
        assert wait(lambda: all(statuses.get("fuser", {}).get("sources", {}).get(sid, {}).get("recovered", 0) > 0
                                for sid in stations), 60), (statuses.get("fuser", {}).get("sources"), exited())
        feeding.set()
        feeder.join()

        def accounted() -> bool:  # every reading published is taken or counted, nothing still held
            # Every reading the device sent reached its gateway (loopback UDP at 5 Hz loses nothing) ...
            if any(counters(sid).get("published", 0) + counters(sid).get("rejected", 0) != sent[sid]
                   for sid in stations):
                return False
            published = sum(counters(sid).get("published", 0) for sid in stations)
            src = statuses["fuser"]["sources"]
            counted = sum(src[sid]["rejected"] + src[sid]["missed"] for sid in stations)
            return published > 0 and counters("fuser").get("processed", 0) + counted == published

        assert wait(accounted, 60), (statuses["fuser"], {sid: counters(sid) for sid in stations}, exited())
    finally:
        feeding.set()
        sub.undeclare()
        session.close()
        errs = {}
        for name, p in procs.items():
            if p.poll() is None:
                p.send_signal(signal.SIGTERM)
        for name, p in procs.items():
            _, errs[name] = p.communicate(timeout=20)
        for r in routers:
            if r.poll() is None:
                r.send_signal(signal.SIGINT)
                r.wait(10)
    assert all(p.returncode == 0 and "Traceback" not in errs[n] for n, p in procs.items()), errs
    src = statuses["fuser"]["sources"]
    for sid in stations:
        assert src[sid]["recovered"] >= 1 and src[sid]["missed"] == 0, src[sid]


def _utc_rows(path) -> dict[str, list[dict]]:
    """A live recording's temporal rows per entity path, each {component: value, "t": UTC s}."""
    from rerun.chunk import RrdReader

    out: dict[str, list[dict]] = {}
    for chunk in RrdReader(path).stream():
        if chunk.is_static:
            continue
        rb = chunk.to_record_batch()
        if "utc" not in rb.schema.names:
            continue
        cols = {n: rb.column(n).to_pylist() for n in rb.schema.names if ":" in n}
        ns = rb.column("utc").cast(pa.int64()).to_pylist()
        for i in range(rb.num_rows):
            out.setdefault(chunk.entity_path, []).append({**{n: v[i] for n, v in cols.items()}, "t": ns[i] / 1e9})
    return out


def test_recovery_counts_late_samples_and_names_misses():
    """``Recovery``: a sample later than its source's least lag by more than the margin is
    recovered (one on time, or late by less, is not); a miss is named by its session."""
    from services.node import RECOVERED_LAG_S, Recovery

    r = Recovery({"zid-a": "fuser"})
    for t in range(5):  # lag 0.2 s, then 0.2 + 2 margins (held for an outage), then 0.2 + half a margin
        r.arrived("fuser", float(t), t + 0.2)
    r.arrived("fuser", 5.0, 5.2 + 2 * RECOVERED_LAG_S)
    r.arrived("fuser", 6.0, 6.2 + 0.5 * RECOVERED_LAG_S)
    r.arrived("trk-a", 0.0, 9.0)  # a source's first sample sets its lag: not recovered
    r.on_miss("zid-a", 3)
    r.on_miss("zid-b", 2)
    assert r.counters() == {"recovered": 1, "missed": 5, "recovered.fuser": 1, "missed.fuser": 3, "missed.zid-b": 2}
