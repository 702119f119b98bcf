"""Source processes: a sensor emulator, the scenario's truth clock, a jammer.

Each plays its part of the scenario (``sensors_sim``) in scenario time, paced against
the wall clock: the item for time ``t`` goes out at ``start_at + t / speed`` (or at once
with ``--speed max``). A sensor publishes each scan's measurements (a rotating radar's:
each sector's, when the beam leaves it) on ``meas/<id>`` and then a watermark, so
consumers can order sources; its last watermark is marked final. Watermarks look ahead:
published right after a scan or sector, each promises everything up to just before the
sensor's next one. Noise comes from the process's own generator, seeded by
``(scenario seed, process id)``, so a distributed run draws exactly what the in-process
evaluation draws.

Sources wait until the consumers named by ``wait_for`` have announced themselves (their
subscribers are declared), so nothing is published into the void.

Live emulation (``live``): the same streams on the UTC time base, for a live session's
consumers: every ``t`` on the wire is ``start_at + t`` (UTC POSIX seconds; scenario
time 0 is ``start_at``), paced at ``speed`` 1. A sensor with ``latency_s`` (an emulated
slow link) publishes each scan, and the watermark after it, that long after the scan's
time of validity: its watermarks never claim a time whose data has not been sent. A
live emulator that is stopped marks its latest watermark final (its stream has ended,
it is not a sensor gone silent). Its measurements and watermarks go out on a recoverable
publisher (:meth:`services.node.Node.recoverable_publisher`): it keeps the last
:func:`recovery_cache` samples, the site's recovery window ``recovery_s`` (default 30 s)
of its stream twice over, for a fuser that was cut off from it (a router down or
restarting) to get back on reconnection.
"""

from __future__ import annotations

import dataclasses
import math
import socket
import time
from typing import Iterator

from fusion.lazy import lazy
from schemas import KeySpace, encode, encode_measurement
from sensors_sim import jam_events, truth_events
from sensors_sim.emulators import sensor_batches

from .errors import UserError
from .node import Node, Stopped
from .scenario import load


asterix_emit = lazy("services.ingest.asterix_emit")  # only a sensor sending ASTERIX needs these
asterix_capture = lazy("services.ingest.asterix")


def recovery_cache(scenario, sensor_id: str) -> int:
    """Samples in the site's recovery window (``scenario.recovery``, ``recovery_s``) of a
    sensor's stream, twice over: per scan its targets (and at most ``max_alive`` traffic
    aircraft), its mean clutter and one watermark (a rotating radar: one per sector)."""
    s = scenario.sensor(sensor_id)
    traffic = getattr(scenario, "traffic", None)
    per_scan = len(s.targets) + (traffic.max_alive if traffic is not None else 0) + s.clutter_rate + max(1, s.sectors)
    return math.ceil(2.0 * scenario.recovery * per_scan / s.period)


class Pacer:
    """Sleeps until scenario time ``t`` is due; ``speed = inf`` never sleeps. ``stamp``
    maps scenario time to the wire's time base (UTC in live emulation)."""

    def __init__(self, node: Node, start_at: float, speed: float, live: bool = False):
        self.node = node
        self.start_at = start_at
        self.speed = speed
        self.offset = start_at if live else 0.0

    def stamp(self, t: float) -> float:
        return self.offset + t

    def wait(self, t: float) -> bool:
        """Returns False if the process was asked to stop meanwhile."""
        if math.isinf(self.speed):
            return not self.node.stop.is_set()
        due = self.start_at + t / self.speed
        while True:
            left = due - time.time()
            if left <= 0 or self.node.stop.is_set():
                return not self.node.stop.is_set()
            self.node.stop.wait(min(left, 0.5))


