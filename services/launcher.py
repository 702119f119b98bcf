"""``zfusion run``: one scenario as separate OS processes over Zenoh.

The launcher checks what was asked (:mod:`services.request`), builds the run's
processes (:class:`services.plan.RunPlan`, the list ``zfusion plan`` prints), opens a
Zenoh peer on a free loopback port (the "hub" the children dial; they then find each
other by gossip, no router) and has :class:`services.supervisor.Supervisor` start and
watch them. It collects the fused estimates and the processes' statuses; when the
fuser is done it stops everything, scores the estimates against truth
(:class:`services.summary.RunScorer`: as they settle in a live run, so an endless run
holds a window of them) and prints and writes the summary.

A child that fails on its own (positive exit code) ends the run at once, exit 1, with
its last line; one killed from outside is the supervisor's to restart. On SIGINT/SIGTERM
the launcher stops the children in order. ``--live`` runs the same processes on UTC
time until Ctrl-C, ``--for`` or the sources' end. What each outage does and what the
summary reports: docs/reliability.md ("Faults"); live runs: docs/live.md.
"""

from __future__ import annotations

import contextlib
import dataclasses
import datetime as _dt
import json
import logging
import math
import queue
import random
import socket
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable

import zenoh

from fusion.lazy import lazy
from fusion.methods import TRACK_FUSION_METHODS, track_fusion_rule
from schemas import KeySpace, to_estimate

from .commands import options
from .errors import FAILURE, UserError, zenoh_reason
from .export.outputs import OUTPUTS
from .intake import Intake
from .node import Inbox, Node, Stopped, ZenohOptions
from .plan import FUSER_ID, RECORDER_ID, Asterix, Live, RunPlan, source_timeout
from .request import check_methods, resolve_topology, scenario_of
from .resources import ProcessUsage, own_usage
from .rotation import rotated_files
from .summary import RunScorer, format_table, run_summary
from .supervisor import Children, Supervisor

log = logging.getLogger("zfusion")
asterix_site = lazy("services.ingest.asterix")  # only a run with --asterix needs it

LAUNCHER_ID = "launcher"
END_GRACE = 10.0  # s after the last source ends, when no fuser is left to say it is done
START_LEAD_MAX = 15.0  # s: the most a paced run's sources are given to start (Launch.start)
RECORDER_STALL = 30.0  # s: at the end, the recorder is stopped once it has recorded nothing new this long
RECORDER_DONE_WAIT = 5.0  # s the recorder has to end by itself once everyone else has (it ends on their "done")
# s the sources and trackers have to end by themselves once the fuser is done, beyond the source
# timeout: a tracker cut off from its sensor (stopped past Zenoh's lease) ends a feedback timeout
# (the source timeout) after it is back (services/tracker.py)
END_WAIT = 10.0
END_STALL = 10.0  # s beyond its source timeout a fuser may show no progress once every source has ended
STOP_GRACE = 2.0  # s a process has to stop after SIGTERM before it is killed (it should take < 1 s)
# s the recorder has at the run's end: killed, its file loses its footer and the rows it had not
# flushed; on a loaded machine (five test workers on two cores) it once took more than 5 s
RECORDER_STOP_GRACE = 15.0
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


def free_udp_port() -> int:
    """A loopback UDP port free now (the kernel's pick), for a gateway that binds it a
    moment later."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def asterix_route(scenario_ref: str, scenario, rrd: Path, udp: str) -> Asterix:
    """``--asterix-in``: the scenario with a SAC/SIC for each radar and ADS-B station,
    written beside the recording (``<rrd stem>.asterix.toml``), and the gateway's UDP
    ``HOST:PORT`` they send to; a :class:`UserError` if it cannot be."""
    site = rrd.with_name(f"{rrd.stem}.asterix.toml")
    try:
        return Asterix(str(site), udp, asterix_site.write_site(scenario_ref, scenario, site))
    except ValueError as e:
        raise UserError(f"--asterix-in: {e}") from None
    except OSError as e:
        raise UserError(f"--asterix-in: cannot write {site}: {e.strerror or e}") from None


def _ephemeral_low() -> int:
    """The first port of the kernel's ephemeral range (Linux; 32768 where it cannot be read)."""
    try:
        return int(Path("/proc/sys/net/ipv4/ip_local_port_range").read_text().split()[0])
    except (OSError, ValueError, IndexError):
        return 32768


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


