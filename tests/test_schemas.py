"""Wire format: round trips, and a named, counted error for every bad field of every kind."""

from __future__ import annotations

import math

import msgpack
import numpy as np
import pytest

from fusion.types import Estimate, Measurement
from schemas import KeySpace, SchemaError, decode, encode, encode_estimate, encode_measurement, to_estimate, \
    to_measurement

SITE = [1.0, 2.0, 3.0]


def _pack(d: dict) -> bytes:
    return msgpack.packb(d, use_bin_type=True)


def good(kind: str) -> dict:
    env = {"v": 1, "kind": kind, "src": "s1", "seq": 3, "t": 2.0}
    body = {
        "bearing": {"sensor": "s1", "site": SITE, "az": 0.1, "std_az": 0.01},
        "azel": {"sensor": "s1", "site": SITE, "az": 6.2, "std_az": 0.001, "el": 0.2, "std_el": 0.001},
        "range_az": {"sensor": "s1", "site": SITE, "az": 3.0, "std_az": 0.02, "range": 1e4, "std_range": 20.0},
        "az_el_range": {"sensor": "s1", "site": SITE, "az": 1.0, "std_az": 0.02, "el": -0.1, "std_el": 0.02,
                        "range": 5e3, "std_range": 10.0},
        "watermark": {"final": False},
        "track": {"track": "T1", "node": "centre", "method": "SS", "x": [1.0, 2.0], "P": [[2.0, 0.1], [0.1, 3.0]],
                  "nis": 1.5, "nis_dof": 2},
        "prediction": {"track": "T1", "node": "radar2d", "method": "DDHNV", "x": [1.0], "P": [[1.0]]},
        "truth": {"target": "T1", "x": [1.0, 2.0, 3.0]},
        "jam_state": {"pos": SITE, "on": True, "mode": "barrage", "power": 100.0, "law": "uniform",
                      "affects": ["s1"]},
        "status": {"state": "running", "role": "sensor", "counters": {"published": 4}, "events": ["x"]},
    }[kind]
    return {**env, **body}


ALL_KINDS = ["bearing", "azel", "range_az", "az_el_range", "watermark", "track", "prediction", "truth",
             "jam_state", "status"]


@pytest.mark.parametrize("kind", ALL_KINDS)
def test_good_messages_validate(kind):
    msg = decode(_pack(good(kind)))
    assert msg.kind == kind and msg.src == "s1" and msg.seq == 3 and msg.t == 2.0


# (field, bad value, expected cause) for each kind; every field of every kind is covered.
BAD_ENVELOPE = [("v", 2, "version"), ("v", None, "version"), ("kind", "nope", "kind"), ("kind", 3, "type"),
                ("src", "a/b", "value"), ("src", 5, "type"), ("seq", -1, "range"), ("seq", 1.5, "type"),
                ("t", math.nan, "non-finite"), ("t", math.inf, "non-finite"), ("t", "0", "type")]
BAD_FIELDS = {
    "bearing": [("az", 2 * math.pi, "range"), ("az", -0.1, "range"), ("az", math.nan, "non-finite"),
                ("std_az", 0.0, "range"), ("std_az", -1.0, "range"), ("site", [1.0, 2.0], "shape"),
                ("site", [1.0, math.nan, 2.0], "non-finite"), ("site", "x", "type"), ("sensor", "a b", "value"),
                ("extra_field", 1, "unknown-field")],
    "azel": [("el", 2.0, "range"), ("el", -1.6, "range"), ("std_el", math.inf, "non-finite"),
             ("az", True, "type")],
    "range_az": [("range", 0.0, "range"), ("range", -5.0, "range"), ("std_range", 0.0, "range"),
                 ("el", 0.1, "unknown-field")],
    "az_el_range": [("range", math.nan, "non-finite"), ("std_el", "1", "type")],
    "watermark": [("final", "yes", "type")],
    "track": [("x", [], "shape"), ("x", [[1.0]], "shape"), ("P", [[1.0, 0.0], [5.0, 1.0]], "value"),
              ("P", [[1.0]], "shape"), ("P", [[-1.0, 0.0], [0.0, 1.0]], "value"), ("nis", -1.0, "range"),
              ("nis_dof", 0, "range"), ("track", "", "value"), ("node", None, "missing"), ("method", 1, "type"),
              ("x", [1.0] * 100, "shape"), ("extra", [1], "type")],
    "prediction": [("x", [math.inf], "non-finite")],
    "truth": [("x", [math.nan], "non-finite"), ("target", "*", "value")],
    "jam_state": [("on", 1, "type"), ("mode", "sweep", "value"), ("law", "gauss", "value"),
                  ("power", -1.0, "range"), ("affects", "s1", "type"), ("pos", [0.0], "shape")],
    "status": [("state", "weird", "value"), ("counters", {"a": "b"}, "type"), ("events", [1], "type"),
               ("role", None, "missing"), ("sources", {"s": {"dead_intervals": [[0, "x"]]}}, "type")],
}
CASES = [(k, f, v, c) for k in ALL_KINDS for f, v, c in BAD_ENVELOPE if not (f == "kind" and v == "nope")] + \
        [(k, f, v, c) for k, rows in BAD_FIELDS.items() for f, v, c in rows]


