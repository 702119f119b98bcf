"""Track-to-track fusion rules against independent references: generalised least
squares on the stacked estimates, the closed-form Bar-Shalom–Campo formula, brute-force
covariance-intersection weights, a centralised (stacked) Kalman update, and Monte Carlo
cross-covariances of two linear Kalman filters."""

from __future__ import annotations

import numpy as np
import pytest

from fusion import kalman
from fusion.motion import ConstantAcceleration
from fusion.track_fusion import (
    TrackFuser,
    ci_weights,
    fuse_bar_shalom_campo,
    fuse_ci,
    fuse_info,
    fuse_naive,
)
from fusion.links import Gaussian, LocalReport
from fusion.types import Estimate


def _spd(rng, n, scale=1.0):
    A = rng.normal(size=(n, n))
    return scale * (A @ A.T + n * np.eye(n))


def _joint(rng, N, n):
    """A random joint covariance of N n-dim estimation errors, and its blocks."""
    S = _spd(rng, N * n)
    return S, [[S[i * n : (i + 1) * n, j * n : (j + 1) * n] for j in range(N)] for i in range(N)]


def _gls(xs, S):
    """BLUE of x from stacked estimates x_i = x + e_i, Cov(e) = S: (AᵀS⁻¹A)⁻¹AᵀS⁻¹z."""
    n = xs[0].size
    A = np.vstack([np.eye(n)] * len(xs))
    Si = np.linalg.inv(S)
    P = np.linalg.inv(A.T @ Si @ A)
    return P @ A.T @ Si @ np.concatenate(xs), P


def test_naive_is_gls_for_independent_estimates():
    rng = np.random.default_rng(1)
    for N in (2, 3, 4):
        Ps = [_spd(rng, 5) for _ in range(N)]
        xs = [rng.normal(size=5) * 10 for _ in range(N)]
        S = np.zeros((5 * N, 5 * N))
        for i, P in enumerate(Ps):
            S[i * 5 : (i + 1) * 5, i * 5 : (i + 1) * 5] = P
        x_ref, P_ref = _gls(xs, S)
        x, P = fuse_naive(xs, Ps)
        np.testing.assert_allclose(x, x_ref, rtol=1e-10)
        np.testing.assert_allclose(P, P_ref, rtol=1e-10)


