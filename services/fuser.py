"""The command-centre fuser process (centralised topology).

Subscribes to every sensor's ``meas/<sensor>``, validates and time-orders the input
(:class:`~services.ordering.WatermarkMerger`), runs one estimation method of
``fusion/`` on the ordered stream and publishes its estimates on ``fused``.

:class:`FuserCore` is the whole behaviour without Zenoh: bytes in, estimates out. The
process around it only moves bytes, so tests (and the fuzzer) can drive the core and
the real process with the same inputs.
"""

from __future__ import annotations

import math
import queue
import time
from typing import Any, Callable

from fusion.methods import make_method
from fusion.types import Estimate
from schemas import MEASUREMENT_KINDS, KeySpace, SchemaError, decode, encode_estimate, to_measurement

from .node import Node, RejectLog, load


class FuserCore:
    """Validate, order and estimate.

    Args:
        method: an object with ``process`` / ``advance`` / ``finish``.
        sources: the sensor ids this fuser waits for.
        keys: the deployment's key space (to check that ``src`` matches the key).
        reject: where rejections are counted.
        timeout, start_grace, horizon: see :class:`~services.ordering.WatermarkMerger`.
    """

    def __init__(self, method: Any, sources: list[str], keys: KeySpace, reject: RejectLog,
                 timeout: float, start_grace: float = 30.0, horizon: float = math.inf, now: float = 0.0):
        from .ordering import WatermarkMerger

        self.method = method
        self.keys = keys
        self.reject = reject
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
        if family != "meas" or msg.src != key_id:
            self.reject(hint, "spoofed-src", f"message says src={msg.src!r} but came on {key}")
            return
        if msg.kind == "watermark":
            rej = self.merger.watermark(msg.src, msg.t, msg.body["final"], now, self.events)
        elif msg.kind in MEASUREMENT_KINDS:
            if msg.body["sensor"] != msg.src:
                self.reject(hint, "spoofed-src", f"measurement of sensor {msg.body['sensor']!r} sent by {msg.src!r}")
                return
            rej = self.merger.add(msg.src, msg.t, msg.seq, to_measurement(msg), now, self.events)
        else:
            self.reject(hint, "kind", f"{msg.kind!r} is not expected on {key}")
            return
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
    method = make_method(method_name, {**scenario.tracker, **overrides})
    sources = list(scenario.sensors)
    inbox: queue.SimpleQueue[tuple[str, bytes]] = queue.SimpleQueue()
    with Node(process_id, "fuser", keys, zopts) as node:
        core = FuserCore(method, sources, keys, node.reject, timeout, start_grace,
                         horizon=scenario.duration + 1.0, now=time.monotonic())
        node.subscribe(keys.all("meas"), lambda s: inbox.put((str(s.key_expr), s.payload.to_bytes())))
        pub = node.publisher(keys.fused())
        node.announce()
        node.publish_status("ready")
        seq = 0
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

