"""JIPDA of one scan (fusion.tracking.jipda) against independent references: Stone Soup's ``JPDA``
with ``PDAHypothesiser`` and ``PDAUpdater`` on the same plots (a linear position model
and the nonlinear spherical ones), brute-force enumeration of the joint events, the
IPDA's closed-form existence recursion on one track, the Gaussian-mixture form of the
PDA update; the loopy-belief-propagation approximation against the exact sum; and the
properties (rows of β sum to one, a plot's β over tracks at most one, P⁺ positive
definite)."""

from __future__ import annotations

import datetime as dt
import itertools
import math

import numpy as np
import pytest
from scipy.stats import chi2, multivariate_normal

from stonesoup.dataassociator.probability import JPDA
from stonesoup.hypothesiser.probability import PDAHypothesiser
from stonesoup.models.measurement.linear import LinearGaussian
from stonesoup.models.measurement.nonlinear import CartesianToElevationBearing, CartesianToElevationBearingRange
from stonesoup.models.transition.linear import CombinedLinearGaussianTransitionModel, ConstantVelocity
from stonesoup.predictor.kalman import KalmanPredictor
from stonesoup.types.angle import Bearing, Elevation
from stonesoup.types.detection import Detection
from stonesoup.types.state import GaussianState
from stonesoup.types.track import Track
from stonesoup.updater.kalman import ExtendedKalmanUpdater
from stonesoup.updater.probability import PDAUpdater

from fusion import kalman
from fusion.tracking.jipda import (EXACT_EVENTS, JIPDA, ClutterWindow, ExistenceRule, best_permutation_marginals, clusters, clutter_density, exact_marginals, existence_update,
                          hypothesise, ipda_existence, lbp_marginals, marginals, n_events_bound, pda_update,
                          scan_update)
from fusion.measurement.models import SphericalModel

DEG = math.pi / 180.0
T0 = dt.datetime(2024, 1, 1)
# Stone Soup orders a 3D constant-velocity state [x vx y vy z vz]; ours is [e n u ve vn vu].
PERM = np.array([0, 2, 4, 1, 3, 5])  # ours[k] = stonesoup[PERM[k]]
INV = np.argsort(PERM)


class PositionModel:
    """A linear model of the position, ``z = p + v``: the protocol's minimum."""

    def __init__(self, std: float, n_x: int = 6):
        self.n_z, self.n_x = 3, n_x
        self.R = np.eye(3) * std**2
        self.angles = np.zeros(3, dtype=bool)
        self._H = np.eye(3, n_x)

    def h(self, x):
        return np.asarray(x, dtype=float)[..., :3]

    def jacobian(self, x):
        return self._H

    def residual(self, z, z_hat):
        return np.asarray(z, dtype=float) - z_hat


# Stone Soup references -------------------------------------------------------------------
class AnalyticElevationBearingRange(CartesianToElevationBearingRange):
    """Stone Soup's model with its Jacobian in closed form (its own is by finite
    differences, good to ~1e-7): el, bearing counter-clockwise from x, range."""

    def jacobian(self, state, **kwargs):
        return _ss_jacobian(self, state, with_range=True)


class AnalyticElevationBearing(CartesianToElevationBearing):
    def jacobian(self, state, **kwargs):
        return _ss_jacobian(self, state, with_range=False)


def _ss_jacobian(model, state, with_range):
    x, y, z = (np.asarray(state.state_vector, float)[list(model.mapping), 0]
               - np.asarray(model.translation_offset, float)[:, 0])
    rho2 = x * x + y * y
    rho = math.sqrt(rho2)
    r2 = rho2 + z * z
    rows = [[-x * z / (rho * r2), -y * z / (rho * r2), rho / r2],  # elevation
            [-y / rho2, x / rho2, 0.0]]  # bearing = atan2(y, x)
    if with_range:
        r = math.sqrt(r2)
        rows.append([x / r, y / r, z / r])
    H = np.zeros((len(rows), model.ndim_state))
    H[:, list(model.mapping)] = rows
    return H


