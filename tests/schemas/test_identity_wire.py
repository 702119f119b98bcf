"""A cooperative target's identity on the wire: optional ``identity`` {address, callsign}
on measurements and ``track`` messages, through the fast and the strict paths alike (same
bytes, same message), validated field by field; absent where there is none, leaving the
bytes of such a message unchanged."""

from __future__ import annotations

import msgpack
import numpy as np
import pytest

from fusion.types import Estimate, Identity, Measurement
from schemas import SchemaError, decode, encode, encode_estimate, encode_measurement, to_estimate, to_measurement
from schemas.messages import _estimate_payload, _validate_fast, _validate_strict, measurement_fields

IDENTITIES = [Identity("4ca7b1", "RYR1234"), Identity("~a1b2c3", None), Identity(None, "AFR 12"),
              Identity("39b002", "ABCDEFGH")]


def _report(identity) -> Measurement:
    return Measurement(12.5, "adsb", "position", np.array([1000.0, -2000.0, 9000.0]), np.array([30.0, 30.0, 15.0]),
                       np.zeros(3), 4, identity=identity)


def _track(identity) -> Estimate:
    x = np.array([1000.0, -2000.0, 5000.0, 0.0, 100.0, 0.0])
    return Estimate(12.0, x, np.diag([400.0, 100.0, 900.0, 1.0, 1.0, 1.0]), "SS", "centre", "T1", 2.5, 3,
                    identity=identity)


@pytest.mark.parametrize("identity", IDENTITIES)
def test_a_reports_identity_round_trips_by_both_paths(identity):
    m = _report(identity)
    data = encode_measurement(m, "adsb")
    d = msgpack.unpackb(data)
    assert d["identity"] == {k: v for k, v in (("address", identity.address), ("callsign", identity.callsign)) if v}
    assert to_measurement(decode(data)) == m
    fast, strict = _validate_fast(d), _validate_strict(d)
    assert fast is not None and to_measurement(fast) == to_measurement(strict) == m  # the fast path takes it


@pytest.mark.parametrize("identity", IDENTITIES)
def test_a_tracks_identity_round_trips_by_both_paths(identity):
    e = _track(identity)
    data = encode_estimate(e, "fuser", 7)
    assert data == encode("track", "fuser", 7, e.t, **_estimate_payload(e))  # fast encoder = strict
    assert to_estimate(decode(data)).identity == identity
    d = msgpack.unpackb(data)
    assert _validate_fast(d) is not None and to_estimate(_validate_strict(d)).identity == identity


def test_no_identity_leaves_the_messages_as_they_were():
    assert "identity" not in msgpack.unpackb(encode_measurement(_report(None), "adsb"))
    assert "identity" not in msgpack.unpackb(encode_estimate(_track(None), "fuser", 7))
    assert to_estimate(decode(encode_estimate(_track(None), "fuser", 7))).identity is None


@pytest.mark.parametrize("bad, cause, field", [
    ({"address": "4CA7B1"}, "value", "identity.address"),  # upper case
    ({"address": "4ca7b1ff0"}, "value", "identity.address"),  # nine characters
    ({"address": "4ca7g1"}, "value", "identity.address"),
    ({"address": "~"}, "value", "identity.address"),
    ({"address": ""}, "value", "identity.address"),
    ({"address": 0x4ca7b1}, "type", "identity.address"),
    ({"callsign": "RYR12345X"}, "value", "identity.callsign"),  # nine characters
    ({"callsign": "ryr1"}, "value", "identity.callsign"),
    ({"callsign": "RYR-1"}, "value", "identity.callsign"),
    ({"callsign": ""}, "value", "identity.callsign"),
    ({}, "value", "identity"),
    ({"address": None, "callsign": None}, "value", "identity"),
    ({"address": "4ca7b1", "squawk": "7700"}, "unknown-field", "squawk"),
    ("4ca7b1", "type", "identity"),
    (None, "type", "identity"),
])
@pytest.mark.parametrize("message", ["meas", "track"])
def test_a_bad_identity_is_refused_by_name(bad, cause, field, message):
    base = encode_measurement(_report(None), "adsb") if message == "meas" else encode_estimate(_track(None), "f", 7)
    d = msgpack.unpackb(base)
    d["identity"] = bad
    assert _validate_fast(d) is None
    with pytest.raises(SchemaError) as e:
        decode(msgpack.packb(d))
    assert (e.value.cause, e.value.field) == (cause, field)
    if message == "meas":
        with pytest.raises(SchemaError):
            encode("position", "adsb", 4, 12.5, **{**measurement_fields(_report(None)), "identity": bad})
