"""The command-centre fuser process.

Centralised topology: subscribes to every sensor's ``meas/<sensor>`` and runs one
estimation method of ``fusion/`` on the time-ordered measurements. Distributed, feedback
and two-stage topologies: subscribes to every local tracker's ``local/<node>`` and runs
the method's centre (:mod:`fusion.network`) on the time-ordered uplinks, sending priors
down on ``feedback/<node>``. Either way it validates and orders its input
(:class:`~services.ordering.WatermarkMerger`) and publishes its estimates on ``fused``.

It keeps no state on disk: restarted after kill -9, it joins mid-stream at the first scan
it has heard whole (after a watermark of every sensor: ``schedule``), and in the distributed topologies the nodes re-run the start-up
handshake, which rebuilds the common prior and cross-covariances the fusion rules need
(docs/reliability.md, "Faults", says why and what is counted); a regional fuser
restarted with no standby starts from its region's picture, which the system fuser keeps
(:func:`services.leader.rebuild`). It finishes when every
source is final or dead and at least one is final: sources all dead at once (a router
restart) are not the end (if their end is lost, the launcher stops it: docs/reliability.md).
Live (``--site``, docs/live.md): UTC time, no end, stamps from
the future refused, a lagging source waited for at most ``--max-delay`` s, late data
applied by re-filtering (:class:`fusion.oosm.Refiltering`).

:class:`FuserCore` is the whole behaviour without Zenoh: bytes in, estimates out. The
process around it only moves bytes, so tests (and the fuzzer) drive the core and the real
process with the same inputs.
"""

from __future__ import annotations

import functools
import json
import math
import queue
import time
from collections import Counter
from pathlib import Path
from typing import Any, Callable, Mapping

from fusion.lazy import lazy
from fusion.links import InitRequest
from fusion.measurement.kinds import KINDS
from fusion.methods import METHODS, make_method, method_config, split, track_fusion_rule
from fusion.mtt import AssociationConfig
from fusion.network import MultiTrackCentre, TrackCentre
from fusion.regional import RegionalFuser, RegionalMethod, RegionalStage, SystemStage
from fusion.oosm import Refiltering
from fusion.types import Estimate
from schemas import (KeySpace, Message, SchemaError, decode, encode, encode_estimate, to_estimate, to_measurement,
                     tracker_id)
from schemas.links import encode_downlink, encode_regional_frame, horizon_message, regional_frame, uplink

from .errors import UserError
from .intake import HORIZON_SLACK_S, Intake
from .leader import Leadership, rebuild
from .live import ClockGuard, LiveOptions
from .logs import utc_text
from .node import Inbox, Node, Recovery, RejectLog
from .ordering import DEFAULT_MAX_HELD, WatermarkMerger, hold_cap
from .picture import Picture, RegionPictures, pictures
from .plan import standby_id
from .scenario import load, load_site
from .source import recovery_cache

# how long a standby joining a leader (or a regional fuser starting) waits for its picture (a new
# session finds its route by gossip: seconds under load)
JOIN_PATIENCE_S = 5.0

# --json only: the scorer (scipy.stats, the scenario's truth) loads when a summary is written
summary = lazy("services.summary")


class MeasurementIntake:
    """What the fuser (or a local tracker) takes from ``meas/<sensor>``, beyond the wire
    checks of :class:`services.intake.Intake` (the key's family, kind and sender).

    With the scenario's ``sensors`` given, a measurement must also be of its sensor's
    kind and state its sensor's nominal noise std (sensors never state another: jamming
    is not announced in the data): a well-formed message that claims a 1e-300 std, or
    an angle sensor's message on a radar's key, is a configuration error or a forgery,
    and is refused rather than fused (cause ``kind-mismatch`` / ``std-mismatch``). A
    kind whose reports state their own noise (``own_noise``, a cooperative position
    report) is exempt from the std check.
    """

    family = "meas"

    def __init__(self, sensors: Mapping[str, Any] | None = None):
        self.expected = {sid: (s.measurement_kind, tuple(float(v) for v in s.std))
                         for sid, s in (sensors or {}).items()}

    def item(self, key_id: str, msg: Message) -> tuple[str, Any] | tuple[None, str]:
        m = to_measurement(msg)
        if key_id in self.expected:
            kind, std = self.expected[key_id]
            if m.kind != kind:
                return None, f"kind-mismatch:{key_id} is a {kind} sensor, the message is {m.kind}"
            if not KINDS[kind].own_noise and tuple(float(v) for v in m.std) != std:
                return None, f"std-mismatch:{key_id} has std {list(std)}, the message says {list(m.std)}"
        return "item", m