def _to_ss_z(kind, z):
    """Our measurement (compass az first) as Stone Soup's (elevation, bearing ccw from x[, range])."""
    if kind == "position":
        return np.asarray(z, float).reshape(-1, 1)
    bearing = math.atan2(math.cos(z[0]), math.sin(z[0]))  # π/2 − az, in (−π, π]
    return np.array([[Elevation(z[1])], [Bearing(bearing)], *([[z[2]]] if kind == "az_el_range" else [])])


def _ss_model(kind, model):
    if kind == "position":
        return LinearGaussian(ndim_state=6, mapping=(0, 2, 4), noise_covar=model.R)
    std = model.std
    offset = np.asarray(model.site, float).reshape(3, 1)
    if kind == "az_el_range":
        return AnalyticElevationBearingRange(ndim_state=6, mapping=(0, 2, 4), translation_offset=offset,
                                             noise_covar=np.diag([std[1] ** 2, std[0] ** 2, std[2] ** 2]))
    return AnalyticElevationBearing(ndim_state=6, mapping=(0, 2, 4), translation_offset=offset,
                                    noise_covar=np.diag([std[1] ** 2, std[0] ** 2]))


class PerTrackHypothesiser(PDAHypothesiser):
    """Stone Soup's PDA hypothesiser with a P_D per track: JPDA with ``P_D rᵢ`` in place of
    ``P_D`` is JIPDA's joint association (its miss weight ``1 − P_D rᵢ P_G``, its plot
    weights ``P_D rᵢ N/ρ``)."""

    def hypothesise(self, track, detections, timestamp, **kwargs):
        self.prob_detect = track.metadata["p_detect"]
        return super().hypothesise(track, detections, timestamp, **kwargs)


def stonesoup_jpda(kind, model, states, Z, p_detect, gate_prob, density, r=None):
    """``(β (n, m + 1), x⁺, P⁺)`` from Stone Soup's JPDA + PDAUpdater (states in our order)."""
    ss_model = _ss_model(kind, model)
    predictor = KalmanPredictor(CombinedLinearGaussianTransitionModel([ConstantVelocity(1.0)] * 3))
    updater = ExtendedKalmanUpdater(ss_model)
    hyp = PerTrackHypothesiser(predictor, updater, clutter_spatial_density=density, prob_detect=p_detect,
                               prob_gate=gate_prob)
    r = np.ones(len(states)) if r is None else r
    tracks = [Track([GaussianState(x[INV].reshape(-1, 1), P[np.ix_(INV, INV)], timestamp=T0)],
                    init_metadata={"p_detect": p_detect * ri}) for (x, P), ri in zip(states, r)]
    detections = [Detection(_to_ss_z(kind, z), timestamp=T0, measurement_model=ss_model) for z in Z]
    associated = JPDA(hyp).associate(set(tracks), set(detections), T0)
    pda = PDAUpdater(ss_model)
    beta = np.zeros((len(tracks), len(Z) + 1))
    xs, Ps = [], []
    for i, track in enumerate(tracks):
        for h in associated[track]:
            j = 0 if not h else 1 + detections.index(h.measurement)
            beta[i, j] = float(h.probability)
        post = pda.update(associated[track])
        xs.append(np.asarray(post.state_vector, float)[PERM, 0])
        Ps.append(np.asarray(post.covar, float)[np.ix_(PERM, PERM)])
    return beta, xs, Ps


