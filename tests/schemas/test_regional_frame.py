"""The regional_frame message (a regional fuser's frame for the system fuser): a round
trip bit for bit, and each malformed part refused by field and cause."""

from __future__ import annotations

import msgpack
import numpy as np
import pytest

from fusion.regional import RegionalFrame
from fusion.types import Estimate, Identity
from schemas import SchemaError, decode
from schemas.links import encode_regional_frame, regional_frame
from schemas.messages import FRAME_MAX


def _frame() -> RegionalFrame:
    rng = np.random.default_rng(3)
    A = rng.normal(size=(6, 6))
    tracks = (Estimate(10.25, rng.normal(size=6), A @ A.T, "SS", "west", "west.T1", nis=2.5, nis_dof=3),
              Estimate(10.5, rng.normal(size=9), np.eye(9), "SS", "west", "west.T4", existence=0.9,
                       identity=Identity("4ca1f2", "EIN21")))
    return RegionalFrame("west", 10.0, tracks, ("west.T2", "west.T3"))


def test_a_frame_crosses_the_wire_bit_for_bit():
    f = _frame()
    g = regional_frame(decode(encode_regional_frame(f, "west", 7)))
    assert (g.region, g.t, g.dropped) == (f.region, f.t, f.dropped)
    for a, b in zip(f.tracks, g.tracks):
        assert (a.t, a.track, a.node, a.method, a.nis, a.nis_dof, a.existence, a.identity) == \
            (b.t, b.track, b.node, b.method, b.nis, b.nis_dof, b.existence, b.identity)
        assert np.array_equal(a.x, b.x) and np.array_equal(a.P, b.P)


def _tamper(**changes) -> bytes:
    d = msgpack.unpackb(encode_regional_frame(_frame(), "west", 7), raw=False)
    for path, value in changes.items():
        *parents, last = path.split("__")
        node = d
        for p in parents:
            node = node[int(p)] if p.isdigit() else node[p]
        if value is KeyError:
            del node[last]
        else:
            node[last] = value
    return msgpack.packb(d, use_bin_type=True)


@pytest.mark.parametrize("changes,cause,field", [
    ({"tracks": "no"}, "type", "tracks"),
    ({"tracks": [{}] * (FRAME_MAX + 1)}, "type", "tracks"),
    ({"tracks__0__t": KeyError}, "missing", "tracks.t"),
    ({"tracks__0__x": [float("nan")] * 6}, "non-finite", "tracks.x"),
    ({"tracks__1__P": [[1.0, 2.0], [3.0, 4.0]]}, "shape", "tracks.P"),
    ({"tracks__0__track": "a/b"}, "value", "tracks.track"),
    ({"tracks__0__colour": "red"}, "unknown-field", "tracks.colour"),
    ({"dropped": ["ok", "no/slash"]}, "value", "dropped"),
    ({"dropped": "west.T2"}, "type", "dropped"),
    ({"extra": 1}, "unknown-field", "extra"),
])
def test_a_malformed_frame_is_refused_by_field_and_cause(changes, cause, field):
    with pytest.raises(SchemaError) as e:
        decode(_tamper(**changes))
    assert (e.value.cause, e.value.field) == (cause, field)
