"""A standby joining a running leader rebuilds its tracks from the leader's picture
(services/leader.py ``rebuild``): in process, the picture as the leader serves it (the
encoded estimates, through :func:`services.picture.documents`), a fresh method started
from it, and the measurements after the picture's scan give the leader's estimates bit
for bit, seq numbers included (one target; many targets once every track is confirmed),
or converging to them (a track tentative at the join); a method whose state is more
than its published tracks is left alone."""

from __future__ import annotations

import numpy as np
import pytest

from fusion.methods import make_method, method_config
from schemas import encode_estimate
from sensors_sim import load_scenario
from services.evaluation import merged_measurements, run_method
from services.leader import rebuild
from services.fuser import _delete_misses
from services.picture import Picture, documents

from conftest import ROOT

SCENARIO = "patent-3d-orbit"
CROSSING = str(ROOT / "tests" / "data" / "crossing.toml")  # three aircraft crossing in clutter


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


def _picture_at(estimates, t: float, delete_misses: int) -> dict:
    picture = Picture("fuser", delete_misses)
    for seq, e in enumerate([e for e in estimates if e.t <= t], 1):
        picture.published(e, encode_estimate(e, "fuser", seq))
    return documents(picture.replies())["fuser"]


def _many(stream_of: str):
    sc = load_scenario(stream_of)
    stream = list(merged_measurements(sc, 0))
    return sc, stream, run_method(sc, "SS", measurements=stream), method_config(sc.tracker, "SS", {})


@pytest.mark.parametrize("at", [7.0, 30.0])
def test_a_many_target_standby_joined_with_every_track_confirmed_is_the_leader(at):
    """Three aircraft crossing in clutter (SS, GNN): joined once the three tracks are
    confirmed, the rebuilt table's later estimates are the leader's, bit for bit, ids
    included; a standby that starts afresh from the same data numbers other tracks."""
    sc, stream, leader, config = _many(CROSSING)
    standby = make_method("SS", config)
    got = rebuild(standby, _picture_at(leader, at, _delete_misses(sc)))
    assert got is not None and got.tracks == ("T1", "T2", "T3")
    after = _after(standby, stream, got.t)
    expected = [e for e in leader if e.t > at]
    assert len(after) == len(expected) > 40
    for a, b in zip(after, expected):
        assert (a.t, a.track) == (b.t, b.track) and np.array_equal(a.x, b.x) and np.array_equal(a.P, b.P)
    fresh = _after(make_method("SS", config), stream, got.t)
    assert [(e.t, e.track) for e in fresh] != [(e.t, e.track) for e in expected]


def test_a_track_tentative_at_the_join_converges():
    """Joined at 4 s, when one track is confirmed and two are tentative (not in the
    picture): the standby starts those two again from the scans after the join, so their
    ids come out the same (98.8 % of the leader's later (t, id) pairs present) but their
    states only converge: 100.8 m apart at most, 0.66 m at the last frame, against the
    leader's 62.6 m position std."""
    sc, stream, leader, config = _many(CROSSING)
    at = 4.0
    standby = make_method("SS", config)
    got = rebuild(standby, _picture_at(leader, at, _delete_misses(sc)))
    assert got is not None and len(got.tracks) == 1
    mine = {(e.t, e.track): e for e in _after(standby, stream, got.t)}
    theirs = {(e.t, e.track): e for e in leader if e.t > at}
    common = [k for k in theirs if k in mine]
    assert len(common) >= 0.95 * len(theirs)
    assert any(not np.array_equal(mine[k].x, theirs[k].x) for k in common)  # not equal: converging
    end = max(t for t, _ in common)
    for k in (k for k in common if k[0] == end):
        sigma = np.sqrt(np.trace(theirs[k].P[:3, :3]))
        assert np.linalg.norm(mine[k].x[:3] - theirs[k].x[:3]) < 0.05 * sigma


def test_what_cannot_be_rebuilt_is_left_alone():
    """No picture, a picture without tracks, a one-target method given two tracks, and a
    many-target JIPDA tracker (its tracks' existence and logic are not in the picture):
    no rebuild, the method as built."""
    sc = load_scenario(SCENARIO)
    stream = _stream(sc)
    leader = run_method(sc, "SS", measurements=stream)
    ss = make_method("SS", method_config(sc.tracker, "SS", {}))
    assert rebuild(ss, None) is None and rebuild(ss, _picture([])) is None and ss.filter is None
    two = _picture(leader[:3])
    two["tracks"].append(dict(two["tracks"][0], id="T2"))
    assert rebuild(ss, two) is None and ss.filter is None
    jipda = make_method("SS", method_config({**sc.tracker, "association": "jipda"}, "SS", {}))
    assert rebuild(jipda, _picture(leader[:3])) is None and not jipda.tracks