class AsterixOut:
    """Where a sensor's ASTERIX goes: datagrams to ``udp`` (HOST, PORT) and/or records
    of a pcap capture written to ``pcap`` (to 127.0.0.1 at the UDP port, or 8600), each
    stamped with its wire time; ``failed`` counts datagrams the socket refused."""

    def __init__(self, udp: tuple[str, int] | None = None, pcap: str | None = None):
        self.udp, self.port = udp, udp[1] if udp else 8600
        self.sock = self.file = None
        self.sent = self.failed = 0
        try:
            if udp:
                self.sock = socket.socket(socket.AF_INET6 if ":" in udp[0] else socket.AF_INET, socket.SOCK_DGRAM)
        except OSError as e:
            raise UserError(f"--asterix: {e.strerror or e}") from None
        try:
            if pcap:
                self.file = open(pcap, "wb")
                self.file.write(asterix_capture.PCAP_HEADER)
        except OSError as e:
            self.close()
            raise UserError(f"--asterix-pcap {pcap}: {e.strerror or e}") from None

    def send(self, t_wire: float, data: list[bytes]) -> None:
        for d in data:
            if self.sock is not None:
                try:
                    self.sock.sendto(d, self.udp)
                    self.sent += 1
                except OSError:
                    self.failed += 1
            if self.file is not None:
                self.file.write(asterix_capture.pcap_record(t_wire, d, self.port))
        if self.file is not None and data:
            self.file.flush()

    def close(self) -> None:
        for f in (self.sock, self.file):
            if f is not None:
                f.close()


def run(process_id: str, scenario_ref: str, keys: KeySpace, zopts, speed: float, start_at: float | None,
        wait_for: list[str], run_index: int = 0, wait_timeout: float = 60.0,
        seed: int | None = None, live: bool = False, duration: float | None = None,
        asterix: AsterixOut | None = None) -> int:
    """One source process; ``asterix``: a sensor sends ASTERIX there instead of
    publishing on Zenoh (the caller closes it)."""
    scenario = load(scenario_ref, seed, duration)
    if live and duration is None and scenario.endless:  # a live emulation without an end: until stopped
        scenario = dataclasses.replace(scenario, duration=math.inf)
    if process_id == "truth":
        role = "truth"
    elif process_id in scenario.sensors:
        role = "sensor"
    elif process_id in scenario.jammers:
        role = "jammer"
    else:
        raise UserError(f"{process_id!r} is not a source of scenario {scenario.name} "
                         f"(sources: {', '.join(scenario.process_ids())})")
    emit = None
    if asterix is not None:
        if role != "sensor":
            raise UserError(f"--asterix: {process_id!r} is not a sensor (a radar or ADS-B station with sac_sic)")
        try:
            emit = asterix_emit.emitter(scenario, process_id)
        except ValueError as e:
            raise UserError(f"--asterix: {e}") from None
    with Node(process_id, role, keys, zopts, live=live) as node:
        node.announce()
        node.publish_status("starting")
        try:
            node.wait_for(wait_for, wait_timeout)
        except Stopped:  # a clean stop, not a failure
            node.publish_status("stopped")
            return 0
        except TimeoutError as e:
            node.event(str(e))
            node.publish_status("stopped")
            return 2
        pacer = Pacer(node, start_at if start_at is not None else time.time(), 1.0 if live else speed, live)
        if emit is not None:
            t_last = _play_asterix(node, scenario, pacer, run_index, emit, asterix)
        else:
            play = {"sensor": _play_sensor, "truth": _play_truth, "jammer": _play_jammer}[role]
            t_last = play(node, scenario, pacer, run_index)
        node.publish_status("done" if not node.stop.is_set() else "stopped", pacer.stamp(t_last))
    return 0


def _status_every(node: Node, period: float = 1.0) -> Iterator[None]:
    last = 0.0
    while True:
        now = time.monotonic()
        if now - last >= period:
            last = now
            node.publish_status("running")
        yield