def test_bar_shalom_campo_two_tracks_closed_form_and_gls():
    rng = np.random.default_rng(2)
    S, B = _joint(rng, 2, 6)
    xs = [rng.normal(size=6), rng.normal(size=6)]
    P1, P2, P12 = B[0][0], B[1][1], B[0][1]
    G = (P1 - P12) @ np.linalg.inv(P1 + P2 - P12 - P12.T)
    x_bsc = xs[0] + G @ (xs[1] - xs[0])
    P_bsc = P1 - G @ (P1 - P12.T)
    x, P, W = fuse_bar_shalom_campo(xs, [P1, P2], B)
    np.testing.assert_allclose(x, x_bsc, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(P, P_bsc, rtol=1e-10, atol=1e-12)
    x_ref, P_ref = _gls(xs, S)
    np.testing.assert_allclose(x, x_ref, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(P, P_ref, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(sum(W), np.eye(6), atol=1e-12)
    np.testing.assert_allclose(sum(Wi @ xi for Wi, xi in zip(W, xs)), x, atol=1e-12)


def test_bar_shalom_campo_n_tracks_is_gls():
    rng = np.random.default_rng(3)
    S, B = _joint(rng, 4, 5)
    xs = [rng.normal(size=5) for _ in range(4)]
    x, P, _ = fuse_bar_shalom_campo(xs, [B[i][i] for i in range(4)], B)
    x_ref, P_ref = _gls(xs, S)
    np.testing.assert_allclose(x, x_ref, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(P, P_ref, rtol=1e-9, atol=1e-12)


def test_bar_shalom_campo_with_zero_cross_covariance_is_naive():
    rng = np.random.default_rng(4)
    Ps = [_spd(rng, 4), _spd(rng, 4)]
    xs = [rng.normal(size=4), rng.normal(size=4)]
    Z = np.zeros((4, 4))
    x, P, _ = fuse_bar_shalom_campo(xs, Ps, [[None, Z], [Z, None]])
    xn, Pn = fuse_naive(xs, Ps)
    np.testing.assert_allclose(x, xn, rtol=1e-10)
    np.testing.assert_allclose(P, Pn, rtol=1e-10)


def test_fusing_a_track_with_itself():
    rng = np.random.default_rng(5)
    P, x = _spd(rng, 4), rng.normal(size=4)
    xb, Pb, _ = fuse_bar_shalom_campo([x, x], [P, P], [[P, P], [P, P]])
    np.testing.assert_allclose(xb, x, atol=1e-12)
    np.testing.assert_allclose(Pb, P, rtol=1e-12)
    xc, Pc, _ = fuse_ci([x, x], [P, P])
    np.testing.assert_allclose(Pc, P)
    _, Pn = fuse_naive([x, x], [P, P])
    np.testing.assert_allclose(Pn, P / 2, rtol=1e-12)  # the double counting the patent's rule does


@pytest.mark.parametrize("criterion", ["trace", "det"])
def test_ci_weight_is_the_minimiser(criterion):
    rng = np.random.default_rng(6)

    def f(M):  # the criterion, evaluated directly (vectorised over a stack of matrices)
        return np.trace(np.linalg.inv(M), axis1=-2, axis2=-1) if criterion == "trace" else -np.linalg.slogdet(M)[1]

    for _ in range(10):
        Ps = [_spd(rng, 6, 10 ** rng.uniform(-2, 2)), _spd(rng, 6)]
        Ys = [np.linalg.inv(P) for P in Ps]
        grid = np.linspace(0, 1, 20001)[:, None, None]
        best = f(grid * Ys[0] + (1 - grid) * Ys[1]).min()
        w = ci_weights(Ps, criterion)
        assert w.sum() == pytest.approx(1.0)
        assert f(w[0] * Ys[0] + w[1] * Ys[1]) <= best + 1e-9 * abs(best)
    # N = 3 against a simplex grid
    Ps = [_spd(rng, 4, s) for s in (1.0, 3.0, 0.3)]
    Ys = [np.linalg.inv(P) for P in Ps]
    a, b = np.meshgrid(np.linspace(0, 1, 301), np.linspace(0, 1, 301))
    keep = a + b <= 1
    a, b = a[keep][:, None, None], b[keep][:, None, None]
    best = f(a * Ys[0] + b * Ys[1] + (1 - a - b) * Ys[2]).min()
    w = ci_weights(Ps, criterion)
    assert f(sum(wi * Y for wi, Y in zip(w, Ys))) <= best + 1e-6 * abs(best)


def test_ci_is_consistent_for_any_correlation():
    rng = np.random.default_rng(7)
    for _ in range(50):
        N = int(rng.integers(2, 4))
        _, B = _joint(rng, N, 4)
        Ps = [B[i][i] for i in range(N)]
        xs = [np.zeros(4)] * N
        _, Pf, w = fuse_ci(xs, Ps, "trace")
        Wt = [Pf @ (wi * np.linalg.inv(P)) for wi, P in zip(w, Ps)]  # x_f = Σ W_i x_i
        true = sum(Wt[i] @ B[i][j] @ Wt[j].T for i in range(N) for j in range(N))
        assert np.linalg.eigvalsh(Pf - true).min() >= -1e-9 * np.abs(Pf).max()


def test_info_with_shared_prior_equals_the_stacked_update():
    rng = np.random.default_rng(8)
    n = 6
    xb, Pb = rng.normal(size=n) * 100, _spd(rng, n, 50.0)
    Hs = [rng.normal(size=(2, n)), rng.normal(size=(3, n)), rng.normal(size=(1, n))]
    Rs = [_spd(rng, H.shape[0]) for H in Hs]
    zs = [rng.normal(size=H.shape[0]) * 10 for H in Hs]
    loc = [kalman.update(xb, Pb, z - H @ xb, H, R) for z, H, R in zip(zs, Hs, Rs)]
    H = np.vstack(Hs)
    R = np.zeros((H.shape[0],) * 2)
    i = 0
    for Ri in Rs:
        R[i : i + len(Ri), i : i + len(Ri)] = Ri
        i += len(Ri)
    central = kalman.update(xb, Pb, np.concatenate(zs) - H @ xb, H, R)
    x, P = fuse_info([r.x for r in loc], [r.P for r in loc], [xb] * 3, [Pb] * 3, xb, Pb)
    np.testing.assert_allclose(x, central.x, rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(P, central.P, rtol=1e-9, atol=1e-12 * np.abs(P).max())
    # Naive fusion counts the shared prior three times: overconfident.
    _, Pn = fuse_naive([r.x for r in loc], [r.P for r in loc])
    assert np.linalg.eigvalsh(central.P - Pn).min() > 0


def test_fusion_rejects_bad_input():
    with pytest.raises(ValueError, match="one or more"):
        fuse_naive([], [])
    with pytest.raises(ValueError, match="positive definite"):
        fuse_naive([np.zeros(2)] * 2, [np.eye(2), -np.eye(2)])
    with pytest.raises(ValueError, match="criterion"):
        ci_weights([np.eye(2)] * 2, "volume")
    with pytest.raises(ValueError, match="fusion rule"):
        TrackFuser("average", ConstantAcceleration(1.0))


# The fuser's cross-covariance bookkeeping ------------------------------------------------
def _two_linear_trackers(feedback: bool, steps=8, samples=20_000, seed=9):
    """Two linear KFs (position-only measurements, different accuracy) tracking one CA
    truth from a shared initial estimate, run on `samples` Monte Carlo realisations at
    once (gains do not depend on the data). Returns the TrackFuser's BSC result for the
    last step and the Monte Carlo errors of the two local tracks at that step."""
    rng = np.random.default_rng(seed)
    motion = ConstantAcceleration(2.0)
    F, Q = motion.F(1.0), motion.Q(1.0)
    H = np.hstack([np.eye(3), np.zeros((3, 6))])
    Rs = [np.diag([25.0, 25.0, 400.0]), np.diag([900.0, 100.0, 25.0])]
    P0 = np.diag([100.0] * 3 + [25.0] * 3 + [1.0] * 3)
    truth = rng.multivariate_normal(np.zeros(9), P0, samples)
    est = [np.zeros((samples, 9)), np.zeros((samples, 9))]
    Ps = [P0, P0]
    fuser = TrackFuser("bar-shalom-campo", motion)
    fuser.initialise(np.zeros(9), P0, 0.0)
    fb_t = [0.0, 0.0]
    Lq = np.linalg.cholesky(Q)
    for k in range(1, steps + 1):
        truth = truth @ F.T + rng.standard_normal((samples, 9)) @ Lq.T
        reports = []
        for i in range(2):
            xp, Pp = est[i] @ F.T, F @ Ps[i] @ F.T + Q
            z = truth @ H.T + rng.standard_normal((samples, 3)) @ np.sqrt(Rs[i])
            res = kalman.update(np.zeros(9), Pp, np.zeros(3), H, Rs[i])
            est[i] = xp + (z - xp @ H.T) @ res.K.T
            Ps[i] = res.P
            reports.append(LocalReport(float(k), f"n{i}", k, Estimate(float(k), np.zeros(9), res.P, "HNV", f"n{i}"),
                                       Gaussian(np.zeros(9), Pp), res.K @ H, fb_t[i]))
            fb_t[i] = None
        fused = fuser.fuse(float(k), reports)
        if feedback and k < steps:
            # Every local restarts from the fused estimate: x_f = Σ W_i x_i with the fuser's weights,
            # which for BSC we recover from the closed form applied to the exact joint covariance.
            C12 = fuser._cross[("n0", "n1")]
            # (D is singular after feedback: the tracks differ only in the span of their gains.)
            G = (Ps[0] - C12) @ np.linalg.pinv(Ps[0] + Ps[1] - C12 - C12.T, rcond=1e-9, hermitian=True)
            xf = est[0] + (est[1] - est[0]) @ G.T
            est = [xf.copy(), xf.copy()]
            Ps = [fused.P, fused.P]
            fb_t = [float(k), float(k)]
    return fuser, fused, [est[i] - truth for i in range(2)]


@pytest.mark.parametrize("feedback", [False, True])
def test_bsc_cross_covariance_recursion_matches_monte_carlo(feedback):
    fuser, fused, e = _two_linear_trackers(feedback)
    C_mc = (e[0].T @ e[1]) / len(e[0])
    C = fuser._cross[("n0", "n1")]
    sd0, sd1 = np.sqrt(np.diag(fuser._P_nodes["n0"])), np.sqrt(np.diag(fuser._P_nodes["n1"]))
    # Monte Carlo error of a correlation-scaled cross-covariance entry ~ 1/√N.
    assert np.abs((C - C_mc) / np.outer(sd0, sd1)).max() < 5 / np.sqrt(len(e[0]))
    # And the fused covariance is that of the fused error (not just a formula).
    C12 = C
    D = fuser._P_nodes["n0"] + fuser._P_nodes["n1"] - C12 - C12.T
    G = (fuser._P_nodes["n0"] - C12) @ np.linalg.pinv(D, rcond=1e-9, hermitian=True)
    ef = e[0] + (e[1] - e[0]) @ G.T
    sdf = np.sqrt(np.diag(fused.P))
    assert np.abs((np.cov(ef.T) - fused.P) / np.outer(sdf, sdf)).max() < 5 / np.sqrt(len(ef))


def test_fuser_refuses_reports_it_cannot_fuse():
    """A report at another time than the fusion's, two of one node, and (bar-shalom-campo)
    one from a node whose track did not start from the fuser's estimate."""
    m = ConstantAcceleration(1.0)

    def report(node, t=1.0, feedback_t=None):
        return LocalReport(t, node, 1, Estimate(t, np.zeros(9), np.eye(9), "HNV", node), Gaussian(np.zeros(9), np.eye(9)),
                           np.zeros((9, 9)), feedback_t)

    f = TrackFuser("naive", m)
    f.initialise(np.zeros(9), np.eye(9), 0.0)
    with pytest.raises(ValueError, match="t=1.0"):
        f.fuse(2.0, [report("a")])
    with pytest.raises(ValueError, match="two tracks from one node"):
        f.fuse(1.0, [report("a"), report("a")])
    f = TrackFuser("bar-shalom-campo", m)
    f.initialise(np.zeros(9), np.eye(9), 0.0)
    with pytest.raises(ValueError, match="no cross-covariance for node 'a'"):
        f.fuse(1.0, [report("a")])
    f.fuse(1.0, [report("a", feedback_t=0.0)])  # restarted from the fuser's estimate at 0: known
