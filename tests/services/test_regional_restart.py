"""A regional fuser restarted with no standby starts warm (issue 28, "Losing a region"):
the system fuser keeps the picture of each region's stream (services/picture.py
``RegionPictures``: each track the region publishes, as ``regional/<region>`` last
carried it, until a frame drops it) and answers ``picture/<region>`` with it; a regional
fuser that finds no older member of its region running rebuilds its table from that
picture (services/leader.py ``rebuild``), so its ids go on and the system track ids
stay. In process, a GNN fuser's rebuilt frames are the killed one's bit for bit, and a
sweep tracker's (region-400) carry its ids; live, kill -9 of the west fuser once its
sources' caches no longer hold the aircraft's first scans, and the restarted west's
first frame carries the aircraft under its id before the kill."""

from __future__ import annotations

import json
import signal
import subprocess
import time

import numpy as np
import psutil
import pytest

from fusion.methods import make_method, method_config
from fusion.regional import RegionalFuser, RegionalStage
from schemas import KeySpace, decode
from sensors_sim import load_scenario
from services.evaluation import merged_measurements, run_method
from services.leader import rebuild
from services.picture import RegionPictures, documents, pictures
from services.scenario import load

from _runs import FusedWatch, child, run_cmd, run_log, stop_run
from conftest import ROOT

TWO_REGIONS = ROOT / "tests" / "data" / "two-regions.toml"
RECOVERY_S = 5.0  # the live run's recovery window: its sources' caches hold 2 x 5 s of stream, not 2 x 30 s
KILL_AFTER = 20.0  # s of system output before the kill: the caches no longer hold the aircraft's first scans (it is
# over the west region alone until 85 s)


def _west(sc) -> RegionalStage:
    return RegionalStage(RegionalFuser(sc.regions["west"], make_method("SS", method_config(sc.tracker, "SS", {}))))


def _pictures(sc, frames, until: float) -> RegionPictures:
    """The system fuser's pictures once it has taken ``frames`` (seq 1, 2, ...) up to ``until``."""
    seen = RegionPictures(sc.regions)
    for seq, f in enumerate(frames, 1):
        if f.t <= until:
            seen.frame(f, seq)
    return seen


@pytest.mark.parametrize("at", [30.0, 120.0])
def test_a_regional_fuser_rebuilt_from_its_region_s_picture_goes_on_as_the_killed_one(at):
    """The west fuser's frames up to ``at`` taken by the system fuser; a fresh west fuser
    rebuilt from the picture the system fuser serves for west, fed the measurements
    after the picture's scan: every later frame the killed fuser's, bit for bit (time,
    ids, x, P, the ids dropped), numbered on from the picture's seq; a fresh fuser on the
    same data (a cold restart) starts its track again, reporting nothing for its first
    frames."""
    sc = load_scenario(TWO_REGIONS)
    stream = list(merged_measurements(sc, 0))
    killed = run_method(None, "", measurements=stream, method=_west(sc))
    doc = documents(_pictures(sc, killed, at).pictures["west"].replies())["west"]
    assert [tr["id"] for tr in doc["tracks"]] == ["west.T1"]
    restarted = _west(sc)
    got = rebuild(restarted, doc)
    assert got is not None and got.tracks == ("west.T1",)
    assert got.seq == max(k for k, f in enumerate(killed, 1) if f.t <= at)
    after = run_method(None, "", measurements=[m for m in stream if m.t > got.t], method=restarted)
    expected = [f for f in killed if f.t > at]
    assert len(after) == len(expected) > 50
    for a, b in zip(after, expected):
        assert (a.t, a.dropped, [e.track for e in a.tracks]) == (b.t, b.dropped, [e.track for e in b.tracks])
        for ea, eb in zip(a.tracks, b.tracks):
            assert np.array_equal(ea.x, eb.x) and np.array_equal(ea.P, eb.P)
    assert any(f.dropped == ("west.T1",) for f in after)  # the aircraft leaves west (and its margin) at 165 s
    cold = run_method(None, "", measurements=[m for m in stream if m.t > got.t], method=_west(sc))
    assert not cold[0].tracks and cold[0].t == after[0].t


