"""A local tracker process: one sensor's node of the distributed topologies.

Subscribes to its sensor's ``meas/<sensor>`` (validated and time-ordered like the
fuser's input, by the same :class:`~services.fuser.FuserCore`) and to
``feedback/<node>`` from the fuser; runs the method's local node
(:mod:`fusion.network`) and publishes its uplinks and watermarks on ``local/<node>``.

If the fuser does not answer (no initial state, no feedback) for ``--feedback-timeout``
seconds, the node runs on alone — updating from its own last estimate, or starting
from its own measurement — and says so in its status events; when downlinks come
back it takes them again.

In a scenario run its sensor's stream ends with a final watermark. If the sensor's
process is gone (no liveliness token of it, while other processes' tokens are seen: the
tracker is not cut off) for ``--feedback-timeout`` seconds and its end was not heard,
the stream is taken as ended at its last data: a tracker paused for longer than Zenoh's
lease loses its link to the sensor, and what the sensor sent meanwhile, its end too;
waiting for it would hold the fuser's merge for ever. Sensors are never restarted in a
scenario run; live, the tracker waits for its sensor.

A *restarted* fuser (a liveliness token of a new incarnation, i.e. Zenoh session, of
the fuser appears, or a downlink whose attachment names one) knows nothing of this node: the node drops its tracks (one, or a
many-target node's ``L<n>`` and ``A<n>``) and re-runs the initialisation handshake,
sending its next plots up as requests (:mod:`services.fuser`, "Restart"). A restarted
tracker is a new node to the fuser: it asks to join and starts from the latest fused
state.
"""

from __future__ import annotations

import math
import queue
import time

import zenoh
from fusion.methods import method_config, split
from schemas import KeySpace, Message, encode, tracker_id
from schemas.links import downlink, encode_uplink

from .fuser import FuserCore, MeasurementIntake
from .intake import HORIZON_SLACK_S, Intake
from .live import LiveOptions
from .errors import UserError
from .node import Inbox, Node, Recovery, Stopped
from .scenario import load, load_site
from .source import recovery_cache


# A node says its watermark again this often while it has nothing new to promise (waiting
# for an init or feedback): it is not silent, which its fuser would take for dead after
# its source timeout (3 s for trackers), passing over the request it waits on.
ALIVE_S = 1.0
ALIVE_MAX = 4096  # liveliness tokens kept (the deployment's processes; more are not tracked)
RETIRED_MAX = 1024  # replaced fuser incarnations remembered (restarts; more are not remembered)


class _Feed:
    """The method FuserCore drives: ordered measurements go into the node's queue."""

    def __init__(self, node):
        self.node = node
        self.watermark = -math.inf
        self.finished = False

    def process(self, m):
        self.node.offer(m)
        return []

    def advance(self, t):
        self.watermark = max(self.watermark, t)
        self.node.set_watermark(t)  # closes a many-target node's frames
        return []

    def finish(self):
        self.finished = True
        self.node.set_watermark(math.inf)  # the sensor's stream has ended: its last frame is complete
        return []


