"""fusion.tracking.table: M-of-N track logic, ids, duplicates."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from scipy import stats

from fusion.tracking.hypotheses import gate_threshold, track_distance2
from fusion.tracking.table import (CONFIRMED, DELETED, TENTATIVE, DuplicateWatch, ManagementRule, TrackIds,
                                   TrackLogic)


def run_logic(rule, hits):
    logic = TrackLogic(rule)
    states = [logic.status]
    for h in hits:
        if logic.status == DELETED:
            break
        states.append(logic.record(h))
    return logic, states


@pytest.mark.parametrize("m, n", [(2, 3), (3, 4), (3, 5), (1, 1), (4, 4)])
def test_m_of_n_confirms_exactly_the_sequences_with_m_hits_in_n(m, n):
    """Every hit sequence after birth: confirmed iff ≥ M − 1 hits in the N − 1 frames
    after birth, at the frame where the M-th hit comes, deleted as soon as M became
    impossible; over all sequences the confirmation probability is the binomial tail
    P(Bin(N − 1, p) ≥ M − 1)."""
    rule = ManagementRule(m, n, delete_misses=2)
    p = 0.7
    total = 0.0
    for hits in itertools.product([True, False], repeat=n - 1):
        logic, states = run_logic(rule, hits)
        cumulative = np.cumsum([True, *hits])
        confirmed = cumulative[-1] >= m
        assert (CONFIRMED in states) == confirmed
        if confirmed:
            assert states.index(CONFIRMED) == int(np.argmax(cumulative >= m))
            total += p ** sum(hits) * (1 - p) ** (n - 1 - sum(hits))
        else:
            assert states[-1] == DELETED
            gone = states.index(DELETED)
            assert cumulative[gone] + (n - 1 - gone) < m <= cumulative[gone - 1] + (n - gone)
    assert total == pytest.approx(stats.binom.sf(m - 2, n - 1, p))


def test_confirmed_track_is_deleted_after_k_consecutive_misses_only():
    rule = ManagementRule(1, 1, delete_misses=3)
    logic, states = run_logic(rule, [False, False, True, False, False, True, False, False, False, True])
    assert states[:-1] == [CONFIRMED] * 9 and states[-1] == DELETED
    assert logic.frames == 10  # the 10th entry is the deletion; the last hit is never recorded
    with pytest.raises(ValueError):
        logic.record(True)
    assert TrackLogic(ManagementRule(2, 3)).status == TENTATIVE
    with pytest.raises(ValueError):
        ManagementRule(4, 3)


def test_track_ids_are_issued_in_order_and_never_reused():
    ids = TrackIds()
    assert [ids.next() for _ in range(3)] == ["T1", "T2", "T3"]


def _state(pos, vel, pos_std=30.0, vel_std=5.0):
    x = np.r_[pos, vel, np.zeros(3)]
    P = np.diag(np.r_[[pos_std**2] * 3, [vel_std**2] * 3, [1.0] * 3])
    return x, P


def test_the_later_of_two_agreeing_tracks_goes_after_f_frames():
    """Tracks a and b follow one aircraft 40 m apart (d² = 40²/(2·30²) ≈ 0.9 ≪ G):
    nothing happens for F − 1 frames, b (given second: the later track) goes at the F-th.
    One frame of disagreement restarts the count."""
    watch = DuplicateWatch(frames=3, gate_prob=0.999)
    a = lambda t: _state([200.0 * t, 0.0, 5000.0], [200.0, 0.0, 0.0])  # noqa: E731
    b = lambda t, dy=40.0: _state([200.0 * t, dy, 5000.0], [200.0, 0.0, 0.0])  # noqa: E731
    assert watch.duplicates([("a", *a(0)), ("b", *b(0))]) == []
    assert watch.duplicates([("a", *a(1)), ("b", *b(1))]) == []
    assert watch.duplicates([("a", *a(2)), ("b", *b(2, dy=2000.0))]) == []  # apart once: count again
    assert watch.duplicates([("a", *a(3)), ("b", *b(3))]) == []
    assert watch.duplicates([("a", *a(4)), ("b", *b(4))]) == []
    assert watch.duplicates([("a", *a(5)), ("b", *b(5))]) == ["b"]
    # The order says who stays: the same pair given the other way round loses a.
    again = DuplicateWatch(frames=1, gate_prob=0.999)
    assert again.duplicates([("b", *b(0)), ("a", *a(0))]) == ["a"]
    assert DuplicateWatch(frames=0, gate_prob=0.999).duplicates([("a", *a(0)), ("b", *b(0))]) == []


def test_crossing_aircraft_are_never_merged():
    """Two aircraft at one map point 300 m apart in height, flying at right angles
    (the crossings of the air-picture scenario): their velocities differ by 283 m/s
    against a few m/s of uncertainty, so they never agree, however long they cross."""
    watch = DuplicateWatch(frames=1, gate_prob=0.999)
    east = _state([0.0, 0.0, 5000.0], [200.0, 0.0, 0.0], vel_std=20.0)
    north = _state([0.0, 0.0, 5300.0], [0.0, 200.0, 0.0], vel_std=20.0)
    assert all(watch.duplicates([("E", *east), ("N", *north)]) == [] for _ in range(10))


def test_a_chain_of_duplicates_keeps_the_first():
    """Three tracks on one target, all agreeing: the first stays, both others go in the
    same frame; a track deleted as a duplicate deletes nothing itself."""
    watch = DuplicateWatch(frames=1, gate_prob=0.999)
    tracks = [(k, *_state([dx, 0.0, 5000.0], [200.0, 0.0, 0.0])) for k, dx in (("a", 0.0), ("b", 30.0), ("c", 60.0))]
    assert watch.duplicates(tracks) == ["b", "c"]
    # b and c agree, a is far: c goes (the later of the pair), b stays.
    tracks[0] = ("a", *_state([9000.0, 0.0, 5000.0], [200.0, 0.0, 0.0]))
    assert DuplicateWatch(frames=1, gate_prob=0.999).duplicates(tracks) == ["c"]


@pytest.mark.parametrize("seed", range(5))
def test_the_cheap_distance_bound_never_hides_a_pair_in_the_gate(seed):
    """The pre-filter |Δpos|² ≤ G·tr(T_pos) is a bound of the χ² test: with random
    covariances the watch deletes what the plain pairwise rule (every pair, in order,
    the later of an agreeing pair goes unless the earlier has gone) deletes."""
    rng = np.random.default_rng(seed)
    tracks = []
    for k in range(8):
        A = rng.normal(size=(9, 9))
        tracks.append((k, rng.normal(scale=60.0, size=9), A @ A.T * rng.uniform(10.0, 400.0) + np.eye(9)))
    gone: set[int] = set()
    for i, j in itertools.combinations(range(8), 2):
        d2, rank = track_distance2(tracks[i][1], tracks[i][2], tracks[j][1], tracks[j][2], dims=range(6))
        if i not in gone and d2 <= gate_threshold(rank, 0.99):
            gone.add(j)
    assert 0 < len(gone) < 7  # the case tests something
    assert DuplicateWatch(frames=1, gate_prob=0.99).duplicates(tracks) == sorted(gone)
