"""``zfusion run``: one scenario as separate OS processes over Zenoh.

The launcher opens a Zenoh peer that listens on a free loopback port (the "hub"
endpoint the children dial; they then find each other by gossip, no router involved),
starts the fuser and the recorder, waits until they have announced themselves, starts
every source (sensors, truth, jammers) with a common start time, collects the fused
estimates, and when the fuser is done stops everything, scores the estimates against
truth and writes the summary.

Children are started with ``PR_SET_PDEATHSIG`` so that even a launcher killed with
SIGKILL leaves none behind; on SIGINT/SIGTERM the launcher stops them in order (SIGTERM,
then SIGKILL after a grace period) and exits.
"""

from __future__ import annotations

import ctypes
import datetime as _dt
import json
import logging
import math
import queue
import signal
import socket
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

from fusion.patent import track_fusion_rule
from fusion.types import Estimate
from schemas import KeySpace, SchemaError, decode, to_estimate, tracker_id

from .node import Node, ZenohOptions, load
from .summary import format_table, method_summary, summary, truth_function

log = logging.getLogger("zfusion")

FUSER_ID = "fuser"
RECORDER_ID = "recorder"
LAUNCHER_ID = "launcher"
TOPOLOGIES = ("centralised", "distributed", "feedback", "two-stage")


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def die_with_parent() -> None:  # runs in the child between fork and exec
    try:
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
    except OSError:
        pass


