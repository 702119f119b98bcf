"""A hot standby per regional fuser (issue 28, "Losing a region"): ``zfusion run
--topology regional --live --standby`` starts ``<region>-standby`` beside each regional
fuser (``zfusion fuser --region R --standby R``), on the region's sensors, publishing the
region's frames on ``regional/R`` only once it leads (services/leader.py). kill -9 of a
regional fuser while the aircraft is in its region alone: with the standby the system
track goes on under one id, no gap longer than two of the radars' periods. (Without it
the launcher restarts the fuser, warm from its region's picture:
test_regional_restart.py.)"""

from __future__ import annotations

import json
import signal
import subprocess
from pathlib import Path

import numpy as np
import psutil
import pytest

from schemas import KeySpace
from services.errors import UserError
from services.fuser import run as run_fuser
from services.plan import FUSER_ID, RECORDER_ID, STANDBY_ID, Live, RunPlan, standby_id
from sensors_sim import load_scenario

from _runs import FusedWatch, child, run_cmd, run_log, stop_run

TWO_REGIONS = Path(__file__).resolve().parents[1] / "data" / "two-regions.toml"
PERIOD = 1.0  # two-regions' radars scan once a second
KILL_AFTER = 8.0  # s of system output before the kill (the aircraft, at e = -25 km + 200 m/s t, is west of the
# overlap, in the west region alone, until 85 s)
AFTER = 8.0  # s of system output after it


def _plan(standby: bool) -> RunPlan:
    return RunPlan.build(str(TWO_REGIONS), load_scenario(TWO_REGIONS), "regional", "SS",
                         fabric=["--connect", "tcp/127.0.0.1:7447"], live=Live(), standby=standby)


def test_the_regional_plan_has_one_standby_per_region_and_none_without():
    plan = _plan(standby=True)
    regions = list(load_scenario(TWO_REGIONS).regions)
    standbys = [s for s in plan if "--standby" in s.argv]
    assert sorted(s.id for s in standbys) == sorted([*map(standby_id, regions), STANDBY_ID])
    for region in regions:
        spec = plan[standby_id(region)]
        argv = list(spec.argv)
        assert spec.role == "fuser" and spec.restartable and spec.waits_for == (region,)
        assert [argv[argv.index(o) + 1] for o in ("--region", "--standby", "--id")] == \
            [region, region, f"{region}-standby"]
        assert argv[argv.index("--site") + 1] == str(TWO_REGIONS)  # the primary's inputs
        for option in ("--id", "--standby"):  # else its primary's command line
            del argv[argv.index(option):argv.index(option) + 2]
        assert argv == list(plan[region].argv)
        assert all(standby_id(region) not in s.waits_for for s in plan if s.id != standby_id(region))
    expect = plan[RECORDER_ID].argv[plan[RECORDER_ID].argv.index("--expect") + 1].split(",")
    assert set(expect) >= {FUSER_ID, *regions, STANDBY_ID, *map(standby_id, regions)}
    assert not [s for s in _plan(standby=False) if "--standby" in s.argv or s.id.endswith("-standby")]


@pytest.mark.parametrize("region, standby, pid, says", [
    ("west", "east", "west-standby", "stands by for its region's fuser only"),
    ("west", "west", "west", "a standby's --id is its own"),
    ("west", None, "west-standby", "a regional fuser's --id is its region's name"),
    (None, "west", "west-standby", "is a region's fuser, not the system fuser"),
])
def test_a_standby_that_makes_no_sense_is_a_user_error(region, standby, pid, says):
    with pytest.raises(UserError, match=says):
        run_fuser(pid, str(TWO_REGIONS), "SS", {}, KeySpace("t"), None, 3.0, 30.0, standby_for=standby,
                  region=region, system=region is None)


def _kill_west(tmp_path: Path, deployment: str, *extra: str) -> tuple[np.ndarray, np.ndarray, set[str], dict, str]:
    """A live regional run of two-regions; after ``KILL_AFTER`` s of system output, kill -9
    of the west fuser (the aircraft over the west region alone), then SIGINT once the
    system output has gone on ``AFTER`` s past the kill. The system track estimates' arrivals
    (monotonic s) and times (UTC s), their track ids, the summary and the launcher's stderr."""
    watch = FusedWatch(deployment)
    proc = subprocess.Popen(run_cmd(tmp_path, str(TWO_REGIONS), deployment, "--topology", "regional", "--live",
                                    "--for", "80", "--connect", watch.endpoint, *extra),
                            stdout=subprocess.DEVNULL, stderr=(tmp_path / "run.log").open("w"))
    try:
        west = child(psutil.Process(proc.pid), "fuser", "west")
        watch.wait_until(0.0, proc, timeout=120)  # the system track's first estimate (UTC times)
        first = watch.got[0][1].t
        watch.wait_until(first + KILL_AFTER, proc)
        at = watch.t
        west.kill()
        watch.wait_until(at + AFTER, proc, timeout=90)
        proc.send_signal(signal.SIGINT)  # ends a live run as --for would: in order, with its summary
        proc.wait(120)
    finally:
        stop_run(proc, watch)
    err = run_log(proc, tmp_path)
    tracks = [(a, m) for a, m in watch.got if m.kind == "track"]
    return np.array([a for a, _ in tracks]), np.array([m.t for _, m in tracks]), {m.body["track"] for _, m in tracks}, \
        json.loads((tmp_path / "out.json").read_text()), err


@pytest.mark.slow
def test_a_killed_regional_fuser_with_a_standby_leaves_no_gap(tmp_path, deployment):
    """kill -9 of the west fuser, the aircraft 20 km inside the west region and outside
    the east one's margin, and no restart (``--no-restart``: the standby alone carries
    the region): west-standby takes over, and the system track goes on under its one id,
    its estimates 0.5 s apart as undisturbed (the radars w and s scan half a period
    apart), none arriving more than two radar periods after the one before (measured:
    0.5 s). The summary says so from outside: west's outage with the one aircraft west
    held, absent from the system picture across the loss no longer than two periods,
    none over them, none not back. Without the standby (the plan's loop removed) nothing
    more comes after the kill and the test fails."""
    arrivals, t, ids, doc, err = _kill_west(tmp_path, deployment, "--standby", "--no-restart")
    assert doc["exit_codes"]["west"] == -9 and doc["exit_codes"][standby_id("west")] == 0, doc["exit_codes"]
    (out,) = doc["outages"]["west"]
    assert out["aircraft"] == 1 and out["period_s"] == PERIOD, out
    assert out["longest_absence_s"] <= 2 * PERIOD and out["absent_over_2_periods"] == out["not_back"] == 0, out
    assert f"{standby_id('west')}: the leader is gone: taking over" in err, err[-3000:]
    assert len(ids) == 1, ids
    assert t[-1] - t[0] >= KILL_AFTER + AFTER and np.all(np.diff(t) > 0) and np.max(np.diff(t)) <= PERIOD, \
        np.max(np.diff(t))
    print(f"longest wall-time gap {np.max(np.diff(arrivals)):.2f} s; west's outage {out}")
    assert np.max(np.diff(arrivals)) <= 2 * PERIOD, np.max(np.diff(arrivals))