# Scenes -------------------------------------------------------------------------------------
def _scene(kind, seed, n_tracks=3, n_clutter=6):
    """A few tracks close together, each detected (P_D), plots of a neighbour in its gate,
    and clutter around them: the model, the tracks' predicted states and the plots."""
    rng = np.random.default_rng(seed)
    if kind == "position":
        model = PositionModel(30.0)
        centre = np.array([20000.0, 30000.0, 5000.0])
    elif kind == "az_el_range":
        model = SphericalModel(("az", "el", "range"), [1000.0, -2000.0, 50.0], (1.0 * DEG, 0.7 * DEG, 25.0), n_x=6)
        centre = np.array([1500.0, 28000.0, 6000.0])  # due north of the site: azimuth wraps at 0/2π
    else:
        model = SphericalModel(("az", "el"), [-500.0, 300.0, 0.0], (0.3 * DEG, 0.3 * DEG), n_x=6)
        centre = np.array([14000.0, 22000.0, 4000.0])
    states, truths = [], []
    for _ in range(n_tracks):
        p = centre + rng.normal(0.0, 300.0, 3)
        A = rng.normal(size=(6, 6))
        P = A @ A.T * 20.0 + np.diag([200.0**2] * 3 + [30.0**2] * 3)
        x = np.concatenate([p, rng.normal(0.0, 100.0, 3)])
        states.append((x, P))
        truths.append(x + rng.multivariate_normal(np.zeros(6), P))
    Z = [model.h(t) + rng.normal(size=model.n_z) * np.sqrt(np.diag(model.R)) for t in truths]
    spread = np.sqrt(np.diag(model.R)) * 6.0 + (np.array([0.02, 0.02, 600.0])[:model.n_z] if kind != "position" else 600.0)
    Z += [model.h(states[rng.integers(n_tracks)][0]) + rng.uniform(-1.0, 1.0, model.n_z) * spread
          for _ in range(n_clutter)]
    Z = np.array(Z)[rng.permutation(len(Z))]
    if kind != "position":
        Z[:, 0] = np.mod(Z[:, 0], 2.0 * math.pi)
    return model, states, Z


KINDS = ["position", "az_el_range", "azel"]


@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_jpda_matches_stonesoup(kind, seed):
    """r = 1: JIPDA is JPDA. Same β and same PDA-updated states as Stone Soup's."""
    model, states, Z = _scene(kind, seed)
    p_detect, gate_prob, density = 0.75, 0.99, 2e-7 if kind == "position" else 3.0
    ours = scan_update(model, states, np.ones(len(states)), Z, p_detect, gate_prob, density)
    beta, xs, Ps = stonesoup_jpda(kind, model, states, Z, p_detect, gate_prob, density)
    assert np.count_nonzero(beta[:, 1:] > 1e-6) >= len(states) + 2  # the scene shares plots between tracks
    assert any(np.count_nonzero(b[1:] > 1e-3) >= 2 for b in beta)
    np.testing.assert_allclose(ours.beta, beta, rtol=0, atol=1e-9)
    for i in range(len(states)):
        np.testing.assert_allclose(ours.x[i], xs[i], rtol=1e-9, atol=1e-9 * np.abs(xs[i]).max())
        np.testing.assert_allclose(ours.P[i], Ps[i], rtol=0, atol=1e-9 * np.abs(Ps[i]).max())
    np.testing.assert_allclose(ours.r, 1.0, rtol=0, atol=1e-15)  # r = 1 stays 1


@pytest.mark.parametrize("kind", KINDS)
def test_joint_association_with_existence_matches_stonesoup(kind):
    """rᵢ < 1: JIPDA's β are Stone Soup's JPDA with P_D rᵢ per track."""
    model, states, Z = _scene(kind, 7)
    r = np.array([0.9, 0.3, 0.6])
    density = 2e-7 if kind == "position" else 3.0
    ours = scan_update(model, states, r, Z, 0.8, 0.995, density)
    beta, _, _ = stonesoup_jpda(kind, model, states, Z, 0.8, 0.995, density, r)
    assert any(np.count_nonzero(b[1:] > 1e-3) >= 2 for b in beta)
    np.testing.assert_allclose(ours.beta, beta, rtol=0, atol=1e-9)


