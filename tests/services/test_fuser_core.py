"""The fuser's core, without Zenoh: bad input of every kind, interleaved with a real
scenario's stream, is counted by cause and changes nothing in the fused output."""

from __future__ import annotations

import dataclasses
import math

import msgpack
import numpy as np
import pytest

from fusion.links import InitRequest
from fusion.methods import make_method, method_config
from fusion.network import TrackCentre, TrackNode
from fusion.patent import TrackerConfig
from fusion.topology import SCHEMES
from fusion.types import Estimate
from schemas import encode, encode_estimate, encode_measurement
from sensors_sim import load_scenario, sensor_events
from services.evaluation import merged_measurements, run_method
from services.fuser import FuserCore, JoinGate, MeasurementIntake
from services.node import RejectLog

from sim3d import ANGLE, RADAR2D, simulate
from _wire import CASES, KEYS, good, wire_stream, with_field

def _garbage(sid: str) -> list[bytes]:
    bad = []
    for kind, field, value, _cause in CASES:
        d = good(kind)
        d["src"] = sid
        if "sensor" in d:
            d["sensor"] = sid
        d = with_field(d, field, value)
        bad.append(msgpack.packb(d, use_bin_type=True))
    valid_but_wrong_kind = msgpack.packb({**good("truth"), "src": sid})  # truth has no business on meas/
    return bad + [b"\xc1", b"", msgpack.packb("str"), valid_but_wrong_kind]


def _forged(scenario) -> list[bytes]:
    """Well-formed measurements on meas/radar2d that contradict the scenario: the angle
    sensor's kind, or a radar plot claiming an absurdly small noise std."""
    radar = [ev.measurement for ev in sensor_events(scenario, "radar2d") if ev.measurement is not None]
    angle = [ev.measurement for ev in sensor_events(scenario, "angle") if ev.measurement is not None]
    out = []
    for i, (r, a) in enumerate(zip(radar, angle)):
        out.append(encode_measurement(dataclasses.replace(a, sensor="radar2d", seq=10_000 + i), "radar2d"))
        out.append(encode_measurement(dataclasses.replace(r, std=r.std * 1e-300, seq=20_000 + i), "radar2d"))
    return out


def _run(scenario, noisy: bool, garbage: list[bytes] | None = None, intake=None):
    reject = RejectLog("test")
    core = FuserCore(make_method("SS", method_config(scenario.tracker, "SS")), list(scenario.sensors), KEYS, reject,
                     timeout=1e9, intake=intake)
    garbage = _garbage("radar2d") if garbage is None else garbage
    out = []
    for i, (key, data) in enumerate(wire_stream(scenario)):
        if noisy and i % 3 == 0:
            for g in garbage[i % 7:: 7]:
                core.offer(KEYS.meas("radar2d"), g, 0.0)
            core.offer(key, data, 0.0)  # a replayed copy: duplicate or out of order
            core.offer(KEYS.meas("angle"), data if "radar2d" in key else data, 0.0)  # wrong key for half of them
        core.offer(key, data, 0.0)
        out.extend(core.step(0.0))
    assert core.finished
    return out, reject


def test_bad_input_of_every_kind_changes_nothing():
    sc = load_scenario("patent-3d")
    clean, r0 = _run(sc, noisy=False)
    noisy, r1 = _run(sc, noisy=True)
    assert r0.total == 0
    assert len(clean) == len(noisy) == 31
    for a, b in zip(clean, noisy):
        assert a.t == b.t and np.array_equal(a.x, b.x) and np.array_equal(a.P, b.P)
    assert {"malformed", "not-a-map", "version", "kind", "type", "non-finite", "range", "shape", "value",
            "unknown-field", "missing", "duplicate", "spoofed-src"} <= set(r1.by_cause), dict(r1.by_cause)


def test_measurements_contradicting_the_scenario_are_refused():
    sc = load_scenario("patent-3d")
    clean, _ = _run(sc, noisy=False, intake=MeasurementIntake(sc.sensors))
    forged, reject = _run(sc, noisy=True, garbage=_forged(sc), intake=MeasurementIntake(sc.sensors))
    assert reject.by_cause["kind-mismatch"] > 0 and reject.by_cause["std-mismatch"] > 0, dict(reject.by_cause)
    assert len(clean) == len(forged)
    for a, b in zip(clean, forged):
        assert a.t == b.t and np.array_equal(a.x, b.x) and np.array_equal(a.P, b.P)
    # without the scenario's sensors the same messages get in and change the track
    fused, unchecked = _run(sc, noisy=True, garbage=_forged(sc))
    assert "kind-mismatch" not in unchecked.by_cause and "std-mismatch" not in unchecked.by_cause
    assert any(not np.allclose(a.x, b.x) for a, b in zip(clean, fused))


