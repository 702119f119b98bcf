"""The run's processes as one list (services/plan.py) and how the supervisor starts and
restarts them (services/supervisor.py), without starting any process."""

from __future__ import annotations

import shlex
import subprocess
import sys
import time

import pytest

from sensors_sim import load_scenario
from services.cli import build_parser
from services.plan import FUSER_ID, RECORDER_ID, Live, ProcessSpec, RunPlan, source_timeout
from services.supervisor import Children, Supervisor

FABRIC = ["--connect", "tcp/127.0.0.1:7447"]


def _plan(name: str, topology: str, method: str, **kw) -> RunPlan:
    return RunPlan.build(name, load_scenario(name), topology, method, fabric=FABRIC, **kw)


def test_a_centralised_run_is_fuser_recorder_then_sources_waiting_for_their_consumers():
    plan = _plan("patent-3d", "centralised", "SS", supervisor="launcher")
    assert [(s.id, s.role) for s in plan] == [("fuser", "fuser"), ("recorder", "recorder"), ("radar2d", "source"),
                                              ("angle", "source"), ("truth", "source")]
    assert {s.id: s.waits_for for s in plan} == {"fuser": (), "recorder": (), "radar2d": ("fuser", "recorder"),
                                                 "angle": ("fuser", "recorder"), "truth": ("recorder",)}
    assert [s.id for s in plan if s.restartable] == ["fuser", "recorder"]
    radar = plan["radar2d"].argv
    assert radar[radar.index("--wait-for") + 1] == "fuser,recorder,launcher"  # and the one that starts them
    assert plan[RECORDER_ID].argv[plan[RECORDER_ID].argv.index("--expect") + 1] == "fuser,radar2d,angle,truth"


def test_a_distributed_run_has_a_tracker_per_sensor_after_the_fuser():
    plan = _plan("patent-3d", "feedback", "PHHNV", settings=[("q", 0.05)], fusion_rule="info")
    trackers = plan.of_role("tracker")
    assert [t.id for t in trackers] == ["trk-radar2d", "trk-angle"]
    assert all(t.waits_for == (FUSER_ID,) and t.restartable for t in trackers)
    assert plan["radar2d"].waits_for == ("trk-radar2d", RECORDER_ID)
    for spec in [plan[FUSER_ID], *trackers]:  # the overrides reach every estimator
        assert ("--set", "q=0.05") in zip(spec.argv, spec.argv[1:]) and "--fusion-rule" in spec.argv
    assert plan[RECORDER_ID].argv[plan[RECORDER_ID].argv.index("--expect") + 1] == \
        "fuser,trk-radar2d,trk-angle,radar2d,angle,truth"


def test_a_live_run_gives_its_estimators_the_site_and_its_sources_utc():
    plan = _plan("patent-3d", "centralised", "SS", live=Live(0.5, 8.0))
    fuser = plan[FUSER_ID].argv
    assert fuser[1:3] == ("--site", "patent-3d") and "--seed" not in fuser
    assert fuser[fuser.index("--max-delay") + 1] == "0.5" and fuser[fuser.index("--oosm-window") + 1] == "8.0"
    radar = plan["radar2d"].argv
    assert "--live" in radar and radar[radar.index("--duration-s") + 1] == "30.0"
    endless = _plan("patent-3d-orbit", "centralised", "SS", live=Live(endless=True))
    assert "--duration-s" not in endless["radar2d"].argv  # until stopped


def test_every_command_of_a_plan_is_one_the_command_line_takes():
    parser = build_parser()
    plans = [_plan("patent-3d", "two-stage", "DDHNV", router="tcp/127.0.0.1:7447", json_path="r.json",
                   outputs={"export-geojson": ("geojson", "--file", "/tmp/g.json")}, spawn=True, rotate_s=60.0),
             _plan("df-multi", "centralised", "EKF", live=Live(), duration=20.0)]
    for plan in plans:
        for spec in plan:
            args = parser.parse_args(list(spec.argv))
            assert args.command == spec.argv[0]
            if spec.role not in ("router", "tracker"):
                assert getattr(args, "id", spec.id) == spec.id