def test_stonesoup_reference_sees_the_conversion():
    """The reference is not blind: a compass azimuth given to Stone Soup as its bearing
    unconverted changes the association."""
    model, states, Z = _scene("az_el_range", 0)
    good, _, _ = stonesoup_jpda("az_el_range", model, states, Z, 0.75, 0.99, 3.0)
    Zw = Z.copy()
    Zw[:, 0] = np.mod(Zw[:, 0] + 2.0 * DEG, 2.0 * math.pi)
    bad, _, _ = stonesoup_jpda("az_el_range", model, states, Zw, 0.75, 0.99, 3.0)
    assert np.abs(good - bad).max() > 0.05


# Exact sum -----------------------------------------------------------------------------------
def _events(w0, W):
    """Every joint event and its weight, listed (itertools.product, as Stone Soup's JPDA
    does): ``event[i]`` 0 for a miss, ``1 + j`` for plot j."""
    n = W.shape[0]
    options = [[0] + [1 + j for j in np.flatnonzero(W[i] > 0)] for i in range(n)]
    for event in itertools.product(*options):
        taken = [a for a in event if a]
        if len(taken) == len(set(taken)):
            yield event, np.prod([w0[i] if a == 0 else W[i, a - 1] for i, a in enumerate(event)])


def _marginals_of(events, shape):
    beta = np.zeros((shape[0], shape[1] + 1))
    for event, weight in events:
        for i, a in enumerate(event):
            beta[i, a] += weight
    return beta / beta.sum(axis=1, keepdims=True)


def _brute_force(w0, W):
    """β by listing every joint event."""
    return _marginals_of(_events(w0, W), W.shape)


def _best_permutation_brute_force(w0, W):
    """JPDA*'s β by listing every joint event, grouping them by (tracks detected, plots
    taken) and keeping the heaviest of each group (Blom and Bloem's pruning, read directly)."""
    best = {}
    for event, weight in _events(w0, W):
        key = (frozenset(i for i, a in enumerate(event) if a), frozenset(a for a in event if a))
        if weight > best.get(key, (None, -1.0))[1]:
            best[key] = (event, weight)
    return _marginals_of(best.values(), W.shape)


def _random_cluster(rng, n, m, density=0.5):
    W = rng.exponential(1.0, (n, m)) * (rng.random((n, m)) < density) * 10.0 ** rng.uniform(-2, 2, (n, 1))
    w0 = rng.uniform(0.05, 1.0, n)
    return w0, W


@pytest.mark.parametrize("seed", range(20))
def test_exact_marginals_equal_enumeration(seed):
    rng = np.random.default_rng(seed)
    w0, W = _random_cluster(rng, int(rng.integers(1, 6)), int(rng.integers(1, 7)), rng.uniform(0.3, 1.0))
    np.testing.assert_allclose(exact_marginals(w0, W), _brute_force(w0, W), rtol=1e-12, atol=1e-14)


@pytest.mark.parametrize("seed", range(20))
def test_best_permutation_marginals_equal_enumeration(seed):
    rng = np.random.default_rng(100 + seed)
    w0, W = _random_cluster(rng, int(rng.integers(1, 6)), int(rng.integers(1, 7)), rng.uniform(0.3, 1.0))
    np.testing.assert_allclose(best_permutation_marginals(w0, W), _best_permutation_brute_force(w0, W),
                               rtol=1e-12, atol=1e-14)
    if W.shape[0] == 1:  # one track has no permutation: JPDA's marginals
        np.testing.assert_allclose(best_permutation_marginals(w0, W), exact_marginals(w0, W), rtol=1e-12)