@dataclass(frozen=True)
class Fabric:
    """Where the run's processes meet: the launcher's own Zenoh options, its children's,
    and the endpoint another shell can join the session at (None: a router's)."""

    mine: ZenohOptions
    theirs: ZenohOptions
    endpoint: str | None

    @classmethod
    def of(cls, args) -> "Fabric":
        """From ``--connect``/``--zenoh-config`` (a router's fabric), else a hub on
        ``--listen`` or a free loopback port; a :class:`UserError` if it cannot be used."""
        if args.connect and len(unreachable(args.connect)) == len(args.connect):
            raise UserError(f"--connect {' '.join(args.connect)}: nothing accepts a connection there; start the "
                            f"router first (zfusion router --listen ENDPOINT) or fix the endpoint", FAILURE)
        listen = getattr(args, "listen", None)
        if args.connect or args.zenoh_config:
            mine = ZenohOptions(connect=args.connect or [], config_file=args.zenoh_config,
                                **({"listen": [listen]} if listen else {}))
            fabric = cls(mine, mine, listen)
        else:
            hub = listen or f"tcp/127.0.0.1:{free_port()}"
            fabric = cls(ZenohOptions(listen=[hub]), ZenohOptions(connect=[hub]), hub)
        try:
            fabric.mine.to_config()
        except (zenoh.ZError, ValueError) as e:
            raise UserError(f"--listen {listen}: not a Zenoh endpoint (e.g. tcp/127.0.0.1:7447)" if listen
                            else zenoh_reason(e)) from None
        return fabric


