"""Wire format: round trips, and a named, counted error for every bad field of every kind."""

from __future__ import annotations


import numpy as np
import pytest

from fusion.types import Estimate, Measurement
from schemas import KeySpace, SchemaError, decode, encode, encode_estimate, encode_measurement, to_estimate, \
    to_measurement
from _wire import ALL_KINDS, CASES, OPTIONAL, SITE, good, pack, with_field

@pytest.mark.parametrize("kind", ALL_KINDS)
def test_good_messages_validate(kind):
    msg = decode(pack(good(kind)))
    assert msg.kind == kind and msg.src == "s1" and msg.seq == 3 and msg.t == 2.0


@pytest.mark.parametrize("kind,field,value,cause", CASES)
def test_bad_field_gives_named_error(kind, field, value, cause):
    with pytest.raises(SchemaError) as ei:
        decode(pack(with_field(good(kind), field, value)))
    assert ei.value.cause == cause
    if cause not in ("version",):
        assert field in str(ei.value) or ei.value.field == field


@pytest.mark.parametrize("kind", ALL_KINDS)
def test_missing_required_field(kind):
    d = good(kind)
    required = [k for k in d if k not in OPTIONAL]
    for f in required:
        dd = dict(d)
        del dd[f]
        with pytest.raises(SchemaError) as ei:
            decode(pack(dd))
        assert ei.value.cause in ("missing", "version"), (f, ei.value)


@pytest.mark.parametrize("data,cause", [(b"\xc1", "malformed"), (b"", "malformed"), (pack([1, 2]), "not-a-map"),
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
    assert k.family_and_id(k.fused("fuser")) == ("fused", "fuser")
    with pytest.raises(ValueError):
        k.meas("a/b")
    with pytest.raises(ValueError):
        KeySpace("**")
    with pytest.raises(ValueError):
        k.family_and_id("zf/other/meas/x")