def test_jpda_star_keeps_two_close_tracks_apart():
    """Two tracks 500 m apart along x (σ 300 m, position plots of σ 300 m: gain ½), each
    aircraft's plot 50 m short of its track: the plots are 500 m apart as the tracks are.
    JPDA weights the crossed pairing too (β ≈ 0.1) and pulls the tracks together by
    ``½ β_cross · 1000`` m; JPDA* keeps only the likelier pairing, so both tracks move by
    ``½ β_own · (−50)`` and stay 500 m apart (all rᵢ = 1: JPDA and JPDA*). Clutter so
    sparse (ρ = 1e-14 m⁻³) that events with one track missed weigh < 1e-6: JPDA* prunes
    only among events that detect the same tracks, and those events are not pruned."""
    model = PositionModel(300.0, n_x=3)
    P = np.eye(3) * 300.0**2
    states = [(np.zeros(3), P), (np.array([500.0, 0.0, 0.0]), P)]
    Z = np.array([[-50.0, 0.0, 0.0], [450.0, 0.0, 0.0]])
    plain = scan_update(model, states, [1.0, 1.0], Z, 0.99, 0.999, density=1e-14)
    star = scan_update(model, states, [1.0, 1.0], Z, 0.99, 0.999, density=1e-14, jpda_star=True)
    assert plain.beta[0, 2] > 0.05 and plain.beta[1, 1] > 0.05
    assert star.beta[0, 2] < 1e-6 and star.beta[1, 1] < 1e-6  # the crossed pairing is pruned
    assert plain.x[1][0] - plain.x[0][0] == pytest.approx(500.0 - 500.0 * plain.beta[0, 2], abs=1e-3)
    assert star.x[1][0] - star.x[0][0] == pytest.approx(500.0, abs=1e-3)
    for i in range(2):
        assert star.x[i][0] == pytest.approx(states[i][0][0] - 25.0, abs=1e-3)


def test_lbp_error_against_exact():
    """Loopy belief propagation against the exact sum on 300 random clusters of 2–6 tracks
    and 2–8 plots (weights spread over four decades; docs/algorithms.md states the error
    on 1,000): small on the whole, and a fraction of the error of ignoring the other
    tracks (each track's own PDA). LBP is exact on a tree (tracks that share one plot)."""
    rng = np.random.default_rng(30)
    lbp, alone = [], []
    for _ in range(300):
        w0, W = _random_cluster(rng, int(rng.integers(2, 7)), int(rng.integers(2, 9)), rng.uniform(0.3, 0.9))
        exact = exact_marginals(w0, W)
        lbp.append(np.abs(lbp_marginals(w0, W) - exact).max())
        pda = np.concatenate([w0[:, None], W], axis=1)
        alone.append(np.abs(pda / pda.sum(axis=1, keepdims=True) - exact).max())
    lbp, alone = np.array(lbp), np.array(alone)
    assert np.mean(lbp) < 0.015 and np.median(lbp) < 0.005 and np.percentile(lbp, 95) < 0.06
    assert np.mean(lbp) < 0.1 * np.mean(alone)
    w0, W = np.array([0.3, 0.5]), np.array([[2.0, 0.7, 0.0], [0.0, 1.5, 0.4]])  # a tree
    np.testing.assert_allclose(lbp_marginals(w0, W), exact_marginals(w0, W), atol=1e-10)


def test_large_cluster_goes_to_lbp():
    rng = np.random.default_rng(4)
    w0, W = _random_cluster(rng, 8, 12, 1.0)  # 13⁸ events
    assert n_events_bound(W) > EXACT_EVENTS
    beta, exact = marginals(w0, W)
    assert not exact
    np.testing.assert_allclose(beta.sum(axis=1), 1.0)
    beta_small, exact_small = marginals(w0[:2], W[:2, :3])
    assert exact_small
    np.testing.assert_allclose(beta_small, _brute_force(w0[:2], W[:2, :3]), atol=1e-14)


# Clusters ------------------------------------------------------------------------------------
def test_clusters_are_connected_components():
    gated = [np.array([0, 1]), np.array([5]), np.array([1, 2]), np.array([], int), np.array([6, 5]), np.array([3])]
    got = [(t.tolist(), p.tolist()) for t, p in clusters(gated, 8)]
    assert got == [([0, 2], [0, 1, 2]), ([1, 4], [5, 6]), ([5], [3])]
    assert clusters([np.array([], int)] * 3, 4) == []


