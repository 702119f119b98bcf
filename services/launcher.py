"""``zfusion run``: one scenario as separate OS processes over Zenoh, and their supervisor.

The launcher opens a Zenoh peer on a free loopback port (the "hub" the children dial;
they then find each other by gossip, no router), starts the fuser and the recorder,
waits until they have announced themselves, and starts every source (sensors, truth,
jammers) with a common start time as far ahead as the fuser and recorder took to come
up, so that the sources are running by then even under load. It collects the fused
estimates, and when the fuser is done stops everything, scores them against truth
(:class:`services.summary.RunScorer`: as they settle in a live run, so an endless run
holds a window of them) and writes the summary.

As supervisor: a child killed from outside (a signal the launcher did not send) is an
*outage*. The fuser, trackers and recorder are restarted with the same command line
(``--restart``, at most :data:`MAX_RESTARTS` times each, :data:`RESTART_DELAY` s later),
sources never (they stand for the sensors). A child that fails on its own (positive
exit code) ends the run at once, exit 1, with its last line. Children get
``PR_SET_PDEATHSIG``, so even a launcher killed with SIGKILL leaves none behind; on
SIGINT/SIGTERM it stops them in order. ``--live`` runs the same processes on UTC time
(:func:`services.live.live_argv`). What each outage does and what the summary reports:
docs/reliability.md ("Faults"); live runs: docs/live.md.
"""

from __future__ import annotations

import contextlib
import ctypes
import dataclasses
import datetime as _dt
import json
import logging
import math
import queue
import random
import signal
import socket
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable

import zenoh

from fusion.methods import TRACK_FUSION_METHODS, track_fusion_rule
from schemas import KeySpace, SchemaError, decode, to_estimate, tracker_id

from .commands import options
from .errors import FAILURE, UserError
from .export.outputs import OUTPUTS
from .node import Inbox, Node, ZenohOptions
from .request import check_methods, resolve_topology, scenario_of
from .resources import ProcessUsage, own_usage
from .rotation import rotated_files
from .summary import RunScorer, format_table, run_summary

log = logging.getLogger("zfusion")

FUSER_ID = "fuser"
RECORDER_ID = "recorder"
LAUNCHER_ID = "launcher"
RESTART_DELAY = 0.5  # s: lets the fabric see the dead process's token go before the new one appears
MAX_RESTARTS = 3  # per process: a process killed again and again is not coming back
END_GRACE = 10.0  # s after the last source ends, when no fuser is left to say it is done
# s of silence after which a source is dead at --speed max: nothing is paced there, so a
# source that is silent is far more often starved of CPU (many processes, two cores) than
# dead, and taking it for dead changes what is fused
MAX_SPEED_TIMEOUT = 15.0
START_LEAD_MAX = 15.0  # s: the most a paced run's sources are given to start (see main)
RECORDER_STALL = 30.0  # s: at the end, the recorder is stopped once it has recorded nothing new this long
SETTLE_MARGIN = 1.0  # s beyond the OOSM window and max delay before a live estimate is scored for good
LIVE_LEAD = 8.0  # s from starting the sources of a live run to its scenario time 0 (their start-up)


PORTS_FROM = 10000  # free_port's lowest pick (below it: well-known and registered services)


def free_port() -> int:
    """A loopback TCP port free now, for a listener that binds it a moment later. It is
    drawn at random below the kernel's ephemeral range, so that no outgoing connection
    (the kernel takes those ports for them) and no other caller picking at the same time
    is likely to take it in between; where that range leaves no room, the kernel picks."""
    low = _ephemeral_low()
    rng = random.SystemRandom()
    for _ in range(64 if low - PORTS_FROM >= 1000 else 0):
        port = rng.randrange(PORTS_FROM, low)
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
            try:
                s.bind(("127.0.0.1", port))
            except OSError:
                continue
            return port
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _ephemeral_low() -> int:
    """The first port of the kernel's ephemeral range (Linux; 32768 where it cannot be read)."""
    try:
        return int(Path("/proc/sys/net/ipv4/ip_local_port_range").read_text().split()[0])
    except (OSError, ValueError, IndexError):
        return 32768