def test_core_equals_in_process_evaluation():
    sc = load_scenario("patent-3d")
    core_out, _ = _run(sc, noisy=False)
    ref = run_method(sc, "SS")
    assert len(core_out) == len(ref)
    for a, b in zip(core_out, ref):
        assert a.t == b.t and np.array_equal(a.x, b.x) and np.array_equal(a.P, b.P)


DF_CENTRALISED = [(sc, m) for sc in ("thesis-fixed-c3", "jammed-df")
                  for m in ("EKF", "MEKF1", "MEKF2", "MEKF3", "MEKF4", "MEKF5", "IMM", "TORRIERI")]


@pytest.mark.parametrize("scenario,method", DF_CENTRALISED)
def test_df_methods_through_the_core_equal_in_process(scenario, method):
    """Every centralised DF method, its stations' messages arriving out of step (each
    station a few epochs behind the one before), gives exactly the in-process estimates:
    the fuser's ordering and streaming, without the transport (a subset also runs over
    Zenoh, tests/services/test_topologies.py)."""
    sc = load_scenario(scenario)
    core = FuserCore(make_method(method, method_config(sc.tracker, method)), list(sc.sensors), KEYS,
                     RejectLog("test"), timeout=1e9)
    out = []
    for key, data in wire_stream(sc, lag={s: 3.5 * i for i, s in enumerate(sc.sensors)}):
        core.offer(key, data, 0.0)
        out.extend(core.step(0.0))
    ref = run_method(sc, method)
    assert core.finished and core.reject.total == 0 and len(out) == len(ref) == 40
    for a, b in zip(out, ref):
        assert a.t == b.t and np.array_equal(a.x, b.x) and np.array_equal(a.P, b.P)


def test_offer_returns_what_it_decoded():
    """A node that needs the message too (a tracker's recovery count) takes it from
    ``offer`` rather than decoding every sample twice: the message, accepted or refused
    after decoding; None for bytes that do not decode."""
    sc = load_scenario("patent-3d")
    core = FuserCore(make_method("SS", method_config(sc.tracker, "SS")), list(sc.sensors), KEYS, RejectLog("test"),
                     timeout=1e9)
    key, data = wire_stream(sc)[0]
    msg = core.offer(key, data, 0.0)
    assert msg is not None and (msg.src, msg.t) == (KEYS.family_and_id(key)[1], 0.0) and core.reject.total == 0
    again = core.offer(key, data, 0.0)  # a duplicate: refused, but it did decode
    assert again is not None and again.seq == msg.seq and core.reject.by_cause["duplicate"] == 1
    assert core.offer(key, b"\xc1", 0.0) is None and core.reject.by_cause["malformed"] == 1


def test_reject_log_memory_is_bounded_by_invented_source_names():
    reject = RejectLog("test", max_sources=3)
    for i in range(1000):  # every garbage message on a key of its own
        reject(f"mallory-{i}", "unknown-source", "nobody")
    reject("mallory-1", "msgpack", "bad bytes")  # a known name keeps its own entry
    assert reject.total == 1001 and len(reject.by_pair) == 5
    assert reject.rejected_by_source() == {"mallory-0": 1, "mallory-1": 2, "mallory-2": 1, RejectLog.OTHER: 997}


def test_an_estimate_the_wire_refuses_is_counted_and_dropped():
    """The publish path (``FuserCore.encoded``): an estimate the wire cannot carry is
    counted by cause and dropped, the first of each cause said once in an event; a valid
    one is the bytes ``encode_estimate`` gives."""
    sc = load_scenario("patent-3d")
    core = FuserCore(make_method("SS", method_config(sc.tracker, "SS")), list(sc.sensors), KEYS, RejectLog("test"),
                     timeout=1e9)
    good_e = Estimate(1.0, np.array([1.0, 2.0]), np.eye(2), "SS", "centre", "T1", 3.0, 2)
    negative = dataclasses.replace(good_e, P=np.diag([1.0, -1.0]))
    too_many = dataclasses.replace(good_e, nis=81.0, nis_dof=81)
    assert core.encoded(encode_estimate, good_e, "fuser", 1) == encode_estimate(good_e, "fuser", 1)
    assert [core.encoded(encode_estimate, e, "fuser", 2) for e in (negative, negative, too_many)] == [None] * 3
    assert dict(core.unpublished) == {"value": 2, "range": 1}
    assert len(core.events) == 2 and "negative variance" in core.events[0] and "nis_dof" in core.events[1]