# Existence -----------------------------------------------------------------------------------
@pytest.mark.parametrize("kind", KINDS)
def test_one_track_existence_is_the_ipda_closed_form(kind):
    """One track: r⁺ = (1 − δ) r / (1 − δ r), δ = P_D P_G − P_D Σ Nⱼ/ρ, with Nⱼ from scipy;
    and the state is the mixture of the EKF updates with IPDA's weights given existence."""
    model, states, Z = _scene(kind, 3, n_tracks=1, n_clutter=4)
    x, P = states[0]
    p_detect, gate_prob, density, r = 0.7, 0.99, (1e-7 if kind == "position" else 2.0), 0.4
    out = scan_update(model, states, [r], Z, p_detect, gate_prob, density)
    H = model.jacobian(x)
    S = H @ P @ H.T + model.R
    nus = [kalman.innovation(z, model.h(x), model.angles) for z in Z]
    gate = chi2.ppf(gate_prob, model.n_z)
    inside = [k for k, nu in enumerate(nus) if nu @ np.linalg.solve(S, nu) <= gate]
    assert len(inside) >= 2
    ratios = [multivariate_normal(np.zeros(model.n_z), S).pdf(nus[k]) / density for k in inside]
    # (scipy's density of an S of condition ~1e10 (range m², angles rad²) agrees to ~1e-9)
    assert out.r[0] == pytest.approx(ipda_existence(r, ratios, p_detect, gate_prob), rel=1e-8)
    delta = p_detect * gate_prob - p_detect * sum(ratios)
    assert out.r[0] == pytest.approx((1 - delta) * r / (1 - delta * r), rel=1e-8)
    # given existence: miss ∝ 1 − P_D P_G, plot j ∝ P_D Nⱼ/ρ; the state their mixture
    w = np.array([1.0 - p_detect * gate_prob] + [p_detect * q for q in ratios])
    w /= w.sum()
    upd = [kalman.update(x, P, nus[k], H, model.R) for k in inside]
    xm, Pm = kalman.gaussian_mixture(w, np.array([x] + [u.x for u in upd]), np.array([P] + [u.P for u in upd]))
    np.testing.assert_allclose(out.x[0], xm, rtol=1e-10, atol=1e-8)
    np.testing.assert_allclose(out.P[0], Pm, rtol=1e-8, atol=1e-9 * np.abs(Pm).max())


def test_existence_without_plots_and_prediction():
    rule = ExistenceRule(p_survive=0.95)
    model = PositionModel(10.0)
    x = np.array([0.0, 0.0, 0.0, 1.0, 1.0, 1.0])
    P = np.eye(6) * 100.0
    out = scan_update(model, [(x, P)], [0.6], np.array([[1e5, 0.0, 0.0], [0.0, 1e5, 0.0]]), 0.9, 0.99, 1e-9)
    pdg = 0.9 * 0.99
    assert out.r[0] == pytest.approx((1 - pdg) * 0.6 / (1 - pdg * 0.6), rel=1e-14)
    np.testing.assert_array_equal(out.x[0], x)
    np.testing.assert_array_equal(out.P[0], P)
    assert rule.predict(0.8, 2.0) == pytest.approx(0.8 * 0.95**2)
    assert rule.predict(0.8, 0.0) == 0.8
    with pytest.raises(ValueError):
        ExistenceRule(existence_confirm=0.05, existence_delete=0.1)
    # existence given "unassigned": the miss weight among the state hypotheses
    r_post, c0 = existence_update(np.array([0.5]), np.array([0.2]), 0.9, 0.99)
    a = (1 - pdg) * 0.5 / (1 - pdg * 0.5)
    assert r_post[0] == pytest.approx(0.8 + 0.2 * a) and c0[0] == pytest.approx(0.2 * a / (0.8 + 0.2 * a))