def zenoh_reason(e: Exception) -> str:
    """A Zenoh error on one line, without its source locations."""
    return str(e).split(" at /")[0].replace("\n", " ")[:300]


def unreachable(endpoints: Iterable[str], timeout: float = 2.0) -> list[str]:
    """The ``tcp/`` and ``tls/`` endpoints of ``endpoints`` where nothing accepts a connection."""
    out = []
    for ep in endpoints:
        proto, _, addr = ep.partition("/")
        host, _, port = addr.split("#")[0].rpartition(":")
        if proto not in ("tcp", "tls") or not host:
            continue
        try:
            socket.create_connection((host.strip("[]"), int(port)), timeout=timeout).close()
        except (OSError, ValueError):
            out.append(ep)
    return out


def die_with_parent() -> None:  # runs in the child between fork and exec
    try:
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
    except OSError:
        pass


@dataclass
class Children:
    """The run's child processes. Each child's stderr is relayed line by line to ours by a
    thread that keeps only its last non-blank line (what a failed child said last)."""

    procs: dict[str, subprocess.Popen] = field(default_factory=dict)
    argv: dict[str, list[str]] = field(default_factory=dict)  # each child's command line, to restart it
    last_line: dict[str, str] = field(default_factory=dict)  # each child's last line on stderr
    relays: list[threading.Thread] = field(default_factory=list)

    def start(self, name: str, argv: list[str]) -> None:
        cmd = [sys.executable, "-m", "services.cli", *argv]
        log.debug("starting %s: %s", name, " ".join(cmd))
        self.argv[name] = argv
        # Its own process group: a Ctrl-C at the terminal reaches the launcher alone, which
        # stops the children in order (one still importing would print a traceback).
        proc = subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stderr=subprocess.PIPE, preexec_fn=die_with_parent,
                                process_group=0)
        self.procs[name] = proc
        relay = threading.Thread(target=self._relay, args=(name, proc.stderr), daemon=True, name=f"stderr-{name}")
        relay.start()
        self.relays.append(relay)

    def _relay(self, name: str, stream) -> None:
        out = getattr(sys.stderr, "buffer", None)
        for line in iter(stream.readline, b""):
            if line.strip():
                self.last_line[name] = line.decode(errors="replace").strip()
            try:
                if out is not None:
                    out.write(line)
                    out.flush()
                else:
                    sys.stderr.write(line.decode(errors="replace"))
            except (OSError, ValueError):  # our stderr closed: keep draining the child's
                pass
        stream.close()

    def exited(self, names: Iterable[str]) -> str | None:
        """Which of ``names`` have exited, with their exit codes (None if none has)."""
        dead = [f"{n} exited with code {self.procs[n].poll()}" for n in names
                if n in self.procs and self.procs[n].poll() is not None]
        return "; ".join(dead) + " (its error is above)" if dead else None

    def failed(self) -> str | None:
        """The first child that failed on its own (a positive exit code), with what it said
        last; None while none has. A kill (negative code) is an outage, not a failure."""
        for name, proc in self.procs.items():
            code = proc.poll()
            if code is not None and code > 0:
                time.sleep(0.05)  # its last line may still be in the relay
                said = self.last_line.get(name)
                return f"{name} failed (exit {code})" + (f": {said}" if said else "")
        return None

    def wait(self, name: str, timeout: float) -> int | None:
        try:
            return self.procs[name].wait(timeout)
        except subprocess.TimeoutExpired:
            return None

    def terminate(self, names: Iterable[str], drain, grace: float = 10.0) -> None:
        """SIGTERM to ``names``, calling ``drain`` while they stop (their last status); a
        child still there after ``grace`` seconds is killed."""
        live = [self.procs[n] for n in names if n in self.procs and self.procs[n].poll() is None]
        for p in live:
            p.send_signal(signal.SIGTERM)
        deadline = time.monotonic() + grace
        while any(p.poll() is None for p in live) and time.monotonic() < deadline:
            drain(0.1)
        for p in live:
            if p.poll() is None:
                p.kill()
                p.wait()

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
        for relay in self.relays:  # their last words before ours
            relay.join(timeout=1.0)