@dataclass
class Children:
    procs: dict[str, subprocess.Popen] = field(default_factory=dict)

    def start(self, name: str, argv: list[str]) -> None:
        cmd = [sys.executable, "-m", "services.cli", *argv]
        log.debug("starting %s: %s", name, " ".join(cmd))
        self.procs[name] = subprocess.Popen(cmd, stdin=subprocess.DEVNULL, preexec_fn=die_with_parent)

    def wait(self, name: str, timeout: float) -> int | None:
        try:
            return self.procs[name].wait(timeout)
        except subprocess.TimeoutExpired:
            return None

    def stop_all(self, grace: float = 5.0) -> None:
        live = [p for p in self.procs.values() if p.poll() is None]
        for p in live:
            p.send_signal(signal.SIGTERM)
        deadline = time.monotonic() + grace
        for p in live:
            try:
                p.wait(max(0.0, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()


def topology_of(method: str) -> str:
    from fusion.network import SPLITS

    return SPLITS[method].topology if method in SPLITS else "centralised"


# The method a topology runs when none is named: 3D scenarios / DF (bearing) scenarios.
DEFAULT_METHODS = {"distributed": ("HNV", "KF+TR"), "feedback": ("PHHNV", None), "two-stage": ("DDHNV", None)}


def resolve_topology(scenario, topology: str | None, method: str | None) -> tuple[str, str]:
    """Topology and method from the command line and the scenario's defaults; they must agree."""
    default = scenario.defaults.get("method")
    if method is None and topology is not None and (default is None or topology_of(default) != topology):
        if topology == "centralised":
            raise SystemExit(f"zfusion run: scenario {scenario.name} names no centralised method; give --method")
        df = all(scenario.kind_of(s) in ("df", "airborne_df") for s in scenario.sensors)
        method = DEFAULT_METHODS[topology][1 if df else 0]
        if method is None:
            raise SystemExit(f"zfusion run: no DF method runs in the {topology!r} topology (DESIGN.md, Topologies)")
    method = method or default
    if not method:
        raise SystemExit("zfusion run: no --method given and the scenario names no default method")
    topology = topology or topology_of(method)
    if topology_of(method) != topology:
        raise SystemExit(f"zfusion run: method {method} runs in the {topology_of(method)!r} topology, "
                         f"not {topology!r}")
    return topology, method


def default_rrd(scenario: str, topology: str) -> str:
    stamp = _dt.datetime.now().strftime("%Y%m%d-%H%M%S")
    return str(Path("runs") / f"{scenario}-{topology}-{stamp}.rrd")


def run(args) -> int:
    scenario = load(args.scenario, args.seed)
    topology, method = resolve_topology(scenario, args.topology, args.method)
    from fusion.config import method_config
    from fusion.methods import make_method

    overrides = {"fusion_rule": args.fusion_rule} if args.fusion_rule else {}
    make_method(method, method_config(scenario.tracker, method, overrides))  # fail here, with a clear error, not in a child
    speed = math.inf if args.speed == "max" else float(args.speed)
    if not speed > 0:
        raise SystemExit("zfusion run: --speed must be > 0 or 'max'")
    rrd = args.rrd or default_rrd(scenario.name, topology)
    Path(rrd).parent.mkdir(parents=True, exist_ok=True)

    keys = KeySpace(args.deployment)
    if args.connect or args.zenoh_config:
        mine = ZenohOptions(connect=args.connect or [], config_file=args.zenoh_config)
        theirs = mine
    else:
        hub = f"tcp/127.0.0.1:{free_port()}"
        mine = ZenohOptions(listen=[hub])
        theirs = ZenohOptions(connect=[hub])
    common = ["--deployment", args.deployment, *theirs.to_args()] + (["-v"] if args.verbose else [])
    seed = ["--seed", str(scenario.seed)]
    sources = list(scenario.process_ids())
    max_period = max([getattr(s, "period", 1.0) for s in scenario.sensors.values()] + [1.0])
    timeout = 5.0 if math.isinf(speed) else max(3.0, 3.0 * max_period / speed)

    inbox: queue.SimpleQueue[tuple[str, bytes]] = queue.SimpleQueue()
    estimates: list[Estimate] = []
    statuses: dict[str, dict] = {}
    children = Children()
    interrupted = False
    with Node(LAUNCHER_ID, "launcher", keys, mine) as node:
        node.subscribe(keys.fused(), lambda s: inbox.put((str(s.key_expr), s.payload.to_bytes())))
        node.subscribe(keys.all("status"), lambda s: inbox.put((str(s.key_expr), s.payload.to_bytes())))
        node.announce()

        def drain(block: float = 0.0) -> None:
            try:
                while True:
                    key, data = inbox.get(timeout=block) if block else inbox.get_nowait()
                    block = 0.0
                    try:
                        msg = decode(data)
                    except SchemaError as e:
                        node.reject(key.rsplit("/", 1)[-1], e.cause, str(e))
                        continue
                    if msg.kind == "track" and key == keys.fused():
                        estimates.append(to_estimate(msg))
                    elif msg.kind == "status":
                        statuses[msg.src] = msg.body
            except queue.Empty:
                pass

        try:
            children.start(FUSER_ID, ["fuser", "--scenario", args.scenario, "--method", method, "--id", FUSER_ID,
                                      "--source-timeout", str(timeout), *seed, *(
                                          ["--fusion-rule", args.fusion_rule] if args.fusion_rule else []), *common])
            trackers = {s: tracker_id(s) for s in scenario.sensors} if topology != "centralised" else {}
            children.start(RECORDER_ID, ["record", "--rrd", rrd, "--id", RECORDER_ID, "--scenario", args.scenario,
                                         *seed, *(["--spawn"] if getattr(args, "spawn", False) else []),
                                         "--expect", ",".join([FUSER_ID, *trackers.values(), *sources]), *common])
            node.wait_for([FUSER_ID, RECORDER_ID], timeout=60.0)
            for sensor, tid in trackers.items():
                children.start(tid, ["tracker", "--scenario", args.scenario, "--sensor", sensor, "--method", method,
                                     "--fuser", FUSER_ID, "--feedback-timeout", str(timeout), *seed, *(
                                         ["--fusion-rule", args.fusion_rule] if args.fusion_rule else []), *common])
            node.wait_for(trackers.values(), timeout=60.0)
            start_at = time.time() + (0.0 if math.isinf(speed) else 0.5)
            for sid in sources:
                # A source waits only for its consumers: the fuser may finish (and vanish)
                # before a truth or jammer process discovers it, so they must not wait for it.
                first = trackers.get(sid, FUSER_ID)
                consumers = [first, RECORDER_ID] if sid in scenario.sensors else [RECORDER_ID]
                children.start(sid, ["sensor", "--scenario", args.scenario, "--id", sid, "--speed", str(args.speed),
                                     "--start-at", repr(start_at), *seed,
                                     "--wait-for", ",".join([*consumers, LAUNCHER_ID]), *common])
            while not node.stop.is_set():
                drain(0.1)
                code = children.procs[FUSER_ID].poll()
                if code is not None:
                    break
            interrupted = node.stop.is_set()
            if not interrupted:
                for sid in [*sources, *trackers.values()]:
                    children.wait(sid, 10.0)
                children.wait(RECORDER_ID, 30.0)
                drain(0.2)
        except TimeoutError as e:
            log.error("%s", e)
            interrupted = True
        finally:
            children.stop_all()
    codes = {n: p.returncode for n, p in children.procs.items()}
    if interrupted:
        print("zfusion run: interrupted; all processes stopped", file=sys.stderr)
        return 130
    if codes.get(FUSER_ID) != 0:
        print(f"zfusion run: the fuser failed (exit {codes.get(FUSER_ID)})", file=sys.stderr)
        return 1
    fuser_status = statuses.get(FUSER_ID, {})
    src_report = dict(fuser_status.get("sources", {}))
    for sid in sources:  # processes the fuser does not consume (truth, jammers) are reported too
        src_report.setdefault(sid, {"dead_intervals": [], "rejected": 0})
    truth = truth_function(scenario)
    doc = summary(scenario, topology, args.fusion_rule or track_fusion_rule(scenario.tracker, [method]), scenario.seed, 1,
                  {method: method_summary([estimates], truth)}, sources=src_report)
    doc["recording"] = rrd
    doc["exit_codes"] = codes
    print(format_table(doc))
    print(f"recording: {rrd}")
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(doc, indent=1))
    # A process killed from outside (negative code) is an outage the fuser rode through,
    # reported in the summary; a process that failed on its own is an error.
    killed = {n: c for n, c in codes.items() if c is not None and c < 0}
    if killed:
        print(f"zfusion run: processes killed during the run (see 'sources' in the summary): {killed}",
              file=sys.stderr)
    bad = {n: c for n, c in codes.items() if c not in (0, None) and c > 0}
    if bad:
        print(f"zfusion run: processes ended with errors: {bad}", file=sys.stderr)
        return 1
    return 0