@pytest.mark.parametrize("cut", range(4))
def test_a_core_joining_mid_stream_starts_from_a_whole_scan(cut):
    """A core that subscribes mid-way (a restarted fuser) hears the rest of a scan in
    progress: here from each of the four messages of scan t = 10 s (radar plot, radar
    watermark, angle plot, angle watermark). It fuses from the first scan it has heard
    whole, after a watermark of every sensor: its estimates are those of the in-process
    evaluation started at that scan (before, a joining core started from a radar plot
    alone, a track without elevation: a different estimate on every later scan)."""
    sc = load_scenario("patent-3d")
    stream = wire_stream(sc)
    starts = [i for i, (_, data) in enumerate(stream) if msgpack.unpackb(data)["t"] == 10.0]
    reject = RejectLog("test")
    core = FuserCore(make_method("SS", method_config(sc.tracker, "SS")), list(sc.sensors), KEYS, reject,
                     timeout=1e9, intake=MeasurementIntake(sc.sensors), schedule=_schedule(sc))
    out = []
    for key, data in stream[starts[cut]:]:
        core.offer(key, data, 0.0)
        out.extend(core.step(0.0))
    assert core.finished and reject.total == 0
    assert any(e.startswith("joined ") for e in core.events)
    t0 = out[0].t
    assert 10.0 <= t0 <= 12.0
    ref = run_method(sc, "SS", measurements=[m for m in merged_measurements(sc) if m.t >= t0])
    assert len(out) == len(ref) == 31 - t0
    for a, b in zip(out, ref):
        assert a.t == b.t and np.array_equal(a.x, b.x) and np.array_equal(a.P, b.P)


@pytest.mark.parametrize("case", ["refused", "first scan missed"])
def test_a_core_that_heard_every_scan_does_not_join_mid_stream(case):
    """Watermarks refused before a sensor's first (beyond the scenario's end), or a sensor
    whose first scan had no plot (its first message is the watermark after it), are not
    a join mid-way: the core fuses the whole stream, as the in-process evaluation does."""
    sc = load_scenario("patent-3d")
    reject = RejectLog("test")
    core = FuserCore(make_method("SS", method_config(sc.tracker, "SS")), list(sc.sensors), KEYS, reject,
                     timeout=1e9, horizon=sc.duration + 1.0, intake=MeasurementIntake(sc.sensors),
                     schedule=_schedule(sc))
    stream, measurements = wire_stream(sc), merged_measurements(sc)
    if case == "refused":
        core.offer(KEYS.meas("radar2d"), encode("watermark", "radar2d", 7, 1e9, final=False), 0.0)
        core.offer(KEYS.meas("angle"), encode("watermark", "angle", 9, 40.0, final=False), 0.0)
    else:
        first = next(i for i, (key, data) in enumerate(stream) if key == KEYS.meas("angle"))
        stream = stream[:first] + stream[first + 1:]
        measurements = [m for m in measurements if (m.sensor, m.t) != ("angle", 0.0)]
    out = []
    for key, data in stream:
        core.offer(key, data, 0.0)
        out.extend(core.step(0.0))
    assert dict(reject.by_cause) == ({"future": 2} if case == "refused" else {})
    assert not [e for e in core.events if e.startswith("joined ")]
    ref = run_method(sc, "SS", measurements=measurements)
    assert core.finished and len(out) == len(ref) == 31
    for a, b in zip(out, ref):
        assert a.t == b.t and np.array_equal(a.x, b.x) and np.array_equal(a.P, b.P)


def _schedule(sc) -> dict[str, tuple[float, float]]:
    return {sid: (s.start, s.period) for sid, s in sc.sensors.items()}