class Supervisor:
    """Watches the children of a run: records every death, restarts what the policy
    allows (module docstring), and says when a restarted process is back.

    Args:
        children: the run's children.
        restartable: process ids that may be restarted.
        restart: the ``--restart`` policy.
        clock: scenario time now (``None`` before the sources have started).
        event: where to say what happened (the launcher's status events).
        fuser_grace: ``--start-grace`` for a restarted fuser.
    """

    def __init__(self, children: Children, restartable: set[str], restart: bool, clock, event,
                 fuser_grace: float):
        self.children = children
        self.restartable = restartable
        self.restart = restart
        self.clock = clock
        self.event = event
        self.fuser_grace = fuser_grace
        self.codes: dict[str, list[int]] = {}  # exit codes of every incarnation, in order
        self.outages: dict[str, list[dict]] = {}
        self.recordings: list[str] = []
        self.restarts: dict[str, int] = {}
        self._due: dict[str, float] = {}  # monotonic time of each pending restart
        self._restarted: dict[str, float] = {}  # monotonic time of each process's latest restart
        self._handled: set[int] = set()  # pids whose exit has been dealt with

    def poll(self) -> None:
        """Deal with the children that have exited and the restarts that are due."""
        for name, proc in list(self.children.procs.items()):
            if proc.pid in self._handled or proc.poll() is None:
                continue
            self._handled.add(proc.pid)
            code = proc.returncode
            self.codes.setdefault(name, []).append(code)
            if code >= 0:
                continue
            self.outages.setdefault(name, []).append({"t_down": self.clock(), "t_up": None, "exit_code": code})
            if self.restart and name in self.restartable and self.restarts.get(name, 0) < MAX_RESTARTS:
                self._due[name] = time.monotonic() + RESTART_DELAY
                self.event(f"{name} killed (signal {-code}): restarting it")
            else:
                self.event(f"{name} killed (signal {-code})")
        now = time.monotonic()
        for name, due in list(self._due.items()):
            if now >= due:
                del self._due[name]
                self.restarts[name] = self.restarts.get(name, 0) + 1
                self.children.start(name, self._argv(name, self.restarts[name] + 1))
                self._restarted[name] = time.monotonic()

    def pending(self, name: str) -> bool:
        return name in self._due

    def _argv(self, name: str, incarnation: int) -> list[str]:
        argv = list(self.children.argv[name])
        if name == FUSER_ID:  # its sources are running: one not heard within the timeout is dead
            argv += ["--start-grace", str(self.fuser_grace)]
        if "--rrd" in argv:  # never overwrite what the killed recorder wrote
            i = argv.index("--rrd") + 1
            if not self.recordings:
                self.recordings.append(argv[i])
            argv[i] = str(Path(self.recordings[0]).with_suffix(f".{incarnation}.rrd"))
            self.recordings.append(argv[i])
        return argv

    def heard(self, name: str, state: str) -> None:
        """A status from ``name``: the first one of a new incarnation ends its outage. One
        from a process restarted by someone else says "starting" or "ready"; any status
        after our restart is new (the dead one's last was delivered long before)."""
        out = self.outages.get(name)
        if out and out[-1]["t_up"] is None and (state in ("starting", "ready") or name in self._restarted):
            out[-1]["t_up"] = self.clock()
            self.event(f"{name} is back")

    def finish(self) -> dict[str, int]:
        """After the children are stopped: each process's first non-zero exit code, else 0."""
        for name, proc in self.children.procs.items():
            if proc.pid not in self._handled and proc.returncode is not None:
                self._handled.add(proc.pid)
                self.codes.setdefault(name, []).append(proc.returncode)
        return {n: next((c for c in cs if c != 0), cs[-1]) for n, cs in self.codes.items()}