class UplinkIntake:
    """What the fuser of a distributed topology takes from ``local/<node>``; ``nodes`` maps
    tracker id to its sensor, which an uplink must be of."""

    family = "local"

    def __init__(self, nodes: dict[str, str]):
        self.nodes = nodes

    def item(self, key_id: str, msg: Message):
        sensor = self.nodes.get(key_id)
        if sensor is None:
            return None, "unknown-source"
        u = uplink(msg)
        if u.node != sensor:
            return None, f"spoofed-src:uplink of node {u.node!r} sent by {key_id!r}"
        return "item", u


class RegionalIntake:
    """What the system fuser takes from ``regional/<region>``: the frames of the regions'
    fusers (:func:`schemas.links.regional_frame`), one source a region. Each frame taken
    also goes to ``on_frame`` (with its seq), if given: the regions' pictures
    (:class:`services.picture.RegionPictures`)."""

    family = "regional"

    def __init__(self, regions: Mapping[str, Any], on_frame: Callable[[Any, int], None] | None = None):
        self.nodes = dict(regions)
        self.on_frame = on_frame

    def item(self, key_id: str, msg: Message):
        if key_id not in self.nodes:
            return None, "unknown-source"
        frame = regional_frame(msg)
        if self.on_frame is not None:
            self.on_frame(frame, msg.seq)
        return "item", frame


class JoinGate:
    """A track centre (HNV, PHHNV, DDHNV) behind a gate: a report from a node the centre
    has not given an initial state is dropped (the node of a restarted fuser, before it
    has re-run the handshake; module docstring). Everything else passes through. Each
    node's join is an event naming the scan of the request it joined with: the nodes of
    a restarted fuser may rejoin at different scans, and the output from there is the
    in-process run on each node's data from its join on."""

    def __init__(self, centre: TrackCentre, reject: RejectLog, event: Callable[[str], None]):
        self.centre = centre
        self.reject = reject
        self.event = event
        self._asked: dict[str, float] = {}  # node -> the time of its first pending request

    def process(self, u) -> list[Estimate]:
        if isinstance(u, InitRequest):
            self._asked.setdefault(u.node, u.t)
        elif u.node not in self.centre.nodes and u.node not in self._asked:  # (asked: joins with its group)
            self.reject(tracker_id(u.node), "not-joined", f"report at t = {u.t:g} s from {u.node}, which has "
                        f"no initial state from this fuser yet")
            return []
        return self._joins(self.centre.process, u)

    def advance(self, t: float) -> list[Estimate]:
        return self._joins(self.centre.advance, t)

    def finish(self) -> list[Estimate]:
        return self._joins(self.centre.finish)

    def _joins(self, step: Callable[..., list[Estimate]], *args: Any) -> list[Estimate]:
        members = set(self.centre.nodes)
        out = step(*args)
        for node in sorted(self.centre.nodes - members):
            self.event(joined(node, self._asked.pop(node)))
        return out

    def __getattr__(self, name: str) -> Any:
        if name.startswith("__"):  # copy/pickle protocol lookups, before ``centre`` exists
            raise AttributeError(name)
        return getattr(self.centre, name)