def run(sensor: str, scenario_ref: str, method_name: str, overrides: dict, keys: KeySpace, zopts,
        fuser_id: str, feedback_timeout: float, start_grace: float, seed: int | None = None,
        live: LiveOptions | None = None, duration: float | None = None) -> int:
    """A scenario run's tracker, or (``live`` given, ``scenario_ref`` a site) a live
    session's: UTC time, no end, stamps from the future refused. Its one sensor is in
    order by itself, so it has no bounded wait and no out-of-sequence data."""
    scenario = load(scenario_ref, seed, duration) if live is None else load_site(scenario_ref)
    if sensor not in scenario.sensors:
        raise UserError(f"{sensor!r} is not a sensor of {scenario.name} "
                         f"(sensors: {', '.join(scenario.sensors)})")
    me = tracker_id(sensor)
    config = method_config(scenario.tracker, method_name, overrides)
    local = split(method_name).node(sensor, config)
    feed = _Feed(local)
    fuser_token: queue.SimpleQueue[str] = queue.SimpleQueue()  # incarnations of the fuser that appeared
    tokens: queue.SimpleQueue[tuple[bool, str, str]] = queue.SimpleQueue()  # (up, process, incarnation)
    with Node(me, "tracker", keys, zopts, live=live is not None) as node:
        inbox = Inbox(node.stop)
        # Its one sensor is never declared dead here: the tracker waits for it to come back
        # (the fuser, meanwhile, declares this tracker dead and carries on without it).
        core = FuserCore(feed, [sensor], keys, node.reject, math.inf, start_grace,
                         horizon=scenario.duration + HORIZON_SLACK_S if live is None else math.inf, now=time.monotonic(),
                         intake=MeasurementIntake(scenario.sensors), live=live, refilter=False,
                         periods={sensor: scenario.sensor(sensor).period},
                         schedule=None if live is not None else {sensor: (scenario.sensor(sensor).start,
                                                                          scenario.sensor(sensor).period)})
        utc = time.time if live is not None else lambda: None
        recovery = None
        last_sender: list[str] = []  # the fuser incarnation that sent the latest downlink

        def on_downlink_sample(sample: zenoh.Sample) -> None:
            """Zenoh's callback for a downlink: first the incarnation of the fuser that sent
            it (its attachment, ``<process>/<session id>``), so that a restarted fuser's
            first downlink restarts the handshake before it is applied even when its
            liveliness token, on another path through the fabric, comes later (a node that
            took the new fuser's horizon first sent its old tracks' reports, which the new
            centre drops, instead of its plots as requests). A standby's downlinks (another
            process) change nothing: it continues the leader's centre."""
            try:
                process, _, incarnation = (sample.attachment.to_bytes() if sample.attachment is not None
                                           else b"").decode().partition("/")
            except UnicodeDecodeError:
                process = incarnation = ""
            if process == fuser_id and incarnation and last_sender != [incarnation]:
                last_sender[:] = [incarnation]
                fuser_token.put(incarnation)
            inbox(sample)

        if live is not None:  # live: its sensor's and the fuser's publishers give back what a cut-off missed
            recovery = Recovery(node.processes_by_session())
            node.recovering_subscriber(keys.meas(sensor), inbox, recovery.on_miss)
            node.recovering_subscriber(keys.feedback(me), on_downlink_sample, recovery.on_miss)
            # Its uplinks: at most one per measurement of its sensor, and a watermark per scan.
            pub = node.recoverable_publisher(keys.local(me), recovery_cache(scenario, sensor))
        else:
            node.subscribe(keys.meas(sensor), inbox)
            node.subscribe(keys.feedback(me), on_downlink_sample)
            pub = node.publisher(keys.local(me))
        watch = node.session.liveliness().declare_subscriber(
            keys.alive(fuser_id),
            lambda s: s.kind == zenoh.SampleKind.PUT and fuser_token.put(keys.alive_process(str(s.key_expr))[1]),
            history=True)

        def on_token(s: zenoh.Sample) -> None:
            try:
                tokens.put((s.kind == zenoh.SampleKind.PUT, *keys.alive_process(str(s.key_expr))))
            except ValueError:
                pass  # (not a process's token)

        alive_watch = node.session.liveliness().declare_subscriber(keys.all("alive"), on_token, history=True) \
            if live is None else None  # (live: the tracker waits for its sensor)
        try:  # be reachable from the fuser before a sensor (waiting for this token) starts
            node.wait_for([fuser_id], 60.0)
        except Stopped:
            pass  # (the loop below ends at once)
        except TimeoutError as e:
            node.event(f"{e}; running alone")
        node.announce()
        node.publish_status("ready")
        seq = 0
        sent_wm, sent_at = -math.inf, 0.0
        waiting_since: float | None = None
        alone = False
        last_status = 0.0
        down_key = keys.feedback(me)

        feedback = Intake(keys, node.reject, ["feedback"], senders={"feedback": fuser_id})

        def on_downlink(data: bytes) -> Message | None:
            """The fuser's downlink or horizon, applied; the message, if it was one."""
            nonlocal alone, waiting_since
            sample = feedback.offer(down_key, data)
            if sample is None:
                return None
            msg = sample.msg
            if msg.kind == "watermark":
                local.set_horizon(msg.t)
            else:
                try:
                    local.receive(downlink(sensor, msg))
                except ValueError as e:  # well-formed, but not for this node (a kind it takes none of)
                    node.reject(msg.src, "unusable-downlink", f"{msg.kind} at t = {msg.t:g} s: {e}")
                    return msg
            waiting_since = None
            if alone:
                alone = False
                node.event("downlink from the fuser restored")
            if local.ran_alone:  # its request was lost: the fuser refuses its reports
                local.centre_restarted()
                node.event(f"no init from {fuser_id} for the track it started alone: "
                           f"dropped, asking to join again")
            return msg

        fuser_incarnation: str | None = None  # the one this node's track comes from

        def restart_handshake() -> None:
            """The node drops what the dead fuser gave it and asks to join again."""
            nonlocal alone, waiting_since, sent_wm
            if local.centre_restarted():
                node.event(f"{fuser_id} restarted: tracks dropped, asking it for initial states again")
            alone, waiting_since = False, None
            sent_wm = -math.inf  # the new fuser has heard no watermark from us yet

        retired: set[str] = set()  # incarnations of the fuser this node has seen replaced

        def heard_fuser() -> None:
            """The incarnations of the fuser that appeared (tokens, downlinks' senders): a
            new one restarts the handshake, a replaced one is never taken back. Before each
            downlink, so that the new fuser's first horizon is not forgotten by a handshake
            that comes after it (the node, which then knows no horizon, would wait for its
            init until its feedback timeout, holding the fuser's merge back)."""
            nonlocal fuser_incarnation
            while not fuser_token.empty():
                incarnation = fuser_token.get()
                if incarnation in retired or incarnation == fuser_incarnation:
                    continue
                if fuser_incarnation is not None:
                    restart_handshake()
                    if len(retired) < RETIRED_MAX:
                        retired.add(fuser_incarnation)
                fuser_incarnation = incarnation

        alive: set[tuple[str, str]] = set()  # (process, incarnation) of the tokens up, at most ALIVE_MAX
        sensor_heard = False
        gone_since: float | None = None

        def sensor_gone(now: float) -> None:
            """A scenario run's sensor gone without its end heard (module docstring)."""
            nonlocal sensor_heard, gone_since
            while not tokens.empty():
                up, process, incarnation = tokens.get()
                if not up:
                    alive.discard((process, incarnation))
                elif len(alive) < ALIVE_MAX:
                    alive.add((process, incarnation))
                sensor_heard |= up and process == sensor
            seen = {process for process, _ in alive} - {me}
            if sensor in seen or not seen or not sensor_heard or feed.finished:  # (none seen: cut off)
                gone_since = None
            elif gone_since is None:
                gone_since = now
            elif now - gone_since > feedback_timeout:
                t_end = core.end(sensor, now)
                node.event(f"{sensor} gone for more than {feedback_timeout:g} s and the end of its stream not "
                           f"heard: taken as ended at t = {t_end:g} s")
                gone_since = math.inf  # (once)

        while not node.stop.is_set():
            heard_fuser()
            try:
                key, data = inbox.get(timeout=0.05)
                while True:
                    if key == down_key:
                        heard_fuser()
                        msg = on_downlink(data)
                    else:
                        msg = core.offer(key, data, time.monotonic(), utc())
                    if recovery is not None and msg is not None:
                        recovery.arrived(msg.src, msg.t, utc())
                    key, data = inbox.get_nowait()
            except queue.Empty:
                pass
            now = time.monotonic()
            if live is None:
                sensor_gone(now)
            core.step(now)
            for ev in core.events:
                node.event(ev)
            core.events.clear()
            blocked = local.waiting_for
            if blocked is None:
                waiting_since = None
            elif waiting_since is None:
                waiting_since = now
            elif not alone and now - waiting_since > feedback_timeout:
                alone = True
                node.event(f"no {blocked} from {fuser_id} for {feedback_timeout:g} s: running alone")
            for u in local.step(alone=alone):
                seq += 1
                pub.put(encode_uplink(u, me, seq))
            final = feed.finished and not local.pending
            wm = local.upstream_watermark(feed.watermark)
            if math.isfinite(wm) and (wm > sent_wm or final or (wm == sent_wm and now - sent_at >= ALIVE_S)):
                seq += 1
                pub.put(encode("watermark", me, seq, wm, final=final))
                sent_wm, sent_at = wm, now
            node.counters.update(received=core.received, processed=core.processed, published=seq,
                                 pending=len(local.pending), alone=int(alone), stale=local.stale)
            if recovery is not None:
                node.counters.update(recovery.counters())
            if final:
                break
            if now - last_status >= 1.0:
                node.publish_status("running", max(sent_wm, 0.0))
                last_status = now
        node.publish_status("done" if feed.finished else "stopped", max(sent_wm, 0.0))
        watch.undeclare()
        if alive_watch is not None:
            alive_watch.undeclare()
    return 0