def _live_until_done(node: Node, children: Children, sup: "Supervisor", drain, sources: list[str],
                     trackers: list[str], deadline: float, max_delay: float) -> None:
    """A live run (module docstring): until ``deadline`` (UTC), Ctrl-C, or every source
    has ended; then the orderly stop, draining statuses all along."""
    while not node.stop.is_set() and time.time() < deadline:
        drain(0.1)
        sup.poll()
        code = children.procs[FUSER_ID].poll()
        if code is not None and code >= 0 or children.failed():
            break  # the fuser ended on its own, or a child failed (a kill is the supervisor's to restart)
        if all(children.procs[s].poll() is not None for s in sources):
            break
    node.stop.clear()  # Ctrl-C ends a live run like --for; a second one ends the stop sequence
    sup.restart = False
    children.terminate(sources, drain)
    until = time.monotonic() + max_delay + 1.0  # the fuser releases what the sources sent
    while time.monotonic() < until and not node.stop.is_set():
        drain(0.1)
    children.terminate([*trackers, FUSER_ID], drain)
    deadline_rec = time.monotonic() + 30.0  # the recorder ends once it has everyone's last status
    while children.procs[RECORDER_ID].poll() is None and time.monotonic() < deadline_rec and not node.stop.is_set():
        drain(0.1)
    drain(0.2)


def progress_line(scenario, t: float | None, updates: int, sources: dict) -> None:
    """``zfusion run``'s progress on a terminal: scenario time, updates, dead sources."""
    dead = [s for s, r in sources.items() if r.get("dead_intervals") and r["dead_intervals"][-1][1] is None]
    sys.stderr.write(f"\r\033[K{scenario.name}: t = {t or 0.0:.0f} of {scenario.duration:g} s, {updates} updates"
                     + (f", dead: {', '.join(dead)}" if dead else "") + "\r")
    sys.stderr.flush()


def default_rrd(scenario: str, topology: str) -> str:
    stamp = _dt.datetime.now().strftime("%Y%m%d-%H%M%S")
    return str(Path("runs") / f"{scenario}-{topology}-{stamp}.rrd")


def exporter_argv(args) -> dict[str, list[str]]:
    """The ``zfusion export`` children of ``--geojson``/``--cot`` (:data:`OUTPUTS`), each value checked."""
    out = {}
    live = getattr(args, "live", False)  # a live session: the scenario is the site, times are UTC
    for output in OUTPUTS:
        value = getattr(args, output.name, None)
        if value is not None:
            out[output.process_id] = ["export", output.name, output.option, output.prepare(value),
                                      "--site" if live else "--scenario", args.scenario, "--id", output.process_id]
    return out


