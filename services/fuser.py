"""The command-centre fuser process.

Centralised topology: subscribes to every sensor's ``meas/<sensor>`` and runs one
estimation method of ``fusion/`` on the time-ordered measurements. Distributed,
feedback and two-stage topologies: subscribes to every local tracker's
``local/<node>`` and runs the method's centre (:mod:`fusion.network`) on the
time-ordered uplinks, sending priors down on ``feedback/<node>``. Either way it
validates and orders its input (:class:`~services.ordering.WatermarkMerger`) and
publishes its estimates on ``fused``.

:class:`FuserCore` is the whole behaviour without Zenoh: bytes in, estimates out. The
process around it only moves bytes, so tests (and the fuzzer) can drive the core and
the real process with the same inputs.
"""

from __future__ import annotations

import math
import queue
import time
from typing import Any

from fusion.config import method_config
from fusion.methods import make_method
from fusion.network import SPLITS, split
from fusion.types import Estimate
from schemas import MEASUREMENT_KINDS, KeySpace, Message, SchemaError, decode, encode_estimate, to_measurement, tracker_id
from schemas.links import encode_downlink, horizon_message, uplink

from .node import Node, RejectLog, load


class MeasurementIntake:
    """Raw measurements on ``meas/<sensor>`` (centralised fuser, local tracker)."""

    family = "meas"

    def item(self, key_id: str, msg: Message) -> tuple[str, Any] | tuple[None, str]:
        if msg.kind not in MEASUREMENT_KINDS:
            return None, "kind"
        if msg.body["sensor"] != key_id:
            return None, f"spoofed-src:measurement of sensor {msg.body['sensor']!r} sent by {key_id!r}"
        return "item", to_measurement(msg)


class UplinkIntake:
    """Uplinks on ``local/<node>`` (fuser of the distributed topologies).

    ``nodes`` maps tracker id to its sensor. DDHNV's uplink is two messages (estimate,
    then measurement, same ``t``): the estimate waits here for its measurement.
    """

    family = "local"

    def __init__(self, nodes: dict[str, str]):
        self.nodes = nodes
        self._held: dict[str, Message] = {}

    def item(self, key_id: str, msg: Message):
        sensor = self.nodes.get(key_id)
        if sensor is None:
            return None, "unknown-source"
        held = self._held.pop(key_id, None)
        if msg.kind in MEASUREMENT_KINDS:
            if msg.body["sensor"] != sensor:
                return None, f"spoofed-src:measurement of sensor {msg.body['sensor']!r} sent by {key_id!r}"
            if held is not None and held.t == msg.t:
                return "item", uplink(sensor, held, msg)
            return "item", uplink(sensor, msg)
        if msg.kind in ("track", "prediction"):
            if msg.kind == "prediction":  # its measurement follows
                self._held[key_id] = msg
                return "held", None
            return "item", uplink(sensor, msg)
        return None, "kind"