class FirstRequests(JoinGate):
    """A many-target centre's joins: each node's first initialisation request an event,
    as :class:`JoinGate`'s. It needs no gate: a report of a local track this centre did
    not name is dropped by the centre, and its node told to drop it
    (:class:`fusion.network.MultiTrackCentre`). A restarted fuser's nodes drop their
    tracks and send their plots up as requests from the scan they join with; the output
    from there is the in-process run on each node's data from that scan on."""

    def process(self, u) -> list[Estimate]:
        if isinstance(u, InitRequest) and u.node not in self._asked:
            self._asked[u.node] = u.t
            self.event(joined(u.node, u.t))
        return self.centre.process(u)

    def advance(self, t: float) -> list[Estimate]:
        return self.centre.advance(t)

    def finish(self) -> list[Estimate]:
        return self.centre.finish()


def joined(node: str, t: float) -> str:
    """The event of a node's join: the scan of the request it joined with."""
    return f"{tracker_id(node)} joined with its request at t = {t:g} s"


class FuserCore:
    """Validate, order and estimate.

    Args:
        method: an object with ``process`` / ``advance`` / ``finish``.
        sources: the ids this fuser waits for (sensors, or local trackers).
        keys: the deployment's key space (to check that ``src`` matches the key).
        reject: where rejections are counted.
        timeout, start_grace: see :class:`~services.ordering.WatermarkMerger`.
        horizon: data (and watermarks) beyond this scenario time are ``future``, and
            data before 0 ``past`` (:class:`services.intake.Intake`; live: neither).
        intake: what the input is (:class:`MeasurementIntake` by default).
        max_held: the merger's per-source cap (:func:`max_held_for` a scenario).
        live: a live session (:class:`~services.live.LiveOptions`): no horizon, stamps
            checked against ``utc`` (:meth:`offer`), a bounded wait for lagging sources,
            and late data re-filtered (:class:`fusion.oosm.Refiltering`) when
            ``refilter`` is true; without it the merger waits for every live source
            (a centre that sends feedback cannot take it back).
        periods: live: each source's nominal period, how far ahead of its data its
            watermarks may look (:meth:`services.live.ClockGuard.check`).
        schedule: a scenario run's sensors: each one's (first scan time, period). A
            sensor first heard from its second scan on was joined mid-way (a restarted
            fuser or tracker): what is held up to its first watermark heard, of any
            sensor, may be part of a scan and is dropped (:meth:`WatermarkMerger.join`),
            so the core starts from the first scan it has heard whole.
    """

    def __init__(self, method: Any, sources: list[str], keys: KeySpace, reject: RejectLog,
                 timeout: float, start_grace: float = 30.0, horizon: float = math.inf, now: float = 0.0,
                 intake: Any = None, max_held: int | None = None, live: LiveOptions | None = None,
                 refilter: bool = True, periods: Mapping[str, float] | None = None,
                 schedule: Mapping[str, tuple[float, float]] | None = None):
        self.keys = keys
        self.reject = reject
        self.intake = intake or MeasurementIntake()
        self.wire = Intake(keys, reject, [self.intake.family], horizon=math.inf if live else horizon,
                           earliest=-math.inf if live else 0.0)
        self.live = live
        self.refilter = Refiltering(method, live.oosm_window, shared=(reject,)) if live and refilter else None
        self._method = method
        bounded = self.refilter is not None
        self.merger = WatermarkMerger(sources, timeout, start_grace, now, max_held=max_held or DEFAULT_MAX_HELD,
                                      max_delay=live.max_delay if bounded else math.inf,
                                      oosm_window=live.oosm_window if bounded else 0.0)
        self.clock = ClockGuard(live.max_skew) if live else None
        self.periods = dict(periods or {})
        self.schedule = dict(schedule or {})
        self._heard: set[str] = set()  # scheduled sources heard
        self._midway: set[str] = set()  # ... first heard mid-stream, until their first watermark
        self.republished = 0  # estimates re-published after a re-filtering
        self.unpublished: Counter[str] = Counter()  # outputs the wire refused, by cause (:meth:`encoded`)
        self.events: list[str] = []
        self.received = 0
        self.processed = 0
        self.finished = False

    @property
    def method(self) -> Any:
        """The estimator now (a re-filtering replaces it with a restored copy)."""
        return self.refilter.method if self.refilter is not None else self._method

    @method.setter
    def method(self, method: Any) -> None:
        """Swap the estimator of a core that re-filters nothing (benchmarks time the shell)."""
        if self.refilter is not None:
            raise ValueError("a re-filtering core's estimator is restored from its checkpoints")
        self._method = method

    def offer(self, key: str, data: bytes, now: float, utc: float | None = None) -> Message | None:
        """One sample off the wire (``now``: monotonic clock; ``utc``: this host's UTC
        clock, live). Bad input is counted and dropped; never raises. Returns the message
        if the wire intake took it (whether or not it was then accepted), else None."""
        self.received += 1
        sample = self.wire.offer(key, data)
        if sample is None:
            return None
        msg = sample.msg
        st = self.merger.sources.get(msg.src)
        if self.clock is not None and utc is not None and st is not None and st.dead:
            # Heard again after it was declared dead: what it sent while cut off comes now, given
            # back by its publisher; that is its data stamped more than its usual lag (before the
            # outage) and one period before now.
            lag = self.clock.report(msg.src)["lag_s"] or 0.0
            st.recovery_until = utc - lag - self.periods.get(msg.src, 0.0)
        if self.clock is not None and utc is not None and msg.src in self.merger.sources:
            rej = self.clock.check(msg.src, msg.t, utc, self.events,
                                   self.periods.get(msg.src, 0.0) if msg.kind == "watermark" else None)
            if rej is not None:
                self.reject(rej.src, rej.cause, rej.detail)
                return msg
        if msg.kind == "watermark":
            rej = self.merger.watermark(msg.src, msg.t, msg.body["final"], now, self.events)
        else:
            what, item = self.intake.item(sample.ident, msg)
            if what is None:
                cause, _, detail = item.partition(":")
                self.reject(sample.ident, cause, detail or f"{msg.kind!r} is not expected on {key}")
                return msg
            rej = self.merger.add(msg.src, msg.t, msg.seq, item, now, self.events)
        if rej is not None:
            self.reject(rej.src, rej.cause, rej.detail)
        elif msg.src in self.schedule:
            self._scheduled(msg)
        return msg

    def _scheduled(self, msg: Message) -> None:
        """A scheduled sensor's message, taken: the first says whether this core joined its
        stream mid-way (a measurement of its second scan or later, or the watermark after
        it); then its first watermark is where this core has all of it."""
        if msg.src not in self._heard:
            self._heard.add(msg.src)
            start, period = self.schedule[msg.src]
            # A watermark looks ahead to just before the next scan (services/source.py).
            if (msg.t - start) / period > (1.5 if msg.kind == "watermark" else 0.5):
                self._midway.add(msg.src)
        if msg.kind == "watermark" and msg.src in self._midway:
            self._midway.discard(msg.src)
            n = self.merger.join(msg.t)
            self.events.append(f"joined {msg.src}'s stream mid-way (first watermark heard: {msg.t:g} s); "
                               f"fusing from the first scan heard whole ({n} held measurements dropped)")

    def end(self, src: str, now: float) -> float:
        """Take ``src``'s stream as ended without its final watermark (a tracker whose
        sensor's process is gone, its end not heard): what it sent is released as if that
        watermark had come with its last data. Returns the time of that end."""
        st = self.merger.sources[src]
        t = max([st.watermark, *(t for t, _, _ in st.held[-1:]), 0.0])  # (a scenario's time: from 0)
        self.merger.watermark(src, t, True, now, self.events)
        return t

    def step(self, now: float) -> list[Estimate]:
        """Release what the watermarks allow and run the method on it."""
        if self.finished:
            return []
        self.merger.check_timeouts(now, self.events)
        items, wm = self.merger.release(now)
        if items and not self.processed:  # t > 0 for a fuser restarted mid-stream
            self.events.append(f"input starts at {utc_text(items[0].t)}" if self.live is not None
                               else f"input starts at t = {items[0].t:g} s")
        out: list[Estimate] = []
        if self.refilter is not None:
            late = self.merger.take_oosm()  # all at or before the previous release: re-filter first
            if late:
                fixed = self.refilter.insert(late)
                self.republished += len(fixed)
                out.extend(fixed)
                self.processed += len(late)
            out.extend(self.refilter.step(items, wm))
            self.processed += len(items)
            return out
        for m in items:
            out.extend(self.method.process(m))
            self.processed += 1
        if math.isfinite(wm):
            out.extend(self.method.advance(wm))
        if self.merger.done and any(st.final for st in self.merger.sources.values()):
            out.extend(self.method.finish())
            self.finished = True
        return out

    def encoded(self, encode: Callable[..., bytes], *args: Any) -> bytes | None:
        """``encode(*args)``: an estimate or downlink as the wire carries it; None if the
        wire refuses it (an estimator's output the schema cannot carry), counted by cause
        in :attr:`unpublished` (the first of each cause said in an event) and dropped, so
        that nothing the estimator emits can stop the process."""
        try:
            return encode(*args)
        except SchemaError as e:
            self.unpublished[e.cause] += 1
            if self.unpublished[e.cause] == 1:
                self.events.append(f"output not published ({e.cause}): {e}")
            return None

    def sources_report(self) -> dict:
        """Per source: dead intervals and rejections; live also ``oosm``, ``stale`` and its
        clock (:meth:`services.live.ClockGuard.report`)."""
        rejected = self.reject.rejected_by_source()
        out = {}
        for s, st in self.merger.sources.items():
            out[s] = {"dead_intervals": st.dead_intervals, "rejected": rejected.get(s, 0)}
            if self.live is not None:
                out[s].update(oosm=st.oosm, stale=st.stale, recovered=st.recovered, missed=st.missed,
                              **self.clock.report(s))
        return out