def test_zfusion_plan_prints_the_plan_the_launcher_runs():
    """One source of the process list: the printed commands are the plan's, router first."""
    p = subprocess.run([sys.executable, "-m", "services.cli", "plan", "--scenario", "patent-3d", "--topology",
                        "distributed", "--connect", "tcp/127.0.0.1:9999"], capture_output=True, text=True, timeout=60)
    assert p.returncode == 0, p.stderr
    commands = [shlex.split(ln)[1:] for ln in p.stdout.splitlines() if ln.startswith("zfusion ")]
    plan = RunPlan.build(
        "patent-3d", load_scenario("patent-3d"), "distributed", "HNV",
        fabric=["--zenoh-mode", "client", "--connect", "tcp/127.0.0.1:9999"], router="tcp/127.0.0.1:9999",
        json_path="result.json", rrd="site.rrd")
    assert commands == [list(s.argv) for s in plan]
    assert commands[0] == ["router", "--listen", "tcp/127.0.0.1:9999"]


def test_the_source_timeout_is_three_of_the_slowest_scans_of_wall_time():
    sc = load_scenario("patent-3d")
    assert source_timeout(sc, "1") == 3.0 and source_timeout(sc, "0.5") == 6.0
    assert source_timeout(sc, "max") == 15.0


def test_a_role_must_be_known():
    with pytest.raises(ValueError, match="role"):
        ProcessSpec("x", "daemon", ("fuser",))


class _Children:
    def __init__(self):
        self.procs, self.argv, self.log = {}, {}, []

    def start(self, name, argv):
        self.argv[name] = argv
        self.log.append(("start", name))

    def exited(self, names):
        return None


class _Node:
    def __init__(self, log):
        self.log = log

    def wait_for(self, ids, timeout, gone=None):
        self.log.append(("wait", tuple(ids)))


def test_the_supervisor_starts_stage_by_stage_then_the_sources_together():
    plan = _plan("patent-3d", "distributed", "HNV", outputs={"export-cot": ("cot", "--to", "udp://127.0.0.1:9")})
    children = _Children()
    sup = Supervisor(children, plan, True, lambda: None, lambda text: None, fuser_grace=3.0)
    sup.start_consumers(_Node(children.log))
    assert sup.restartable == {"fuser", "recorder", "export-cot", "trk-radar2d", "trk-angle"}
    sup.start_sources(1234.5)
    assert children.log == [("start", "fuser"), ("start", "recorder"), ("start", "export-cot"),
                            ("wait", ("fuser", "recorder", "export-cot")),
                            ("start", "trk-radar2d"), ("start", "trk-angle"), ("wait", ("trk-radar2d", "trk-angle")),
                            ("start", "radar2d"), ("start", "angle"), ("start", "truth")]
    assert children.argv["truth"][-2:] == ["--start-at", "1234.5"]
    # restarted: the fuser does not wait for sources that run already; a recording is never overwritten
    assert sup._argv("fuser", 2)[-2:] == ["--start-grace", "3.0"]
    rec = sup._argv("recorder", 2)
    assert rec[rec.index("--rrd") + 1] == "site.2.rrd" and sup.recordings == ["site.rrd", "site.2.rrd"]


def test_a_plan_whose_processes_wait_for_each_other_cannot_start():
    plan = RunPlan("s", "centralised", "SS", 1, (ProcessSpec("a", "fuser", ("fuser",), waits_for=("b",)),
                                                 ProcessSpec("b", "recorder", ("record",), waits_for=("a",))))
    sup = Supervisor(_Children(), plan, True, lambda: None, lambda text: None, fuser_grace=3.0)
    with pytest.raises(ValueError, match="wait for each other"):
        sup.start_consumers(_Node([]))


@pytest.mark.parametrize("how", ["terminate", "stop_all"])
def test_a_child_killed_at_the_end_is_told_apart_from_one_killed_during_the_run(how):
    """A child that ignores SIGTERM past its grace is killed at the end and named in
    ``Children.forced`` (the launcher says so apart from the processes killed during the
    run, which are outages); one that stops in time is not."""
    stubborn = "import signal, time; signal.signal(signal.SIGTERM, signal.SIG_IGN); print(flush=True); time.sleep(60)"
    ch = Children()
    ch.procs["slow"] = subprocess.Popen([sys.executable, "-c", stubborn], stdout=subprocess.PIPE)
    ch.procs["quick"] = subprocess.Popen([sys.executable, "-c", "import time; print(flush=True); time.sleep(60)"],
                                         stdout=subprocess.PIPE)
    for p in ch.procs.values():
        p.stdout.readline()  # its handler is set
    if how == "terminate":
        ch.terminate(["slow", "quick"], drain=time.sleep, grace=0.5)
    else:
        ch.stop_all(grace=0.5)
    assert ch.forced == {"slow"}
    assert ch.procs["slow"].returncode == -9 and ch.procs["quick"].returncode == -15