def _play_sensor(node: Node, scenario, pacer: Pacer, run_index: int) -> float:
    meas_pub = (node.recoverable_publisher(node.keys.meas(node.id), recovery_cache(scenario, node.id)) if pacer.offset
                else node.publisher(node.keys.meas(node.id)))
    wm_seq = 0
    status = _status_every(node)

    sent = [-math.inf]  # the latest watermark, on the wire's time base

    def watermark(t: float, final: bool) -> None:
        nonlocal wm_seq
        wm_seq += 1
        # Watermarks have their own counter: ``seq`` of measurements counts measurements.
        meas_pub.put(encode("watermark", node.id, wm_seq, t, final=final))
        sent[0] = t

    latency = scenario.sensor(node.id).latency
    batches = sensor_batches(scenario, node.id, run=run_index)
    batch = next(batches, None)
    t_last: float | None = None
    while batch is not None:
        if not pacer.wait(batch.t1 + latency):  # a slow link: the batch goes out latency_s late
            if pacer.offset and math.isfinite(sent[0]):  # live: a stopped emulator's stream ends here
                watermark(sent[0], True)
            return batch.t1
        for ev in batch.events:
            node.count("scans")
            node.count("jammed", int(ev.jammed))
            node.count("outliers", int(ev.outlier))
            node.count("missed", int(ev.measurement is None))
            if ev.measurement is not None:
                m = ev.measurement
                meas_pub.put(encode_measurement(dataclasses.replace(m, t=pacer.stamp(m.t)) if pacer.offset else m,
                                                node.id))
                node.count("published")
        t_last, batch = batch.t1, next(batches, None)
        if batch is not None and batch.t1 > t_last:
            # Look-ahead watermark: the schedule is known, so right after a scan (or a
            # rotating radar's sector) the sensor can promise "nothing up to just before
            # my next one" (a watermark still means "everything up to and including t has
            # been sent"). Consumers then wait for no sensor's next scan, only for the
            # data itself. (Taken on the wire's time base: one ulp of scenario time is
            # nothing in UTC.)
            watermark(math.nextafter(pacer.stamp(batch.t0), -math.inf), False)
        next(status)
    t_end = max(t_last if t_last is not None else 0.0, scenario.duration)
    watermark(pacer.stamp(t_end), True)
    return t_end


def _play_asterix(node: Node, scenario, pacer: Pacer, run_index: int, emit, out: AsterixOut) -> float:
    """The sensor's batches as ASTERIX datagrams (module docstring), each sent when the
    Zenoh stream would publish it."""
    latency = scenario.sensor(node.id).latency
    status = _status_every(node)
    t_last = 0.0
    for batch in sensor_batches(scenario, node.id, run=run_index):
        if not pacer.wait(batch.t1 + latency):
            return batch.t1
        records = emit.records(batch.t1, batch.events, pacer.stamp)
        out.send(pacer.stamp(batch.t1 + latency), asterix_emit.datagrams(records))
        node.count("scans", len(batch.events))
        node.count("published", sum(r.category != 34 for r in records))
        node.counters.update(unencodable=emit.unencodable, send_failed=out.failed)
        t_last = batch.t1
        next(status)
    for t, records in emit.end(pacer.stamp):
        if not pacer.wait(t + latency):
            break
        out.send(pacer.stamp(t + latency), asterix_emit.datagrams(records))
    node.counters["send_failed"] = out.failed
    return max(t_last, scenario.duration)


def _play_truth(node: Node, scenario, pacer: Pacer, run_index: int) -> float:
    pubs: dict[str, object] = {}
    seq = 0
    t = 0.0
    status = _status_every(node)
    for s in truth_events(scenario, run=run_index):
        if not pacer.wait(s.t):
            return s.t
        if s.target not in pubs:
            pubs[s.target] = node.publisher(node.keys.truth(s.target), reliable=False)
        seq += 1
        pubs[s.target].put(encode("truth", node.id, seq, pacer.stamp(s.t), target=s.target, x=s.x))
        node.count("published")
        t = s.t
        next(status)
    return t


def _play_jammer(node: Node, scenario, pacer: Pacer, run_index: int) -> float:
    pub = node.publisher(node.keys.jam(node.id))
    seq = 0
    t = 0.0
    status = _status_every(node)
    for js in jam_events(scenario, node.id):
        if not pacer.wait(js.t):
            return js.t
        seq += 1
        pub.put(encode("jam_state", node.id, seq, pacer.stamp(js.t), pos=js.pos, on=bool(js.on), mode=js.mode,
                       power=float(js.power), law=js.law, affects=list(js.affects)))
        node.count("published")
        t = js.t
        next(status)
    return t