class Launch:
    """A run while it runs: the launcher's node and inbox, the supervisor of its
    children, and what it has heard (fused estimates, statuses, resource usage).

    Args:
        scenario: the scenario as run (its duration what the sources play).
        plan: the run's processes.
        node: the launcher's own process on the fabric (open).
        speed: scenario seconds per wall second (``inf``: ``--speed max``).
        restart: the ``--restart`` policy.
        timeout: the fuser's source timeout (``--start-grace`` of a restarted fuser).
    """

    def __init__(self, scenario, plan: RunPlan, node: Node, speed: float, restart: bool, timeout: float):
        self.scenario = scenario
        self.plan = plan
        self.node = node
        self.speed = speed
        self.scorer = RunScorer(scenario)  # live: replaced once scenario time 0 is known
        self.statuses: dict[str, dict] = {}
        self.heard_at: dict[str, float] = {}  # monotonic time of each process's latest status
        self.usage: dict[str, ProcessUsage] = {}  # each process's CPU time and peak memory, from its statuses
        self.children = Children()
        self.started: float | None = None  # wall-clock epoch of scenario time 0, once the sources start
        self.inbox = Inbox(node.stop)
        self.intake = Intake(node.keys, node.reject, ["fused", "status"])
        self.sup = Supervisor(self.children, plan, restart, self.clock, self.event, fuser_grace=timeout)
        self.timeout = timeout
        self._stalled: tuple[float, int | None] | None = None  # (since, processed) of the fuser once the sources ended
        node.subscribe(node.keys.fused(FUSER_ID), self.inbox)
        node.subscribe(node.keys.all("status"), self.inbox)
        node.announce()

    def clock(self) -> float | None:
        """Scenario time now: by the wall clock when paced, else the latest fused time."""
        if self.started is None:
            return None
        if math.isinf(self.speed):
            return self.scorer.last_t if self.scorer.n else 0.0
        return round((time.time() - self.started) * self.speed, 3)

    def event(self, text: str) -> None:
        self.node.event(f"t = {self.clock()} s: {text}")
        self.node.publish_status("running", self.clock() or 0.0)

    def drain(self, block: float = 0.0) -> None:
        """Take what has come in (waiting up to ``block`` s for the first): fused
        estimates to the scorer, statuses to the supervisor and the usage table."""
        try:
            while True:
                key, data = self.inbox.get(timeout=block) if block else self.inbox.get_nowait()
                block = 0.0
                sample = self.intake.offer(key, data)
                if sample is None:
                    continue
                msg = sample.msg
                if sample.family == "fused":
                    self.scorer.add(to_estimate(msg))
                else:
                    self.statuses[msg.src] = msg.body
                    self.heard_at[msg.src] = time.monotonic()
                    self.usage.setdefault(msg.src, ProcessUsage()).status(msg.seq, msg.body["counters"])
                    self.sup.heard(msg.src, msg.body["state"])
        except queue.Empty:
            pass

    def poll(self) -> None:
        """The supervisor's poll (exits, restarts); each new outage to the scorer, which
        follows the picture's aircraft across it (the outage's absences in the summary)."""
        self.sup.poll()
        for name, outs in self.sup.outages.items():
            for out in outs[len(self.scorer.losses.get(name, ())):]:
                if out["t_down"] is not None:
                    self.scorer.lose(name, out["t_down"])

    def outages(self) -> dict[str, list[dict]]:
        """The supervisor's outages, each with the absences of the picture's aircraft
        across it (:meth:`services.summary.RunScorer.loss`), once the run is scored."""
        return {name: [{**out, **self.scorer.loss(name, k)} if k < len(self.scorer.losses.get(name, ())) else out
                       for k, out in enumerate(outs)] for name, outs in self.sup.outages.items()}

    def start(self, live: Live | None) -> None:
        """Start the consumers, then the sources with scenario time 0 as far ahead as the
        first consumers took to come up, so that the sources are running by then (a source
        that starts late sends its first scans in a burst); live, a fixed lead, so that
        their first scans are not late."""
        startup = self.sup.start_consumers(self.node)
        lead = LIVE_LEAD if live else min(START_LEAD_MAX, max(0.5, startup))
        self.started = time.time() + (0.0 if math.isinf(self.speed) else lead)
        if live:  # settles what no re-filtering can correct any more (docs/bounds.md)
            self.scorer = RunScorer(self.scenario, self.started, live.oosm_window + live.max_delay + SETTLE_MARGIN)
        self.sup.start_sources(self.started)

    def watch(self) -> str | None:
        """A scenario run, until the fuser is done (or a child fails: what it said), the
        run is interrupted, or a fuser killed and not restarted is given up on."""
        children, sup = self.children, self.sup
        sources = self.plan.ids("source")
        show = sys.stderr.isatty()  # a progress line on a terminal only
        shown = 0.0
        last_source_end: float | None = None
        while not self.node.stop.is_set():
            self.drain(0.1)
            self.poll()
            if show and time.monotonic() - shown >= 1.0:
                shown = time.monotonic()
                progress_line(self.scenario, self.clock(), self.scorer.n,
                              self.statuses.get(FUSER_ID, {}).get("sources", {}))
            failure = children.failed()
            if failure:  # a child's own error: the run cannot give what was asked
                return failure
            code = children.procs[FUSER_ID].returncode
            if code is not None and code >= 0:  # the fuser finished (or failed)
                break
            if code is None and self.end_lost(sources):
                waiting = [n for n in (FUSER_ID, *self.plan.ids("tracker")) if children.procs[n].poll() is None]
                text = (f"every source ended {self.timeout + END_STALL:g} s ago and the fuser has processed nothing "
                        f"since (an end it did not hear, or a node waiting for what cannot come): "
                        f"stopping {', '.join(waiting)}")
                log.warning("%s", text)
                self.event(text)
                children.terminate(waiting, self.drain, grace=STOP_GRACE)
                break
            if code is not None and not sup.pending(FUSER_ID):
                # Killed and not restarted by us: a fuser restarted by hand may finish
                # the run; if none does, it ends a grace period after the sources.
                if self.statuses.get(FUSER_ID, {}).get("state") == "done":
                    break
                if last_source_end is None and all(children.procs[s].poll() is not None for s in sources):
                    last_source_end = time.monotonic()
                if last_source_end is not None and time.monotonic() - last_source_end > END_GRACE:
                    break
        return None

    def end_lost(self, sources: list[str]) -> bool:
        """Every source has exited, none is to be restarted, and the fuser's statuses have
        shown nothing more processed since for the source timeout and ``END_STALL`` s
        more: it waits for what will never come — final watermarks lost in a router outage
        or sent before a restarted fuser came up, or a node waiting for an init that
        cannot come, which says its watermark again each second (so "received" grows).
        Not before the timeout: a tracker starved of CPU may be silent that long and is
        waited for. Only statuses heard say so: a fuser busy with a backlog (``--speed
        max``) that sends none is not judged."""
        if any(self.children.procs[s].poll() is None or self.sup.pending(s) for s in sources):
            self._stalled = None
            return False
        status = self.statuses.get(FUSER_ID, {})
        progress = status.get("counters", {}).get("processed")
        now = time.monotonic()
        if self._stalled is None or self._stalled[1] != progress:
            self._stalled = (now, progress)
        return self.heard_at.get(FUSER_ID, 0.0) - self._stalled[0] > self.timeout + END_STALL

    def finish_recorder(self) -> None:
        """The end of a scenario run: the sources and trackers end by themselves; the
        recorder once it has drawn its backlog (at --speed max, seconds of it)."""
        children, stop = self.children, self.node.stop
        wait = END_WAIT + self.timeout
        until = time.monotonic() + wait
        ending = self.plan.ids("source", "tracker")
        while any(children.procs[s].poll() is None for s in ending) and time.monotonic() < until \
                and not stop.is_set():
            self.drain(0.1)
        never_back = self.never_back()
        stuck = [s for s in ending if children.procs[s].poll() is None]
        if stuck and not stop.is_set():  # their last status says "stopped"; one that does not stop is killed
            log.warning("%s did not end %g s after the fuser was done: stopping", ", ".join(stuck), wait)
            children.terminate(stuck, self.drain, grace=STOP_GRACE)
        self.await_recorder(bool(never_back or stuck))

    def never_back(self) -> list[str]:
        """The processes killed and not restarted (their last outage has no ``t_up``)."""
        return [n for n, outs in self.sup.outages.items() if outs[-1]["t_up"] is None]

    def await_recorder(self, missing_done: bool) -> None:
        """Until the recorder ends on everyone's last status ("done"), or has recorded
        nothing new for RECORDER_STALL. It may have missed the "done" of processes that
        ended before it came up, and a process killed and not restarted (--no-restart),
        or one that did not end, sends none (``missing_done``): once it reports an empty
        backlog it has everything; stop it. So too if it has not ended RECORDER_DONE_WAIT
        after everyone else: a "done" it never heard (a process that failed; a status,
        published with congestion control DROP, lost to congestion, or to a lost link)
        does not hold the run."""
        children, stop = self.children, self.node.stop
        missing_done = missing_done or bool(self.sup.restarts.get(RECORDER_ID))  # (its "done"s before: lost)
        since, stalled = time.monotonic(), time.monotonic()
        progress = None
        while children.procs[RECORDER_ID].poll() is None and time.monotonic() - stalled < RECORDER_STALL \
                and not stop.is_set():
            self.drain(0.1)
            counters = self.statuses.get(RECORDER_ID, {}).get("counters", {})
            if (counters.get("recorded"), counters.get("backlog")) != progress:
                progress, stalled = (counters.get("recorded"), counters.get("backlog")), time.monotonic()
            if (missing_done or time.monotonic() > since + RECORDER_DONE_WAIT) and \
                    self.heard_at.get(RECORDER_ID, 0.0) > since + 0.2 and counters.get("backlog") == 0:
                break
        self.drain(0.2)

    def watch_live(self, deadline: float, max_delay: float) -> None:
        """A live run: until ``deadline`` (UTC), Ctrl-C, or every source has ended; then
        the orderly stop (sources, then the fuser and trackers once the fuser has
        released what they sent, then the recorder once it has everyone's last status),
        draining statuses all along."""
        node, children, sup = self.node, self.children, self.sup
        sources = self.plan.ids("source")
        while not node.stop.is_set() and time.time() < deadline:
            self.drain(0.1)
            self.poll()
            code = children.procs[FUSER_ID].poll()
            if code is not None and code >= 0 or children.failed():
                break  # the fuser ended on its own, or a child failed (a kill is the supervisor's to restart)
            if all(children.procs[s].poll() is not None for s in sources):
                break
        node.stop.clear()  # Ctrl-C ends a live run like --for; a second one ends the stop sequence
        sup.restart = False
        children.terminate(sources, self.drain)
        until = time.monotonic() + max_delay + 1.0  # the fuser releases what the sources sent
        while time.monotonic() < until and not node.stop.is_set():
            self.drain(0.1)
        children.terminate([*self.plan.ids("tracker", "fuser")], self.drain)  # the fuser and its standby
        # a process killed and not back (--no-restart) sends no "done": the recorder is not waited for it
        self.await_recorder(bool(self.never_back()))