class FuserCore:
    """Validate, order and estimate.

    Args:
        method: an object with ``process`` / ``advance`` / ``finish``.
        sources: the ids this fuser waits for (sensors, or local trackers).
        keys: the deployment's key space (to check that ``src`` matches the key).
        reject: where rejections are counted.
        timeout, start_grace, horizon: see :class:`~services.ordering.WatermarkMerger`.
        intake: what the input is (:class:`MeasurementIntake` by default).
    """

    def __init__(self, method: Any, sources: list[str], keys: KeySpace, reject: RejectLog,
                 timeout: float, start_grace: float = 30.0, horizon: float = math.inf, now: float = 0.0,
                 intake: Any = None):
        from .ordering import WatermarkMerger

        self.method = method
        self.keys = keys
        self.reject = reject
        self.intake = intake or MeasurementIntake()
        self.merger = WatermarkMerger(sources, timeout, start_grace, horizon, now)
        self.events: list[str] = []
        self.received = 0
        self.processed = 0
        self.finished = False

    def offer(self, key: str, data: bytes, now: float) -> None:
        """One sample off the wire. Bad input is counted and dropped; never raises."""
        self.received += 1
        try:
            family, key_id = self.keys.family_and_id(key)
        except ValueError as e:
            self.reject("?", "key", str(e))
            return
        hint = key_id or "?"
        try:
            msg = decode(data)
        except SchemaError as e:
            self.reject(hint, e.cause, str(e))
            return
        if family != self.intake.family or msg.src != key_id:
            self.reject(hint, "spoofed-src", f"message says src={msg.src!r} but came on {key}")
            return
        if msg.kind == "watermark":
            rej = self.merger.watermark(msg.src, msg.t, msg.body["final"], now, self.events)
        else:
            what, item = self.intake.item(key_id, msg)
            if what is None:
                cause, _, detail = item.partition(":")
                self.reject(hint, cause, detail or f"{msg.kind!r} is not expected on {key}")
                return
            if what == "held":
                return
            rej = self.merger.add(msg.src, msg.t, msg.seq, item, now, self.events)
        if rej is not None:
            self.reject(rej.src, rej.cause, rej.detail)

    def step(self, now: float) -> list[Estimate]:
        """Release what the watermarks allow and run the method on it."""
        if self.finished:
            return []
        self.merger.check_timeouts(now, self.events)
        items, wm = self.merger.release()
        out: list[Estimate] = []
        for m in items:
            out.extend(self.method.process(m))
            self.processed += 1
        if math.isfinite(wm):
            out.extend(self.method.advance(wm))
        if self.merger.done:
            out.extend(self.method.finish())
            self.finished = True
        return out

    def sources_report(self) -> dict:
        return {s: {"dead_intervals": st.dead_intervals, "rejected": self.reject.rejected_by_source().get(s, 0)}
                for s, st in self.merger.sources.items()}


def run(process_id: str, scenario_ref: str, method_name: str, overrides: dict, keys: KeySpace, zopts,
        timeout: float, start_grace: float, seed: int | None = None) -> int:
    scenario = load(scenario_ref, seed)
    config = method_config(scenario.tracker, method_name, overrides)
    if method_name in SPLITS:  # distributed, feedback, two-stage: the centre over the local trackers
        method = split(method_name).centre(config)
        nodes = {tracker_id(s): s for s in scenario.sensors}
        intake: Any = UplinkIntake(nodes)
        sources = list(nodes)
    else:
        method = make_method(method_name, config)
        intake = MeasurementIntake()
        sources = list(scenario.sensors)
    inbox: queue.SimpleQueue[tuple[str, bytes]] = queue.SimpleQueue()
    with Node(process_id, "fuser", keys, zopts) as node:
        core = FuserCore(method, sources, keys, node.reject, timeout, start_grace,
                         horizon=scenario.duration + 1.0, now=time.monotonic(), intake=intake)
        node.subscribe(keys.all(intake.family), lambda s: inbox.put((str(s.key_expr), s.payload.to_bytes())))
        pub = node.publisher(keys.fused())
        down = {tid: node.publisher(keys.feedback(tid)) for tid in (intake.nodes if method_name in SPLITS else ())}
        node.announce()
        node.publish_status("ready")
        seq = down_seq = 0
        horizon = -math.inf
        last_status = 0.0
        t_now = 0.0
        while not node.stop.is_set():
            try:
                key, data = inbox.get(timeout=0.05)
                core.offer(key, data, time.monotonic())
                while True:  # drain what is queued before stepping: fewer, larger releases
                    key, data = inbox.get_nowait()
                    core.offer(key, data, time.monotonic())
            except queue.Empty:
                pass
            for e in core.step(time.monotonic()):
                seq += 1
                pub.put(encode_estimate(e, process_id, seq))
                t_now = e.t
            if down:
                for d in method.take_downlinks():
                    down_seq += 1
                    down[tracker_id(d.node)].put(encode_downlink(d, process_id, down_seq))
                if method.feedback and method.horizon > horizon and math.isfinite(method.horizon):
                    horizon = method.horizon
                    down_seq += 1
                    for p in down.values():
                        p.put(horizon_message(process_id, down_seq, horizon))
            for ev in core.events:
                node.event(ev)
            core.events.clear()
            node.counters.update(received=core.received, processed=core.processed, published=seq,
                                 late=core.merger.late, held=core.merger.held())
            if core.finished:
                break
            if time.monotonic() - last_status >= 1.0:
                node.publish_status("running", t_now, sources=core.sources_report())
                last_status = time.monotonic()
        node.publish_status("done" if core.finished else "stopped", t_now, sources=core.sources_report())
    return 0