def test_a_node_that_runs_alone_while_its_join_is_pending_is_fused_once_joined():
    """A restarted fuser's centre holds a node's request until its scan closes; the node,
    with no answer for its feedback timeout, runs alone meanwhile. Its reports sent while
    the request was pending are fused once the scan closed and the node joined (they
    were refused as "not joined", and the fused output stopped), and the join is one
    event naming the request's time."""
    cfg = TrackerConfig.from_dict({})
    node = TrackNode("radar2d", cfg, "PHHNV", SCHEMES["feedback"])
    events: list[str] = []
    reject = RejectLog("fuser")
    gate = JoinGate(TrackCentre("PHHNV", cfg, SCHEMES["feedback"]), reject, events.append)
    r = [m for m in simulate(1, seed=11, duration=6.0, sensors=(RADAR2D,)).measurements[0] if m.sensor == "radar2d"]
    node.offer(r[0])
    (request,) = node.step()
    assert isinstance(request, InitRequest) and gate.process(request) == []  # its scan is still open
    for m in r[1:4]:
        node.offer(m)
    reports = node.step(alone=True)  # starts from its own r[1]; reports r[2] and r[3]
    assert [u.t for u in reports] == [r[2].t, r[3].t]
    out = [e for u in reports for e in gate.process(u)] + gate.finish()
    assert [e.t for e in out] == [r[0].t, r[2].t, r[3].t] and not reject.by_cause
    assert events == [f"trk-radar2d joined with its request at t = {r[0].t:g} s"]


def test_a_request_refused_as_late_is_made_again_until_one_joins():
    """A node stopped across a fuser restart comes back behind the new centre: its
    request, older than the merged stream, is refused as late and never reaches the
    centre. Once the centre's horizon has passed the request with no init, the node asks
    again with its next measurement (it used to wait for the init for its whole feedback
    timeout, its watermark pinned before the request, stalling the fuser's merge, and
    then ran alone); its first request newer than the centre's stream joins, and its
    reports are fused from that scan on."""
    cfg = TrackerConfig.from_dict({})
    sc = simulate(1, seed=11, duration=12.0, sensors=(ANGLE, RADAR2D)).measurements[0]
    a, r = ([m for m in sc if m.sensor == s] for s in ("angle", "radar2d"))
    radar, angle = (TrackNode(s, cfg, "PHHNV", SCHEMES["feedback"]) for s in ("radar2d", "angle"))
    nodes = {"radar2d": radar, "angle": angle}
    events: list[str] = []
    gate = JoinGate(TrackCentre("PHHNV", cfg, SCHEMES["feedback"]), RejectLog("fuser"), events.append)
    fused: list[Estimate] = []

    def down(t):
        """The centre complete up to ``t``; its downlinks, then (after them, as the fuser
        sends them) its horizon, to every node."""
        fused.extend(gate.advance(t))
        for d in gate.take_downlinks():
            nodes[d.node].receive(d)
        for n in nodes.values():
            n.set_horizon(gate.horizon)

    def scan(ms):
        """Each node's measurement of one scan, and what the nodes send up."""
        down(math.nextafter(ms[0].t, -math.inf))
        for m in ms:
            nodes[m.sensor].offer(m)
        ups = sorted((u for n in nodes.values() for u in n.step()), key=lambda u: (u.t, u.node))
        for u in ups:
            fused.extend(gate.process(u))
        return ups

    for m in r[:5]:  # the restarted centre with the radar alone: its merged stream passes 4.5 s
        scan([m])
    down(4.5)
    assert events == ["trk-radar2d joined with its request at t = 0 s"]
    angle.centre_restarted()  # resumed, it hears of the new fuser: knows no horizon of it yet
    angle.offer(a[1])
    angle.offer(a[2])
    (late,) = angle.step()  # refused by the merger (older than its stream): never reaches the centre
    assert isinstance(late, InitRequest) and late.t == 1.0 and angle.waiting_for == "init"
    angle.set_horizon(gate.horizon)  # the horizon comes down: past the request, and no init
    (again,) = angle.step()
    assert isinstance(again, InitRequest) and again.t == 2.0
    for m in a[3:5]:  # each a request again (refused too), at once: the node catches up
        angle.offer(m)
        (again,) = angle.step()
        assert isinstance(again, InitRequest) and again.t == m.t
    ups = scan([a[5], r[5]])  # its first request newer than the centre's stream: joined
    assert [type(u).__name__ for u in ups] == ["InitRequest", "LocalReport"]
    for i in range(6, 12):
        ups = scan([a[i], r[i]])
        assert sorted(u.node for u in ups) == ["angle", "radar2d"]
    assert events[-1] == "trk-angle joined with its request at t = 5 s"
    assert gate.centre.nodes == {"angle", "radar2d"} and not angle.ran_alone
    assert [e.t for e in fused] == [float(t) for t in range(12)]