@pytest.mark.parametrize("kind,field,value,cause", CASES)
def test_bad_field_gives_named_error(kind, field, value, cause):
    d = good(kind)
    d[field] = value
    with pytest.raises(SchemaError) as ei:
        decode(_pack(d))
    assert ei.value.cause == cause
    if cause not in ("version",):
        assert field in str(ei.value) or ei.value.field == field


@pytest.mark.parametrize("kind", ALL_KINDS)
def test_missing_required_field(kind):
    d = good(kind)
    required = [k for k in d if k not in ("final", "nis", "nis_dof", "affects", "counters", "events")]
    for f in required:
        dd = dict(d)
        del dd[f]
        with pytest.raises(SchemaError) as ei:
            decode(_pack(dd))
        assert ei.value.cause in ("missing", "version"), (f, ei.value)


@pytest.mark.parametrize("data,cause", [(b"\xc1", "malformed"), (b"", "malformed"), (_pack([1, 2]), "not-a-map"),
                                        (b"\x93\x01", "malformed"), (b"x" * (2 << 20), "too-large")])
def test_garbage_bytes(data, cause):
    with pytest.raises(SchemaError) as ei:
        decode(data)
    assert ei.value.cause == cause


def test_measurement_round_trip_is_exact():
    rng = np.random.default_rng(1)
    for kind, n in [("bearing", 1), ("azel", 2), ("range_az", 2), ("az_el_range", 3)]:
        z = rng.uniform(0.01, 1.0, n)
        if kind in ("range_az", "az_el_range"):
            z[-1] = rng.uniform(1, 1e5)
        m = Measurement(rng.uniform(0, 100), "radar-1", kind, z, rng.uniform(0.1, 1, n), rng.normal(size=3), 7)
        assert to_measurement(decode(encode_measurement(m, "radar-1"))) == m


def test_estimate_round_trip_is_exact():
    rng = np.random.default_rng(2)
    A = rng.normal(size=(9, 9))
    e = Estimate(3.25, rng.normal(size=9), A @ A.T, "SS", "centre", "T1", 2.5, 3, {"KH": rng.normal(size=(9, 9))})
    back = to_estimate(decode(encode_estimate(e, "fuser", 1)))
    assert np.array_equal(back.x, e.x) and np.array_equal(back.P, e.P) and back.nis == e.nis
    assert np.array_equal(back.extra["KH"], e.extra["KH"])


def test_encode_refuses_invalid():
    with pytest.raises(SchemaError):
        encode("bearing", "s1", 0, 0.0, sensor="s1", site=SITE, az=7.0, std_az=0.1)


def test_key_space():
    k = KeySpace("test-1")
    assert k.meas("radar2d") == "zf/test-1/meas/radar2d"
    assert k.family_and_id("zf/test-1/meas/radar2d") == ("meas", "radar2d")
    assert k.family_and_id(k.fused()) == ("fused", None)
    with pytest.raises(ValueError):
        k.meas("a/b")
    with pytest.raises(ValueError):
        KeySpace("**")
    with pytest.raises(ValueError):
        k.family_and_id("zf/other/meas/x")