def progress_line(scenario, t: float | None, updates: int, sources: dict) -> None:
    """``zfusion run``'s progress on a terminal: scenario time, updates, dead sources."""
    dead = [s for s, r in sources.items() if r.get("dead_intervals") and r["dead_intervals"][-1][1] is None]
    sys.stderr.write(f"\r\033[K{scenario.name}: t = {t or 0.0:.0f} of {scenario.duration:g} s, {updates} updates"
                     + (f", dead: {', '.join(dead)}" if dead else "") + "\r")
    sys.stderr.flush()


def default_rrd(scenario: str, topology: str) -> str:
    stamp = _dt.datetime.now().strftime("%Y%m%d-%H%M%S")
    return str(Path("runs") / f"{scenario}-{topology}-{stamp}.rrd")


def run(args) -> int:
    """``zfusion run``: check, plan, start, watch, and report (module docstring)."""
    live = getattr(args, "live", False)
    scenario = scenario_of(args)
    if live and args.duration_s is None and args.for_s is not None and args.for_s > scenario.duration:
        scenario = dataclasses.replace(scenario, duration=args.for_s)  # the sources play until --for
    endless = live and args.duration_s is None and args.for_s is None and scenario.endless  # until Ctrl-C
    topology, method = resolve_topology(scenario, args.topology, args.method)
    if args.fusion_rule and method not in TRACK_FUSION_METHODS:
        raise UserError(f"--fusion-rule applies to the track-fusion methods ({', '.join(TRACK_FUSION_METHODS)}), "
                        f"not to {method}")
    check_methods(scenario, [method], options.overrides(args))  # fail here, with a clear error, not in a child
    rrd = args.rrd or default_rrd(scenario.name, topology)
    outputs = {o.process_id: (o.name, o.option, o.prepare(getattr(args, o.name))) for o in OUTPUTS
               if getattr(args, o.name, None) is not None}
    Path(rrd).parent.mkdir(parents=True, exist_ok=True)
    asterix = asterix_route(args.scenario, scenario, Path(rrd), f"127.0.0.1:{free_udp_port()}") \
        if getattr(args, "asterix_in", False) else None
    fabric = Fabric.of(args)
    live_opts = Live(args.max_delay, args.oosm_window, endless) if live else None
    plan = RunPlan.build(
        args.scenario, scenario, topology, method,
        fabric=["--deployment", args.deployment, *fabric.theirs.to_args()] + (["-v"] if args.verbose else []),
        speed=args.speed, rrd=rrd, supervisor=LAUNCHER_ID, settings=getattr(args, "settings", []),
        fusion_rule=args.fusion_rule, duration=args.duration_s, live=live_opts,
        spawn=getattr(args, "spawn", False), rotate_s=getattr(args, "rotate_s", None), outputs=outputs,
        standby=getattr(args, "standby", False), asterix=asterix)

    node = Node(LAUNCHER_ID, "launcher", KeySpace(args.deployment), fabric.mine, live=live)
    try:
        node.__enter__()
    except zenoh.ZError as e:  # e.g. --listen on a port in use
        raise UserError(f"cannot open the session: {zenoh_reason(e)}") from None
    if fabric.endpoint:  # a user's other shell joins the session here (docs/live.md, "The current picture")
        print(f"zfusion run: session at {fabric.endpoint} (zfusion picture --connect {fabric.endpoint}"
              f"{'' if args.deployment == 'default' else ' --deployment ' + args.deployment})", file=sys.stderr,
              flush=True)
    interrupted = not_started = False
    failure: str | None = None  # a child that failed on its own, and what it said
    with contextlib.closing(node):
        launch = Launch(scenario, plan, node, math.inf if args.speed == "max" else float(args.speed),
                        getattr(args, "restart", True), source_timeout(scenario, args.speed))
        try:
            launch.start(live_opts)
            if live:
                launch.watch_live(launch.started + (args.for_s if args.for_s else math.inf), args.max_delay)
            else:
                failure = launch.watch()
            interrupted = node.stop.is_set()
            failure = launch.children.failed()
            if not interrupted and not live and not failure:
                launch.finish_recorder()
        except Stopped:  # Ctrl-C while a stage came up
            interrupted = True
            failure = launch.children.failed()
        except TimeoutError as e:  # a process did not come up
            not_started = True
            failure = launch.children.failed()
            if not failure:
                log.error("%s", e)
        finally:
            launch.sup.restart = False
            launch.children.stop_all(longer={RECORDER_ID: RECORDER_STOP_GRACE})
    return report(args, launch, scenario, topology, method, rrd, interrupted, failure, not_started, endless)