def test_a_sweep_tracker_s_region_rebuilt_from_its_picture_carries_its_ids():
    """region-400's nw fuser (the sweep tracker, rotating radars: a frame reports the
    tracks a sector updated), 50 s, rebuilt from nw's picture at 35 s: every track nw
    published and had not dropped is taken over (116), none dies at the next frame (a
    sweep track's life is its own, ``SweepTracker.taken_over``), and the rebuilt fuser's
    later frames carry 118 of the killed one's 119 ids. With the trackers' frame count
    (three frames without a report) the picture held 30 of them, and with the default
    logic the rebuilt fuser died at its first frame (TrackLogic.record given a sweep's
    arguments)."""
    sc = load("region-400", None, 50.0)
    region = sc.regions["nw"]
    stream = list(merged_measurements(sc, 0, sensors=region.sensors))

    def fuser() -> RegionalStage:
        return RegionalStage(RegionalFuser(region, make_method("SS", method_config(sc.tracker, "SS", {}))))
    killed = run_method(None, "", measurements=stream, method=fuser())
    doc = documents(_pictures(sc, killed, 35.0).pictures["nw"].replies())["nw"]
    restarted = fuser()
    got = rebuild(restarted, doc)
    assert got is not None and len(got.tracks) == len(doc["tracks"]) > 100
    after = run_method(None, "", measurements=[m for m in stream if m.t > got.t], method=restarted)
    theirs = {e.track for f in killed if f.t > 35.0 for e in f.tracks}
    mine = {e.track for f in after for e in f.tracks}
    assert len(mine & theirs) >= 0.95 * len(theirs) and len(mine - theirs) <= 0.02 * len(theirs), \
        (len(mine & theirs), len(theirs), len(mine - theirs))


def test_a_region_s_picture_holds_its_tracks_until_a_frame_drops_them():
    """The ids a frame drops leave the picture at once, a frame older than the picture
    (a cache given again) changes nothing, and each region answers for itself: west
    holds the aircraft until it leaves (165 s), east from when it enters its margin."""
    sc = load_scenario(TWO_REGIONS)
    stream = list(merged_measurements(sc, 0))
    frames = sorted([*run_method(None, "", measurements=stream, method=_west(sc)),
                     *run_method(None, "", measurements=stream, method=RegionalStage(RegionalFuser(
                         sc.regions["east"], make_method("SS", method_config(sc.tracker, "SS", {})))))],
                    key=lambda f: (f.t, f.region))

    def ids(seen, region):
        return [tr["id"] for tr in documents(seen.pictures[region].replies())[region]["tracks"]]
    seen = _pictures(sc, frames, 100.0)
    assert ids(seen, "west") == ["west.T1"] and ids(seen, "east") == ["east.T1"]
    t = seen.pictures["west"].t
    old = next(f for f in frames if f.region == "west" and f.t < t - 10 and f.tracks)
    seen.frame(old, 1)
    (track,) = documents(seen.pictures["west"].replies())["west"]["tracks"]
    assert track["t"] == seen.pictures["west"].t == t
    seen = _pictures(sc, frames, 200.0)
    assert ids(seen, "west") == [] and ids(seen, "east") == ["east.T1"]


