"""The fuser's core, without Zenoh: bad input of every kind, interleaved with a real
scenario's stream, is counted by cause and changes nothing in the fused output."""

from __future__ import annotations

import msgpack
import numpy as np

from fusion.config import method_config
from fusion.methods import make_method
from schemas import KeySpace, encode, encode_measurement
from sensors_sim import load_scenario, sensor_events
from services.evaluation import run_method
from services.fuser import FuserCore
from services.node import RejectLog

from test_schemas import CASES, good

KEYS = KeySpace("unit")


def _wire_stream(scenario):
    """(key, bytes) per sensor in publication order: measurements then a watermark per scan."""
    out = []
    for sid in scenario.sensors:
        wm = 0
        evs = list(sensor_events(scenario, sid))
        for i, ev in enumerate(evs):
            if ev.measurement is not None:
                out.append((ev.t, sid, KEYS.meas(sid), encode_measurement(ev.measurement, sid)))
            wm += 1
            out.append((ev.t, sid, KEYS.meas(sid), encode("watermark", sid, wm, ev.t, final=i == len(evs) - 1)))
    # interleave sources by time, as a network would (stable within a source)
    out.sort(key=lambda r: r[0])
    return [(k, b) for _, _, k, b in out]


def _garbage(sid: str) -> list[bytes]:
    bad = []
    for kind, field, value, _cause in CASES:
        d = good(kind)
        d["src"] = sid
        if "sensor" in d:
            d["sensor"] = sid
        d[field] = value
        bad.append(msgpack.packb(d, use_bin_type=True))
    valid_but_wrong_kind = msgpack.packb({**good("truth"), "src": sid})  # truth has no business on meas/
    return bad + [b"\xc1", b"", msgpack.packb("str"), valid_but_wrong_kind]


def _run(scenario, noisy: bool):
    reject = RejectLog("test")
    core = FuserCore(make_method("SS", method_config(scenario.tracker, "SS")), list(scenario.sensors), KEYS, reject, timeout=1e9)
    garbage = _garbage("radar2d")
    out = []
    for i, (key, data) in enumerate(_wire_stream(scenario)):
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


def test_core_equals_in_process_evaluation():
    sc = load_scenario("patent-3d")
    core_out, _ = _run(sc, noisy=False)
    ref = run_method(sc, "SS")
    assert len(core_out) == len(ref)
    for a, b in zip(core_out, ref):
        assert a.t == b.t and np.array_equal(a.x, b.x) and np.array_equal(a.P, b.P)