def run(args) -> int:
    live = getattr(args, "live", False)
    scenario = scenario_of(args)
    if live and args.duration_s is None and args.for_s is not None and args.for_s > scenario.duration:
        scenario = dataclasses.replace(scenario, duration=args.for_s)  # the sources play until --for
    endless = live and args.duration_s is None and args.for_s is None and scenario.endless  # until Ctrl-C
    topology, method = resolve_topology(scenario, args.topology, args.method)
    if args.fusion_rule and method not in TRACK_FUSION_METHODS:
        raise UserError(f"--fusion-rule applies to the track-fusion methods ({', '.join(TRACK_FUSION_METHODS)}), "
                        f"not to {method}")
    overrides = options.overrides(args)
    check_methods(scenario, [method], overrides)  # fail here, with a clear error, not in a child
    tracker_args = [a for k, v in getattr(args, "settings", []) for a in ("--set", f"{k}={json.dumps(v)}")]
    speed = math.inf if args.speed == "max" else float(args.speed)
    rrd = args.rrd or default_rrd(scenario.name, topology)
    exporters = exporter_argv(args)
    Path(rrd).parent.mkdir(parents=True, exist_ok=True)

    keys = KeySpace(args.deployment)
    if args.connect and len(unreachable(args.connect)) == len(args.connect):
        raise UserError(f"--connect {' '.join(args.connect)}: nothing accepts a connection there; start the "
                        f"router first (zfusion router --listen ENDPOINT) or fix the endpoint", FAILURE)
    listen = getattr(args, "listen", None)
    if args.connect or args.zenoh_config:
        mine = ZenohOptions(connect=args.connect or [], config_file=args.zenoh_config,
                            **({"listen": [listen]} if listen else {}))
        theirs = mine
    else:
        hub = listen or f"tcp/127.0.0.1:{free_port()}"
        mine = ZenohOptions(listen=[hub])
        theirs = ZenohOptions(connect=[hub])
    try:
        mine.to_config()
    except (zenoh.ZError, ValueError) as e:
        raise UserError(f"--listen {listen}: not a Zenoh endpoint (e.g. tcp/127.0.0.1:7447)" if listen
                        else zenoh_reason(e)) from None
    endpoint = listen or (None if args.connect or args.zenoh_config else hub)
    common = ["--deployment", args.deployment, *theirs.to_args()] + (["-v"] if args.verbose else [])
    seed = ["--seed", str(scenario.seed)]
    # what the fuser, trackers and recorder are given: the scenario (with its overrides), or live its site
    given = (["--site", args.scenario] if live else
             ["--scenario", args.scenario, *seed, *(["--duration-s", repr(scenario.duration)] if args.duration_s else [])])
    sources = list(scenario.process_ids())
    max_period = max([getattr(s, "period", 1.0) for s in scenario.sensors.values()] + [1.0])
    timeout = MAX_SPEED_TIMEOUT if math.isinf(speed) else max(3.0, 3.0 * max_period / speed)

    scorer = RunScorer(scenario)  # live: replaced once scenario time 0 is known
    statuses: dict[str, dict] = {}
    heard_at: dict[str, float] = {}  # monotonic time of each process's latest status
    usage: dict[str, ProcessUsage] = {}  # each process's CPU time and peak memory, from its statuses
    children = Children()
    interrupted = not_started = False
    failure: str | None = None  # a child that failed on its own, and what it said
    started: list[float] = []  # wall-clock epoch of scenario time 0, once the sources start

    def clock() -> float | None:
        """Scenario time now: by the wall clock when paced, else the latest fused time."""
        if not started:
            return None
        if math.isinf(speed):
            return scorer.last_t if scorer.n else 0.0
        return round((time.time() - started[0]) * speed, 3)

    node = Node(LAUNCHER_ID, "launcher", keys, mine)
    try:
        node.__enter__()
    except zenoh.ZError as e:  # e.g. --listen on a port in use
        raise UserError(f"cannot open the session: {zenoh_reason(e)}") from None
    if endpoint:  # a user's other shell joins the session here (docs/live.md, "The current picture")
        print(f"zfusion run: session at {endpoint} (zfusion picture --connect {endpoint}"
              f"{'' if args.deployment == 'default' else ' --deployment ' + args.deployment})", file=sys.stderr, flush=True)
    with contextlib.closing(node):
        inbox = Inbox(node.stop)

        def event(text: str) -> None:
            node.event(f"t = {clock()} s: {text}")
            node.publish_status("running", clock() or 0.0)

        sup = Supervisor(children, set(), getattr(args, "restart", True), clock, event, fuser_grace=timeout)
        node.subscribe(keys.fused(), inbox)
        node.subscribe(keys.all("status"), inbox)
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
                        scorer.add(to_estimate(msg))
                    elif msg.kind == "status":
                        statuses[msg.src] = msg.body
                        heard_at[msg.src] = time.monotonic()
                        usage.setdefault(msg.src, ProcessUsage()).status(msg.seq, msg.body["counters"])
                        sup.heard(msg.src, msg.body["state"])
            except queue.Empty:
                pass

        try:
            up_since = time.monotonic()
            children.start(FUSER_ID, ["fuser", *given, "--method", method, "--id", FUSER_ID,
                                      "--source-timeout", str(timeout), *tracker_args, *(
                                          ["--max-delay", repr(args.max_delay), "--oosm-window", repr(args.oosm_window)] if live else []), *(
                                          ["--fusion-rule", args.fusion_rule] if args.fusion_rule else []), *common])
            trackers = {s: tracker_id(s) for s in scenario.sensors} if topology != "centralised" else {}
            children.start(RECORDER_ID, ["record", "--rrd", rrd, "--id", RECORDER_ID, *given,
                                         *(["--spawn"] if getattr(args, "spawn", False) else []),
                                         *(["--rotate-s", str(args.rotate_s)] if getattr(args, "rotate_s", None) else []),
                                         "--expect", ",".join([FUSER_ID, *trackers.values(), *sources]), *common])
            for name, argv in exporters.items():  # listeners like the recorder, up before the sources
                children.start(name, [*argv, *common])
            node.wait_for([FUSER_ID, RECORDER_ID, *exporters], timeout=60.0,
                          gone=lambda: children.exited([FUSER_ID, RECORDER_ID, *exporters]))
            startup = time.monotonic() - up_since  # what starting processes takes on this machine now
            for sensor, tid in trackers.items():
                children.start(tid, ["tracker", *given, "--sensor", sensor, "--method", method,
                                     "--fuser", FUSER_ID, "--feedback-timeout", str(timeout), *tracker_args, *(
                                         ["--fusion-rule", args.fusion_rule] if args.fusion_rule else []), *common])
            node.wait_for(trackers.values(), timeout=60.0, gone=lambda: children.exited(trackers.values()))
            sup.restartable = {FUSER_ID, RECORDER_ID, *trackers.values(), *exporters}
            # Scenario time 0 as far ahead as the fuser and recorder took to come up, so that
            # the sources are running by then (a source that starts late sends its first
            # scans in a burst); live, a fixed lead, so that their first scans are not late.
            lead = LIVE_LEAD if live else min(START_LEAD_MAX, max(0.5, startup))
            start_at = time.time() + (0.0 if math.isinf(speed) else lead)
            started.append(start_at)
            if live:  # settles what no re-filtering can correct any more (docs/bounds.md)
                scorer = RunScorer(scenario, start_at, args.oosm_window + args.max_delay + SETTLE_MARGIN)
            for sid in sources:
                # A source waits only for its consumers: the fuser may finish (and vanish)
                # before a truth or jammer process discovers it, so they must not wait for it.
                first = trackers.get(sid, FUSER_ID)
                consumers = [first, RECORDER_ID] if sid in scenario.sensors else [RECORDER_ID]
                children.start(sid, ["sensor", "--scenario", args.scenario, "--id", sid, "--speed", str(args.speed),
                                     "--start-at", repr(start_at), *seed, *(
                                         ["--duration-s", repr(scenario.duration)]
                                         if (live and not endless) or args.duration_s else []),
                                     *(["--live"] if live else []),
                                     "--wait-for", ",".join([*consumers, LAUNCHER_ID]), *common])
            last_source_end: float | None = None
            if live:
                _live_until_done(node, children, sup, drain, sources, [*trackers.values()],
                                 start_at + (args.for_s if args.for_s else math.inf), args.max_delay)
            show = sys.stderr.isatty()  # a progress line on a terminal only
            shown = 0.0
            while not node.stop.is_set() and not live:
                drain(0.1)
                sup.poll()
                if show and time.monotonic() - shown >= 1.0:
                    shown = time.monotonic()
                    progress_line(scenario, clock(), scorer.n, statuses.get(FUSER_ID, {}).get("sources", {}))
                failure = children.failed()
                if failure:  # a child's own error: the run cannot give what was asked
                    break
                code = children.procs[FUSER_ID].returncode
                if code is not None and code >= 0:  # the fuser finished (or failed)
                    break
                if code is not None and not sup.pending(FUSER_ID):
                    # Killed and not restarted by us: a fuser restarted by hand may finish
                    # the run; if none does, it ends a grace period after the sources.
                    if statuses.get(FUSER_ID, {}).get("state") == "done":
                        break
                    if last_source_end is None and all(children.procs[s].poll() is not None for s in sources):
                        last_source_end = time.monotonic()
                    if last_source_end is not None and time.monotonic() - last_source_end > END_GRACE:
                        break
            interrupted = node.stop.is_set()
            failure = children.failed()
            if not interrupted and not live and not failure:
                for sid in [*sources, *trackers.values()]:
                    children.wait(sid, 10.0)
                never_back = [n for n, outs in sup.outages.items() if outs[-1]["t_up"] is None]
                # It may have missed the "done" of processes that ended before it came up, and
                # a process killed and not restarted (--no-restart) sends none: once it
                # reports an empty backlog it has everything; stop it. Otherwise it ends by
                # itself once it has drawn its backlog (at --speed max, seconds of it).
                since, stalled = time.monotonic(), time.monotonic()
                progress = None
                while children.procs[RECORDER_ID].poll() is None and time.monotonic() - stalled < RECORDER_STALL:
                    drain(0.1)
                    counters = statuses.get(RECORDER_ID, {}).get("counters", {})
                    if (counters.get("recorded"), counters.get("backlog")) != progress:
                        progress, stalled = (counters.get("recorded"), counters.get("backlog")), time.monotonic()
                    if (sup.restarts.get(RECORDER_ID) or never_back) and heard_at.get(RECORDER_ID, 0.0) > since + 0.2 \
                            and counters.get("backlog") == 0:
                        break
                drain(0.2)
        except TimeoutError as e:  # a process did not come up (or Ctrl-C while waiting)
            interrupted = node.stop.is_set()
            not_started = not interrupted
            failure = children.failed()
            if not_started and not failure:
                log.error("%s", e)
        finally:
            sup.restart = False
            children.stop_all()
    codes = sup.finish()
    if interrupted:
        print("zfusion run: interrupted; all processes stopped", file=sys.stderr)
        return 130
    if failure:
        print(f"zfusion run: {failure}; all processes stopped", file=sys.stderr)
        return 1
    if not_started:
        print("zfusion run: the run could not start; all processes stopped", file=sys.stderr)
        return 1
    if codes.get(FUSER_ID, 0) > 0:
        print(f"zfusion run: the fuser failed (exit {codes.get(FUSER_ID)})", file=sys.stderr)
        return 1
    fuser_status = statuses.get(FUSER_ID, {})
    src_report = dict(fuser_status.get("sources", {}))
    for sid in sources:  # processes the fuser does not consume (truth, jammers) are reported too
        src_report.setdefault(sid, {"dead_intervals": [], "rejected": 0})
    epoch = started[0] if live else 0.0
    played = scenario  # live: scored over the time the sources played (--for, Ctrl-C), not the whole duration
    if live:
        played = dataclasses.replace(scenario, duration=min(math.inf if endless else scenario.duration,
                                                             scorer.played()))
    doc = run_summary(scenario, topology, method, args.fusion_rule or track_fusion_rule(scenario.tracker, [method]),
                      scorer.method_summary(played), src_report)
    if live:
        doc["epoch_utc"] = epoch
    doc["recording"] = rrd
    doc["recordings"] = sup.recordings or [rrd]
    if getattr(args, "rotate_s", None):  # each recorder's files, in order
        doc["recordings"] = [str(f) for r in doc["recordings"] for f in rotated_files(r)]
    doc["exit_codes"] = codes
    doc["outages"] = sup.outages
    usage.pop(LAUNCHER_ID, None)  # its own status is not the whole of it: measured here, at the end
    doc["processes"] = {**{n: u.report() for n, u in sorted(usage.items())},
                        LAUNCHER_ID: {**own_usage(), "incarnations": 1}}
    print(format_table(doc))
    print(f"recording: {', '.join(doc['recordings']) if getattr(args, 'rotate_s', None) else rrd}")
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