def test_an_unlikely_track_keeps_weights_that_sum_to_one():
    """A track of existence 1e-9 with a plot far out in its gate: ``β₀`` is within
    rounding of 1, and ``r⁺ = 1 − β₀ + β₀ a`` would cancel; from ``Σⱼ βⱼ`` it does not, so
    the weights given existence sum to 1 as the PDA update requires (to 1e-12)."""
    model = PositionModel(10.0)
    x = np.zeros(6)
    P = np.eye(6) * 100.0
    out = scan_update(model, [(x, P)], [1e-9], np.array([[30.0, 20.0, 0.0]]), 0.9, 0.999, 1e-2)
    beta0, beta = out.beta[0, 0], out.beta[0, 1]
    assert 0.0 < beta < 1e-11
    pdg = 0.9 * 0.999
    a = (1 - pdg) * 1e-9 / (1 - pdg * 1e-9)
    assert out.r[0] == pytest.approx(beta + beta0 * a, rel=1e-12)
    r_post, c0 = existence_update(np.array([1e-9]), np.array([beta0]), 0.9, 0.999, np.array([beta]))
    assert c0[0] + beta / r_post[0] == pytest.approx(1.0, abs=1e-12)


def test_birth_existence_charges_the_birth_frames_misses():
    """A track started from the plots of some of its frame's sensors: its existence is
    ``existence_birth`` with each other sensor's miss, odds × ``(1 − P_D P_G)`` with that
    sensor's P_D; a group of every sensor keeps ``existence_birth``."""
    jipda = JIPDA(0.9, 0.999, p_detect_by_sensor={"radar2": 0.6})
    r = 0.1
    odds = r / (1 - r) * (1 - 0.9 * 0.999) * (1 - 0.6 * 0.999)
    assert jipda.born(r, ["angle2", "radar2"]) == pytest.approx(odds / (1 + odds), rel=1e-12)
    assert jipda.born(r, []) == r


# Properties ----------------------------------------------------------------------------------
@pytest.mark.parametrize("seed", range(8))
@pytest.mark.parametrize("exact_events", [math.inf, 0])  # every cluster exact, and every one by LBP
def test_properties(seed, exact_events):
    kind = KINDS[seed % 3]
    model, states, Z = _scene(kind, 100 + seed, n_tracks=5, n_clutter=8)
    r = np.random.default_rng(seed).uniform(0.05, 1.0, len(states))
    out = scan_update(model, states, r, Z, 0.75, 0.999, 1e-7 if kind == "position" else 1.0,
                      exact_events=exact_events)
    assert out.exact and all(e == (exact_events > 0) for e in out.exact)
    np.testing.assert_allclose(out.beta.sum(axis=1), 1.0, atol=1e-12)
    assert np.all(out.beta >= 0.0)
    assert np.all(out.plot_use <= 1.0 + (1e-12 if exact_events else 1e-6))
    assert np.all((out.r >= 0.0) & (out.r <= 1.0))
    for (x, P), P_new in zip(states, out.P):
        np.testing.assert_allclose(P_new, P_new.T, atol=0)
        assert np.linalg.eigvalsh(P_new).min() > 0.0


def test_pda_update_spread_term_is_positive():
    """P⁺ exceeds the miss/hit blend by K(Σcνν ᵀ − ν̄ν̄ᵀ)Kᵀ ⪰ 0, zero for one plot of weight 1."""
    model = PositionModel(10.0)
    x, P = np.zeros(6), np.eye(6) * 400.0
    H = model.jacobian(x)
    nu = np.array([[10.0, -5.0, 0.0], [-20.0, 5.0, 3.0]])
    x1, P1 = pda_update(x, P, H, model.R, nu, 0.2, np.array([0.5, 0.3]))
    res = kalman.update(x, P, np.zeros(3), H, model.R)
    assert np.linalg.eigvalsh(P1 - (0.2 * P + 0.8 * res.P)).min() > -1e-9
    assert np.linalg.eigvalsh(P1 - (0.2 * P + 0.8 * res.P)).max() > 1.0
    x2, P2 = pda_update(x, P, H, model.R, nu[:1], 0.0, np.array([1.0]))
    one = kalman.update(x, P, nu[0], H, model.R)
    np.testing.assert_allclose(x2, one.x)
    np.testing.assert_allclose(P2, one.P)


