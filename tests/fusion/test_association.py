"""fusion.association: χ² gating, global nearest neighbour, M-of-N track logic, ids."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
from scipy import stats

from fusion.association import (
    CONFIRMED,
    DELETED,
    TENTATIVE,
    DuplicateWatch,
    ManagementRule,
    TrackIds,
    TrackLogic,
    gate_threshold,
    gating_update,
    gnn,
    mahalanobis2,
)
from fusion.measurement.kinds import model_for

ALPHA = 0.01


@pytest.mark.parametrize("dof, prob", [(1, 0.99), (2, 0.999), (4, 0.95)])
def test_gate_threshold_is_the_chi2_quantile(dof, prob):
    G = gate_threshold(dof, prob)
    assert stats.chi2.cdf(G, dof) == pytest.approx(prob, abs=1e-12)
    if dof == 2:  # closed form: P(χ²₂ ≤ G) = 1 − e^{−G/2}
        assert G == pytest.approx(-2.0 * math.log(1.0 - prob))


def test_mahalanobis_distance_is_the_closed_form_and_wraps_azimuth():
    """A target due north of the site with only a north-south position variance: the
    azimuth row sees none of it (∂az/∂p_n = 0), so d² = ν_az²/σ_az² + ν_r²/(σ_n² + σ_r²);
    an azimuth measured just below 2π is a small innovation of a target at 0."""
    sa, sr, sn = 0.01, 20.0, 100.0
    model = model_for("range_az", [0.0, 0.0, 0.0], [sa, sr], 9)
    x = np.zeros(9)
    x[:3] = [0.0, 10_000.0, 0.0]
    P = np.zeros((9, 9))
    P[1, 1] = sn**2
    z = np.array([[2 * math.pi - 0.015, 10_050.0], [0.005, 9_990.0]])
    want = [(0.015 / sa) ** 2 + 50.0**2 / (sn**2 + sr**2), (0.005 / sa) ** 2 + 10.0**2 / (sn**2 + sr**2)]
    np.testing.assert_allclose(mahalanobis2(model, x, P, z), want, rtol=1e-9)


def test_sequential_gating_is_the_scalar_kalman_recursion():
    """Two plots of a 2D radar of a target due north with only a north-south position
    variance: the range is then a scalar linear problem. After the first plot the gating
    state is the scalar Kalman update (m₁ = n₀ + σ_n²/(σ_n² + σ_r²)(r₁ − n₀),
    v₁ = σ_n²σ_r²/(σ_n² + σ_r²)), the second plot's d² is (r₂ − m₁)²/(v₁ + σ_r²) plus its
    azimuth term, and the two d² add up to the joint d² of both ranges stacked."""
    sa, sr, sn = 0.01, 20.0, 300.0
    model = model_for("range_az", [0.0, 0.0, 0.0], [sa, sr], 9)
    x = np.zeros(9)
    x[:3] = [0.0, 10_000.0, 0.0]
    P = np.diag([0.0, sn**2, 0.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0])
    z1, z2 = np.array([0.0, 10_200.0]), np.array([0.004, 10_150.0])
    x1, P1 = gating_update(model, x, P, z1)
    m1 = 10_000.0 + sn**2 / (sn**2 + sr**2) * 200.0
    v1 = sn**2 * sr**2 / (sn**2 + sr**2)
    np.testing.assert_allclose([x1[1], P1[1, 1]], [m1, v1], rtol=1e-12)
    d2_second = float(mahalanobis2(model, x1, P1, z2[None, :])[0])
    np.testing.assert_allclose(d2_second, (0.004 / sa) ** 2 + (10_150.0 - m1) ** 2 / (v1 + sr**2), rtol=1e-9)
    nu = np.array([200.0, 150.0])
    joint = nu @ np.linalg.solve(sn**2 * np.ones((2, 2)) + sr**2 * np.eye(2), nu)
    d2_first = float(mahalanobis2(model, x, P, z1[None, :])[0])
    np.testing.assert_allclose(d2_first + d2_second, joint + (0.004 / sa) ** 2, rtol=1e-9)


def test_true_measurements_fall_in_the_gate_with_the_gate_probability():
    """Truth drawn from the track's N(x, P), measurement from N(h(truth), R): with a
    covariance small enough for h to be linear, d² is χ²(2), so a 99 % gate keeps
    99 % of the true plots (binomial test at 1 %, 20 000 draws)."""
    rng = np.random.default_rng(5)
    model = model_for("azel", [100.0, -200.0, 0.0], [1e-3, 1e-3], 6)
    x = np.array([8000.0, 6000.0, 3000.0, 100.0, 0.0, 0.0])
    A = rng.normal(size=(6, 6))
    P = A @ A.T * 10.0 + np.eye(6) * 100.0
    n = 20_000
    truths = rng.multivariate_normal(x, P, size=n)
    z = model.h(truths) + rng.normal(size=(n, 2)) * 1e-3
    d2 = mahalanobis2(model, x, P, z)
    G = gate_threshold(2, 0.99)
    assert stats.binomtest(int(np.sum(d2 <= G)), n, 0.99).pvalue > ALPHA
    assert stats.kstest(d2, stats.chi2(2).cdf).pvalue > ALPHA


def brute_force_cost(d2, gate):
    """Least total cost over every partial matching: Σ assigned d² + G·(missed rows)."""
    n, m = d2.shape
    best = gate * n
    for k in range(1, min(n, m) + 1):
        for rows in itertools.combinations(range(n), k):
            for cols in itertools.permutations(range(m), k):
                c = d2[list(rows), list(cols)]
                if np.all(c <= gate):
                    best = min(best, float(c.sum()) + gate * (n - k))
    return best


@pytest.mark.parametrize("seed", range(40))
def test_gnn_is_the_least_cost_assignment(seed):
    rng = np.random.default_rng(seed)
    n, m = rng.integers(1, 5, size=2)
    d2 = rng.chisquare(2, size=(n, m)) * rng.choice([0.5, 3.0])
    gate = 9.21
    pairs = gnn(d2, gate)
    rows, cols = [p[0] for p in pairs], [p[1] for p in pairs]
    assert len(set(rows)) == len(rows) and len(set(cols)) == len(cols)
    assert all(d2[r, c] <= gate for r, c in pairs)  # never outside the gate
    cost = sum(d2[r, c] for r, c in pairs) + gate * (n - len(pairs))
    assert cost == pytest.approx(brute_force_cost(d2, gate), abs=1e-9)


def test_gnn_prefers_the_global_optimum_to_the_greedy_one():
    # greedy takes (0,0) = 1 and leaves row 1 with its gate; the optimum swaps
    d2 = np.array([[1.0, 2.0], [1.5, 20.0]])
    assert gnn(d2, gate=9.0) == [(0, 1), (1, 0)]
    assert gnn(np.empty((0, 3)), 9.0) == [] and gnn(np.full((2, 2), 50.0), 9.0) == []


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
    from fusion.association import track_distance2

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