def max_held_for(scenario, window: float | None = None) -> int:
    """The merger's per-source cap: 10× what the busiest sensor sends in ``window``
    seconds (targets plus mean clutter per scan; a site's sensors count one target).
    Default window: a scenario's whole run, since at ``--speed max`` a source may
    legitimately run that far ahead of a late one; live, the source timeout, after
    which a laggard is declared dead (:func:`services.ordering.hold_cap`)."""
    traffic = scenario.traffic.max_alive if getattr(scenario, "traffic", None) is not None else 0
    rate = max((max(len(s.targets) + traffic, 1) + s.clutter_rate) / s.period for s in scenario.sensors.values())
    return hold_cap(rate, (scenario.duration if window is None else window) + 1.0)


def _schedule(scenario) -> dict[str, tuple[float, float]]:
    """Each sensor's (first scan time, period): :class:`FuserCore`'s ``schedule``."""
    return {sid: (s.start, s.period) for sid, s in scenario.sensors.items()}


def _delete_misses(scenario) -> int:
    """Frames without a report after which a track has left the picture: the trackers' rule."""
    association, _ = AssociationConfig.split(scenario.tracker)
    return (association or AssociationConfig).delete_misses


def run(process_id: str, scenario_ref: str, method_name: str, overrides: dict, keys: KeySpace, zopts,
        timeout: float, start_grace: float, seed: int | None = None, live: LiveOptions | None = None,
        duration: float | None = None, json_path: str | None = None, standby_for: str | None = None,
        region: str | None = None, system: bool = False) -> int:
    """The fuser of a scenario run (``scenario_ref``), or of a live session (``live``
    given: ``scenario_ref`` is a site or scenario file, time is UTC, it runs until stopped).
    ``standby_for``: a hot standby of that fuser (:mod:`services.leader`): the same work,
    published under that fuser's identity only once it leads.
    ``region``: the regional fuser of that ``[regions]`` entry (its id is the region's
    name; its standby's, ``standby_for`` the region, another), publishing regional frames
    and their watermarks on ``regional/<region>``;
    ``system``: the system fuser over every region's fuser (:mod:`fusion.regional`),
    which also keeps each region's picture and answers ``picture/<region>`` with it; a
    regional fuser that finds no older member of its region running (started again with
    no standby to take over) rebuilds its tracks from that picture, as a standby joining
    a leader does from the leader's (:func:`services.leader.rebuild`).
    ``json_path``: a scenario run's summary, scored against its truth, written there when
    done (the result of a deployment started by hand; it keeps every estimate until then)."""
    scenario = load(scenario_ref, seed, duration) if live is None else load_site(scenario_ref)
    if (region is not None or system) and not scenario.regions:
        raise UserError(f"{scenario_ref} has no [regions.<name>] tables: no regional topology (docs/regional.md)")
    if region is not None and region not in scenario.regions:
        raise UserError(f"--region {region}: {scenario_ref} has regions {', '.join(scenario.regions)}")
    if standby_for is not None and process_id == standby_for:
        raise UserError(f"--standby {standby_for}: a standby's --id is its own, not its fuser's (e.g. "
                        f"{standby_id(standby_for)})")
    if region is not None and standby_for is not None and standby_for != region:
        raise UserError(f"--region {region} --standby {standby_for}: a regional fuser stands by for its region's "
                        f"fuser only (--standby {region})")
    if region is not None and standby_for is None and process_id != region:
        raise UserError(f"--region {region}: a regional fuser's --id is its region's name, not {process_id!r}")
    if system and (standby_for or process_id) in scenario.regions:
        raise UserError(f"--system: {standby_for or process_id!r} is a region's fuser, not the system fuser")
    config = method_config(scenario.tracker, method_name, overrides)
    distributed = METHODS[method_name].split is not None
    stage: RegionalStage | None = None
    regions_seen: RegionPictures | None = None  # the system fuser's pictures of the regions' streams
    if region is not None:  # one region's centralised tracker, its frames for the system fuser
        stage = method = RegionalStage(RegionalFuser(scenario.regions[region], make_method(method_name, config)))
        sensors = {s: scenario.sensors[s] for s in scenario.regions[region].sensors}
        intake: Any = MeasurementIntake(sensors)
        sources = list(sensors)
        periods = {s: sensors[s].period for s in sources}
    elif system:  # the system picture from the regional fusers' frames
        method = SystemStage(RegionalMethod.system_fuser(method_name, config, scenario.regions))
        regions_seen = RegionPictures(scenario.regions)
        intake = RegionalIntake(scenario.regions, regions_seen.frame)
        sources = list(scenario.regions)
        periods = {r: min(scenario.sensors[s].period for s in scenario.regions[r].sensors) for r in sources}
    elif distributed:  # distributed, feedback, two-stage: the centre over the local trackers
        method = split(method_name).centre(config)
        nodes = {tracker_id(s): s for s in scenario.sensors}
        intake = UplinkIntake(nodes)
        sources = list(nodes)
        periods = {src: scenario.sensor(nodes[src]).period for src in sources}
    else:
        method = make_method(method_name, config)
        intake = MeasurementIntake(scenario.sensors)
        sources = list(scenario.sensors)
        periods = {src: scenario.sensor(src).period for src in sources}
    schedule = {s: v for s, v in _schedule(scenario).items() if s in sources} \
        if live is None and not distributed and not system else None
    with Node(process_id, "fuser", keys, zopts, live=live is not None) as node:
        inbox = Inbox(node.stop)
        for queryable in regions_seen.serve(node.session, keys) if regions_seen is not None else ():
            node.keep(queryable)  # at once: a regional fuser's start waits for its region's picture
        if isinstance(method, (TrackCentre, MultiTrackCentre)):
            gate = JoinGate if isinstance(method, TrackCentre) else FirstRequests
            method = gate(method, node.reject, node.event)
        identity = standby_for or process_id  # the fuser consumers take the fused output of
        utc = time.time if live is not None else lambda: None
        recovery = Recovery(node.processes_by_session()) if live is not None else None
        # a regional fuser hears its region's sensors only; the others, every source of its family
        heard = [keys.meas(s) for s in sources] if stage is not None else [keys.all(intake.family)]
        if recovery is not None:  # live sensors' and trackers' publishers give back what a cut-off missed
            for key in heard:  # (a standby, a regional fuser: what they sent before, too, for a rebuild below)
                node.recovering_subscriber(key, inbox, recovery.on_miss,
                                           history=standby_for is not None or stage is not None)
            # Its own streams too: a release is at most one estimate per measurement (or uplink) taken.
            cache = sum(recovery_cache(scenario, s) for s in scenario.sensors)
            publisher = functools.partial(node.recoverable_publisher, cache=cache)
        else:
            for key in heard:
                node.subscribe(key, inbox)
            publisher = node.publisher
        # The election once the session's links have settled: a member not yet linked is not yet seen.
        leader = Leadership(node.session, keys, identity, standby_for is not None, start_grace, node.event, node.stop)
        node.keep(leader)
        # Joining a running leader: its tracks from its picture, asked before this process serves its own. A
        # regional fuser with no leader to join (started again, no standby): its region's, the system fuser's.
        asks = leader.joins if stage is None else not leader.joins
        found = pictures(node.session, keys, identity, JOIN_PATIENCE_S) if asks else []
        rebuilt = rebuild(method, found[0]) if found else None
        whose = "the leader's picture" if stage is None else f"{identity}'s picture (the system fuser's)"
        feedback = METHODS[method_name].topology in ("feedback", "two-stage")  # its centre's feedback is final
        core = FuserCore(method, sources, keys, node.reject, timeout, start_grace,
                         horizon=scenario.duration + HORIZON_SLACK_S if live is None else math.inf, now=time.monotonic(),
                         intake=intake, max_held=max_held_for(scenario, None if live is None else timeout),
                         live=live, refilter=not feedback and stage is None and not system, periods=periods,
                         schedule=schedule)
        seq = down_seq = 0
        if rebuilt is not None:
            core.merger.join(rebuilt.t)
            seq = rebuilt.seq
            node.event(f"rebuilt {', '.join(rebuilt.tracks)} from {whose} (seq {rebuilt.seq}); fusing "
                       f"what comes after {utc_text(rebuilt.t) if live is not None else f't = {rebuilt.t:g} s'}")
        elif found and found[0]["tracks"]:
            node.event(f"{method_name}'s tracks cannot be rebuilt from {whose}: starting from the "
                       f"first scan heard")
        pub = publisher(keys.regional(identity) if stage is not None else keys.fused(identity))
        encoder = encode_regional_frame if stage is not None else encode_estimate
        frames_through = -math.inf  # a regional fuser: the watermark of its frames published last
        picture = Picture(identity, _delete_misses(scenario))
        if stage is None:  # a regional fuser's frames are no picture: it answers no `zfusion picture`
            node.keep(picture.serve(node.session, keys))
        down = {tid: publisher(keys.feedback(tid)) for tid in (intake.nodes if distributed else ())}
        # Each downlink says which process and incarnation sent it: a node sees a restarted
        # fuser in its first downlink, whichever path its liveliness token takes (services.tracker).
        sender = f"{process_id}/{node.session.zid()}".encode()
        node.announce()
        node.publish_status("ready")
        kept: list[Estimate] | None = [] if json_path and live is None else None
        horizon = -math.inf
        last_status = 0.0
        t_now = 0.0
        while not node.stop.is_set():
            try:
                key, data = inbox.get(timeout=0.05)
                core.offer(key, data, time.monotonic(), utc())
                while True:  # drain what is queued before stepping: fewer, larger releases
                    key, data = inbox.get_nowait()
                    core.offer(key, data, time.monotonic(), utc())
            except queue.Empty:
                pass
            leader.check()
            for e in core.step(time.monotonic()):
                data = core.encoded(encoder, e, identity, seq + 1)
                if data is None:
                    continue
                seq += 1
                if leader.leads:
                    pub.put(data)
                t_now = e.t
                if stage is not None:
                    continue
                if kept is not None:
                    kept.append(to_estimate(decode(data)))  # what a listener gets
                picture.published(e, data)
            if stage is not None:  # how far its frames are complete, for the system fuser's merge
                through = max(stage.watermark(), t_now) if core.finished else stage.watermark()
                if through > frames_through or core.finished:
                    frames_through = max(frames_through, through)
                    seq += 1
                    if leader.leads:
                        pub.put(encode("watermark", identity, seq, frames_through, final=core.finished))
            if down:
                method = core.method
                for d in method.take_downlinks():
                    data = core.encoded(encode_downlink, d, identity, down_seq + 1)
                    if data is not None:
                        down_seq += 1
                        if leader.leads:
                            down[tracker_id(d.node)].put(data, attachment=sender)
                # Fed-back nodes, and every many-target node, wait for the horizon; said again
                # each second for a node that missed it (stopped, or restarting its handshake)
                # and would wait for its feedback timeout, holding the merge back meanwhile.
                again = time.monotonic() - last_status >= 1.0
                if math.isfinite(method.horizon) and (method.horizon > horizon or again):
                    horizon = method.horizon
                    down_seq += 1
                    for p in down.values() if leader.leads else ():
                        p.put(horizon_message(identity, down_seq, horizon), attachment=sender)
            for src, n in recovery.take_misses() if recovery is not None else ():
                if src in core.merger.sources:
                    core.merger.sources[src].missed += n
                    core.events.append(f"source {src}: {n} samples lost (beyond its publisher's cache)")
            for ev in core.events:
                node.event(ev)
            core.events.clear()
            node.counters.update(received=core.received, processed=core.processed, published=seq,
                                 late=core.merger.late, held=core.merger.held(),
                                 inbox=inbox.qsize(), inbox_waits=inbox.waits,
                                 unpublished=sum(core.unpublished.values()), leads=int(leader.leads),
                                 takeovers=leader.takeovers, yielded=leader.yielded,
                                 **{f"unpublished.{c}": n for c, n in core.unpublished.items()})
            if core.refilter is not None:
                node.counters.update(oosm=sum(st.oosm for st in core.merger.sources.values()),
                                     republished=core.republished, checkpoints=len(core.refilter))
            if core.finished:
                break
            if time.monotonic() - last_status >= 1.0:
                node.publish_status("running", t_now, sources=core.sources_report())
                last_status = time.monotonic()
        node.publish_status("done" if core.finished else "stopped", t_now, sources=core.sources_report())
    if kept is not None and core.finished:
        _write_result(json_path, scenario, method_name, config, kept, core.sources_report())
    return 0


def _write_result(path: str, scenario, method: str, config: Mapping, estimates: list[Estimate],
                  sources: dict) -> None:
    """``--json``: the run's summary, as ``zfusion run --json`` writes it, and its table on stdout."""
    rule = (config.get("fusion_rule") if METHODS[method].fuses_tracks else None) or track_fusion_rule(
        scenario.tracker, [method])
    for sid in scenario.process_ids():  # processes the fuser does not consume (truth, jammers) too
        sources.setdefault(sid, {"dead_intervals": [], "rejected": 0})
    scorer = summary.RunScorer(scenario)
    for e in estimates:
        scorer.add(e)
    doc = summary.run_summary(scenario, METHODS[method].topology, method, rule, scorer.method_summary(), sources)
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    Path(path).write_text(json.dumps(doc, indent=1))
    print(summary.format_table(doc), flush=True)