# Clutter density -----------------------------------------------------------------------------
def test_clutter_density_from_plots():
    """Plots uniform over a radar's cover (azimuth all round × range 0–80 km) and an angle
    sensor's (azimuth × elevation 0–60°): the estimate's mean within 3 % of λ/V over 200
    scans, and the expected target plots taken off the count."""
    rng = np.random.default_rng(8)
    for lam, spans, angles in [(200.0, [2 * math.pi, 80000.0], [True, False]),
                               (50.0, [2 * math.pi, math.pi / 3], [True, True])]:
        truth = lam / np.prod(spans)
        est = []
        for _ in range(200):
            Z = rng.random((rng.poisson(lam), 2)) * spans
            est.append(clutter_density(Z, np.array(angles), 0.0))
        assert np.mean(est) == pytest.approx(truth, rel=0.03)
    Z = rng.random((100, 2)) * [2 * math.pi, 80000.0]
    full = clutter_density(Z, np.array([True, False]), 0.0)
    assert clutter_density(Z, np.array([True, False]), 20.0) == pytest.approx(full * 80 / 100)
    # one plot spans nothing: the gate volume stands in
    assert clutter_density(Z[:1], np.array([True, False]), 0.5, min_volume=40.0) == pytest.approx(1 / 40.0)
    with pytest.raises(ValueError):
        clutter_density(Z[:1], np.array([True, False]), 0.5)


def test_clutter_window_over_sparse_scans():
    """Ten false alarms a scan among 20 target plots bunched in a corner of the cover: one
    scan's plots span little of it (ρ̂ far too high), the last ten scans' span most."""
    rng = np.random.default_rng(9)
    spans, angles = np.array([2 * math.pi, 80000.0]), np.array([True, False])
    truth = 10.0 / np.prod(spans)
    window = ClutterWindow(10)
    single, windowed = [], []
    for k in range(60):
        Z = np.vstack([rng.random((rng.poisson(10.0), 2)) * spans,
                       [1.0, 30000.0] + rng.random((20, 2)) * [0.5, 20000.0]])
        single.append(clutter_density(Z, angles, 20.0))
        rho = window.update(Z, angles, 20.0)
        if k >= 10:
            windowed.append(rho)
    assert np.mean(windowed) == pytest.approx(truth, rel=0.15)
    assert np.std(windowed) < 0.5 * np.std(single)
    assert abs(np.mean(single) / truth - 1.0) > 2 * abs(np.mean(windowed) / truth - 1.0)
    with pytest.raises(ValueError):
        ClutterWindow(0)


def test_estimated_density_is_used_when_none_given():
    model, states, Z = _scene("position", 0)
    hyps = [hypothesise(model, x, P, Z, 0.99) for x, P in states]
    r = np.array([0.5, 0.5, 0.5])
    rho = clutter_density(Z, model.angles, 0.75 * 0.99 * r.sum(), max(h.gate_volume for h in hyps))
    np.testing.assert_allclose(scan_update(model, states, r, Z, 0.75, 0.99).beta,
                               scan_update(model, states, r, Z, 0.75, 0.99, rho).beta, rtol=0, atol=0)
    assert scan_update(model, states, r, Z, 0.75, 0.99).density == rho


def test_gate_volume_is_the_ellipsoid():
    model = PositionModel(10.0)
    P = np.diag([100.0, 400.0, 900.0, 1, 1, 1])
    h = hypothesise(model, np.zeros(6), P, np.zeros((1, 3)), 0.99)
    S = P[:3, :3] + model.R
    G = chi2.ppf(0.99, 3)
    assert h.gate_volume == pytest.approx(4 / 3 * math.pi * G**1.5 * math.sqrt(np.linalg.det(S)), rel=1e-12)