@pytest.mark.slow
def test_a_restarted_regional_fuser_without_a_standby_starts_from_its_region_s_picture(tmp_path, deployment):
    """Live two-regions without ``--standby``, its sources' caches 10 s long
    (``recovery_s = 5``): kill -9 of the west fuser after 20 s of system output, the
    aircraft over the west region alone. Before the kill the system fuser answers
    ``picture/west`` with ``west.T1``. The launcher restarts west, which finds no older
    member of its region, asks that picture and says it rebuilt ``west.T1``; its first
    frame on ``regional/west`` carries the aircraft under that id, later than the last
    frame before the kill (what came up to the picture's scan is not fused again), and
    the system track keeps its one id; the summary's outage of west: the one aircraft
    west held, back in the system picture (absent 0.5 s of scenario time, one step, with
    west back 2.1 s after the kill; 5.0 s, five of the 1 s radars' periods, with two other
    live runs beside it and west back after 4.6 s: the system fuser had gone on without
    west before the restarted fuser's frames came). Without the warm start (the regional fuser's ask
    removed in services/fuser.py: ``asks = leader.joins and stage is None``) the
    restarted west's first frame is the caches' replay, 12.5 s of output, with no track
    (its track tentative again), and the test fails."""
    site = tmp_path / "two-regions.toml"
    site.write_text(f"recovery_s = {RECOVERY_S}\n{TWO_REGIONS.read_text()}", encoding="utf-8")
    watch = FusedWatch(deployment)
    frames: list[tuple[float, object]] = []  # (arrival, message) on regional/west
    sub = watch.session.declare_subscriber(KeySpace(deployment).regional("west"),
                                           lambda s: frames.append((time.monotonic(), decode(s.payload.to_bytes()))))
    proc = subprocess.Popen(run_cmd(tmp_path, str(site), deployment, "--topology", "regional", "--live",
                                    "--for", "120", "--connect", watch.endpoint),
                            stdout=subprocess.DEVNULL, stderr=(tmp_path / "run.log").open("w"))
    try:
        launcher = psutil.Process(proc.pid)
        west = child(launcher, "fuser", "west")
        watch.wait_until(0.0, proc, timeout=120)  # the system track's first estimate (UTC times)
        first = watch.got[0][1].t
        watch.wait_until(first + KILL_AFTER, proc)
        (held,) = pictures(watch.session, KeySpace(deployment), "west", timeout=10.0)  # the system fuser's
        west.kill()
        killed_at, at = time.monotonic(), watch.t
        child(launcher, "fuser", "west", exclude=(west.pid,))
        deadline = time.monotonic() + 90
        while not any(a > killed_at + 0.5 and m.kind == "regional_frame" for a, m in list(frames)):
            assert proc.poll() is None and time.monotonic() < deadline, "no frame of the restarted west"
            time.sleep(0.05)
        watch.wait_until(at + 10.0, proc, timeout=90)
        proc.send_signal(signal.SIGINT)  # ends a live run as --for would: in order, with its summary
        proc.wait(120)
    finally:
        sub.undeclare()
        stop_run(proc, watch)
    err = run_log(proc, tmp_path)
    doc = json.loads((tmp_path / "out.json").read_text())
    (out,) = doc["outages"]["west"]
    assert out["exit_code"] == -9 and out["t_up"] is not None, out
    print(f"west's outage in the summary: {out}")
    assert out["aircraft"] == 1 and out["not_back"] == 0 and out["period_s"] == 1.0, out
    assert out["absent_over_2_periods"] == int(out["longest_absence_s"] > 2.0), out
    assert "west: rebuilt west.T1 from west's picture" in err, err[-3000:]
    shown = [(a, m) for a, m in frames if m.kind == "regional_frame"]
    before = [m for a, m in shown if a < killed_at]
    after = [m for a, m in shown if a > killed_at + 0.5]
    assert [e["track"] for e in before[-1].body["tracks"]] == ["west.T1"], before[-1].body
    assert [tr["id"] for tr in held["tracks"]] == ["west.T1"] and held["t"] <= before[-1].t, held
    print(f"west's last frame before the kill at {before[-1].t - first:.1f} s of output, the restarted one's first "
          f"at {after[0].t - first:.1f} s: {[e['track'] for e in after[0].body['tracks']]}")
    assert [e["track"] for e in after[0].body["tracks"]] == ["west.T1"], after[0].body
    assert after[0].t > before[-1].t
    tracks = [(a, m) for a, m in watch.got if m.kind == "track"]
    assert {m.body["track"] for _, m in tracks} == {tracks[0][1].body["track"]}
    t = np.array([m.t for _, m in tracks])
    print(f"system estimate times: longest step {np.max(np.diff(t)):.2f} s, "
          f"wall-time gap {np.max(np.diff([a for a, _ in tracks])):.2f} s")
    assert np.all(np.diff(t) > 0) and t[-1] >= at + 10.0