def report(args, launch: Launch, scenario, topology: str, method: str, rrd: str, interrupted: bool,
           failure: str | None, not_started: bool, endless: bool) -> int:
    """The run's end: why it stopped early (exit 130 or 1), else its summary table, the
    summary JSON and the exit codes of its processes (exit 1 if one failed)."""
    codes = launch.sup.finish()
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
    live = getattr(args, "live", False)
    src_report = dict(launch.statuses.get(FUSER_ID, {}).get("sources", {}))
    for sid in launch.plan.ids("source"):  # processes the fuser does not consume (truth, jammers) are reported too
        src_report.setdefault(sid, {"dead_intervals": [], "rejected": 0})
    played = scenario  # live: scored over the time the sources played (--for, Ctrl-C), not the whole duration
    if live:
        played = dataclasses.replace(scenario, duration=min(math.inf if endless else scenario.duration,
                                                             launch.scorer.played()))
    doc = run_summary(scenario, topology, method, args.fusion_rule or track_fusion_rule(scenario.tracker, [method]),
                      launch.scorer.method_summary(played), src_report)
    if live:
        doc["epoch_utc"] = launch.started
    doc["recording"] = rrd
    doc["recordings"] = launch.sup.recordings or [rrd]
    if getattr(args, "rotate_s", None):  # each recorder's files, in order
        doc["recordings"] = [str(f) for r in doc["recordings"] for f in rotated_files(r)]
        doc["recording"] = doc["recordings"][0] if doc["recordings"] else rrd  # the first file: rrd is only a stem
    doc["exit_codes"] = codes
    doc["outages"] = launch.outages()
    usage = dict(launch.usage)
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
    forced = launch.children.forced
    killed = {n: c for n, c in codes.items() if c is not None and c < 0 and n not in forced}
    if killed:
        print(f"zfusion run: processes killed during the run (see 'sources' in the summary): {killed}",
              file=sys.stderr)
    if forced:  # the run was over: an end slower than the grace (a loaded machine), not an outage
        print(f"zfusion run: processes that did not stop within their grace after SIGTERM, killed at the end: "
              f"{', '.join(sorted(forced))}", file=sys.stderr)
    bad = {n: c for n, c in codes.items() if c not in (0, None) and c > 0}
    if bad:
        print(f"zfusion run: processes ended with errors: {bad}", file=sys.stderr)
        return 1
    return 0
