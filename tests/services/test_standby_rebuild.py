"""A standby joining a running leader rebuilds its track from the leader's picture
(services/leader.py ``rebuild``): in process, the picture as the leader serves it (the
encoded estimates, through :func:`services.picture.documents`), a fresh method started
from it, and the measurements after the picture's scan give the leader's estimates bit
for bit, seq numbers included; a method whose state is more than its published track is
left alone."""

from __future__ import annotations

import numpy as np
import pytest

from fusion.methods import make_method, method_config
from schemas import encode_estimate
from sensors_sim import load_scenario
from services.evaluation import merged_measurements, run_method
from services.leader import rebuild
from services.picture import Picture, documents

SCENARIO = "patent-3d-orbit"


def _stream(sc):
    return [m for m in merged_measurements(sc, 0) if m.t <= 120.0]


def _picture(estimates) -> dict:
    """The leader's picture after it published ``estimates`` (seq 1, 2, ...)."""
    picture = Picture("fuser")
    for seq, e in enumerate(estimates, 1):
        picture.published(e, encode_estimate(e, "fuser", seq))
    return documents(picture.replies())["fuser"]


def _after(method, stream, t):
    """What ``method`` emits on the part of ``stream`` after ``t``, fed as a fuser does."""
    return run_method(None, "", measurements=[m for m in stream if m.t > t], method=method)


@pytest.mark.parametrize("name", ["SS", "LCDD", "HNDD", "ANGLE"])
@pytest.mark.parametrize("k", [1, 7, 60])
def test_a_rebuilt_standby_is_the_leader_bit_for_bit(name, k):
    """Joined after the leader's k-th estimate: every later estimate equal (x, P, NIS,
    time, track id) and numbered on from the leader's seq; a standby that starts afresh
    from the same data instead (what it did before) is not."""
    sc = load_scenario(SCENARIO)
    config = method_config(sc.tracker, name, {})
    stream = _stream(sc)
    leader = run_method(sc, name, measurements=stream)
    standby = make_method(name, config)
    got = rebuild(standby, _picture(leader[:k]))
    assert got is not None and got.seq == k and got.tracks == ("T1",)
    after = _after(standby, stream, got.t)
    expected = leader[k:]
    assert len(after) == len(expected) > 20
    for a, b in zip(after, expected):
        assert (a.t, a.track, a.nis, a.nis_dof) == (b.t, b.track, b.nis, b.nis_dof)
        assert np.array_equal(a.x, b.x) and np.array_equal(a.P, b.P)
    fresh = _after(make_method(name, config), stream, got.t)
    assert not np.array_equal(fresh[-1].P, expected[-1].P)


def test_what_cannot_be_rebuilt_is_left_alone():
    """No picture, a picture without tracks, a many-target method and a picture of two
    tracks: no rebuild, the method as built."""
    sc = load_scenario(SCENARIO)
    stream = _stream(sc)
    leader = run_method(sc, "SS", measurements=stream)
    ss = make_method("SS", method_config(sc.tracker, "SS", {}))
    assert rebuild(ss, None) is None and rebuild(ss, _picture([])) is None and ss.filter is None
    two = _picture(leader[:3])
    two["tracks"].append(dict(two["tracks"][0], id="T2"))
    assert rebuild(ss, two) is None and ss.filter is None
    many = make_method("SS", method_config({**sc.tracker, "association": "gnn"}, "SS", {}))
    assert rebuild(many, _picture(leader[:3])) is None
