"""Two-bearing fix (ipu), Torrieri, Stansfield, perpendicular LS, leave-one-out."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import least_squares

from fusion.angles import wrap_pi
from fusion.df.models import bearing, bearing_jacobian
from fusion.df.triangulation import (
    GeometryError,
    intersect_bearings,
    intersection_jacobian,
    ipu,
    leave_one_out,
    pairwise_intersection_mean,
    perpendicular_ls,
    stansfield,
    studentised_residuals,
    torrieri,
)

EMITTER = np.array([15e3, 15e3])
C1 = np.array([[0.0, 0.0], [20e3, 0.0]])
SIGMA = 0.0175

# (site1, site2, emitter): the thesis geometry, stations north of the emitter, a station
# on the emitter's x coordinate, and a pair whose bearings straddle north.
GEOMETRIES = [
    (C1[0], C1[1], EMITTER),
    (np.array([0.0, 30e3]), np.array([20e3, 30e3]), EMITTER),
    (np.array([15e3, 0.0]), np.array([0.0, 0.0]), EMITTER),
    (np.array([-5e3, 0.0]), np.array([5e3, 0.0]), np.array([0.0, 20e3])),
]


@pytest.mark.parametrize("s1,s2,p", GEOMETRIES)
def test_intersection_recovers_the_emitter_and_its_jacobian_matches_finite_differences(s1, s2, p):
    b1, b2 = bearing(p, s1), bearing(p, s2)
    np.testing.assert_allclose(intersect_bearings(s1, b1, s2, b2), p, atol=1e-6)
    F = intersection_jacobian(s1, b1, s2, b2)
    h = 1e-6
    fd = np.column_stack([
        (intersect_bearings(s1, b1 + h, s2, b2) - intersect_bearings(s1, b1 - h, s2, b2)) / (2 * h),
        (intersect_bearings(s1, b1, s2, b2 + h) - intersect_bearings(s1, b1, s2, b2 - h)) / (2 * h),
    ])
    np.testing.assert_allclose(F, fd, rtol=1e-6, atol=1e-3)


def test_ipu_covariance_matches_monte_carlo_scatter_of_the_fix():
    rng = np.random.default_rng(11)
    b1, b2 = bearing(EMITTER, C1[0]), bearing(EMITTER, C1[1])
    _, P = ipu(C1[0], b1, SIGMA, C1[1], b2, SIGMA)
    n = 200_000
    fixes = intersect_bearings(C1[0], b1 + SIGMA * rng.standard_normal(n), C1[1], b2 + SIGMA * rng.standard_normal(n))
    C = np.cov(fixes.T)
    # whitened by the predicted covariance the scatter must be the identity: this checks
    # variances and the correlation alike, independent of scale
    L = np.linalg.cholesky(P)
    W = np.linalg.solve(L, np.linalg.solve(L, C).T)
    assert np.max(np.abs(W - np.eye(2))) < 0.05, W
    np.testing.assert_allclose(np.diag(C), np.diag(P), rtol=0.05)


def test_ipu_diagonal_option_keeps_only_the_diagonal():
    s1, s2 = np.array([0.0, 0.0]), np.array([10e3, 0.0])
    b1, b2 = bearing(EMITTER, s1), bearing(EMITTER, s2)
    _, P = ipu(s1, b1, SIGMA, s2, b2, SIGMA)
    _, Pd = ipu(s1, b1, SIGMA, s2, b2, SIGMA, diagonal=True)
    assert abs(P[0, 1]) > 0.1 * np.sqrt(P[0, 0] * P[1, 1])  # the thesis geometry is correlated
    np.testing.assert_array_equal(Pd, np.diag(np.diag(P)))


def test_parallel_and_diverging_bearings_are_clear_errors():
    with pytest.raises(GeometryError, match="parallel"):
        ipu(C1[0], 0.3, SIGMA, C1[1], 0.3, SIGMA)
    with pytest.raises(ValueError, match="diverge"):  # rays meet behind the sites
        intersect_bearings(C1[0], np.pi / 2 + 0.1, C1[1], np.pi / 2 - 0.1)


def _scatter_geometry(rng, n=6):
    sites = rng.uniform(-30e3, 30e3, size=(n, 2))
    sig = rng.uniform(0.005, 0.03, size=n)
    betas = bearing(EMITTER, sites) + sig * rng.standard_normal(n)
    return sites, betas, sig


def test_torrieri_iterated_equals_general_nonlinear_least_squares():
    rng = np.random.default_rng(5)
    for _ in range(5):
        sites, betas, sig = _scatter_geometry(rng)
        fix = torrieri(sites, betas, sig)
        assert fix.converged
        ref = least_squares(lambda x: wrap_pi(betas - bearing(x, sites)) / sig, x0=EMITTER,
                            method="lm", xtol=1e-15, ftol=1e-15, gtol=1e-15)
        # relative agreement, i.e. 1e-8 × ~20 km = 0.2 mm
        assert np.linalg.norm(fix.x - ref.x) <= 1e-8 * np.linalg.norm(ref.x)
        J = ref.jac
        np.testing.assert_allclose(fix.P, np.linalg.inv(J.T @ J), rtol=1e-5)


def test_torrieri_rows_are_the_bearing_gradient_by_finite_differences():
    rng = np.random.default_rng(2)
    sites, _, _ = _scatter_geometry(rng)
    x = EMITTER + 100.0
    G = bearing_jacobian(x, sites)
    h = 1e-3
    fd = np.column_stack([(bearing(x + d, sites) - bearing(x - d, sites)) / (2 * h) for d in np.eye(2) * h])
    np.testing.assert_allclose(G, fd, rtol=1e-6)


def test_torrieri_one_step_is_the_thesis_closed_form():
    # document 002 eqs (2.22)-(2.26), written out independently of the matrix code
    rng = np.random.default_rng(9)
    sites, betas, sig = _scatter_geometry(rng, 4)
    x0 = EMITTER + np.array([300.0, -200.0])
    d = x0 - sites
    D = np.hypot(d[:, 0], d[:, 1])
    phi0 = np.arctan2(d[:, 1], d[:, 0])
    c, s = np.cos(phi0), np.sin(phi0)
    w = 1.0 / (D ** 2 * sig ** 2)
    mu, lam, nu = np.sum(c * c * w), np.sum(s * s * w), np.sum(s * c * w)
    r = wrap_pi(betas - phi0)
    xe = x0[0] + np.sum(r * (nu * c - mu * s) / (D * sig ** 2)) / (mu * lam - nu ** 2)
    ye = x0[1] + np.sum(r * (lam * c - nu * s) / (D * sig ** 2)) / (mu * lam - nu ** 2)
    fix = torrieri(sites, betas, sig, x0=x0, iterations=1)
    np.testing.assert_allclose(fix.x, [xe, ye], rtol=1e-12)


def test_stansfield_and_perpendicular_ls_solve_their_linear_problems():
    rng = np.random.default_rng(4)
    sites, betas, sig = _scatter_geometry(rng)
    a = np.column_stack([-np.sin(betas), np.cos(betas)])
    b = np.sum(a * sites, axis=1)
    x0 = EMITTER + 500.0
    w = 1.0 / (np.sum((x0 - sites) ** 2, axis=1) * sig ** 2)
    ref_st = np.linalg.lstsq(a * np.sqrt(w)[:, None], b * np.sqrt(w), rcond=None)[0]
    np.testing.assert_allclose(stansfield(sites, betas, sig, x0=x0, iterations=1).x, ref_st, rtol=1e-10)
    ref_pl = np.linalg.lstsq(a, b, rcond=None)[0]
    np.testing.assert_allclose(perpendicular_ls(sites, betas, sig).x, ref_pl, rtol=1e-10)
    # Stansfield iterated to convergence is a fixed point of its own weighting
    st = stansfield(sites, betas, sig, iterations=0)
    w = 1.0 / (np.sum((st.x - sites) ** 2, axis=1) * sig ** 2)
    np.testing.assert_allclose(np.linalg.lstsq(a * np.sqrt(w)[:, None], b * np.sqrt(w), rcond=None)[0], st.x, rtol=1e-9)


def test_line_fixes_have_the_monte_carlo_covariance_they_claim():
    # perpendicular LS is linear in the lines, so a vectorised Monte Carlo is cheap
    rng = np.random.default_rng(8)
    sites = np.array([[0.0, 0.0], [10e3, 0.0], [20e3, 0.0], [30e3, 5e3]])
    beta0 = bearing(EMITTER, sites)
    n = 100_000
    betas = beta0 + SIGMA * rng.standard_normal((n, len(sites)))
    a = np.stack([-np.sin(betas), np.cos(betas)], axis=-1)
    b = np.sum(a * sites, axis=-1)
    x = np.linalg.solve(np.einsum("nki,nkj->nij", a, a), np.einsum("nki,nk->ni", a, b)[..., None])[..., 0]
    P = perpendicular_ls(sites, beta0, SIGMA).P
    np.testing.assert_allclose(np.diag(np.cov(x.T)), np.diag(P), rtol=0.05)


def test_pairwise_mean_is_the_average_of_the_pair_intersections():
    rng = np.random.default_rng(3)
    sites = C1.tolist() + [[10e3, 0.0]]
    sites = np.array(sites)
    betas = bearing(EMITTER, sites) + SIGMA * rng.standard_normal(3)
    pts = [intersect_bearings(sites[i], betas[i], sites[j], betas[j]) for i, j in [(0, 1), (0, 2), (1, 2)]]
    np.testing.assert_allclose(pairwise_intersection_mean(sites, betas), np.mean(pts, axis=0), rtol=1e-12)


def test_studentised_residual_matches_an_explicit_leave_one_out_refit():
    rng = np.random.default_rng(6)
    sites, betas, sig = _scatter_geometry(rng, 8)
    fix = torrieri(sites, betas, sig)
    t = studentised_residuals(fix.x, fix.P, sites, betas, sig)
    for i in range(len(betas)):
        keep = np.arange(len(betas)) != i
        f_i = torrieri(sites[keep], betas[keep], sig[keep])
        r_del = wrap_pi(betas[i] - bearing(f_i.x, sites[i]))
        g = bearing_jacobian(f_i.x, sites[i])
        s_del = np.sqrt(sig[i] ** 2 + g @ f_i.P @ g)
        assert t[i] == pytest.approx(r_del / s_del, rel=2e-2, abs=1e-3)


def test_leave_one_out_drops_the_outlier_and_only_it():
    rng = np.random.default_rng(12)
    sites = np.array([[0.0, 0.0], [10e3, 0.0], [20e3, 0.0], [30e3, 0.0], [0.0, 30e3], [30e3, 30e3]])
    betas = bearing(EMITTER, sites) + SIGMA * rng.standard_normal(len(sites))
    betas[2] += 0.3  # a jammed bearing, ~17σ
    plain = torrieri(sites, betas, SIGMA)
    gated = leave_one_out(sites, betas, np.full(len(sites), SIGMA), gate=4.0)
    assert gated.used.tolist() == [True, True, False, True, True, True]
    assert np.linalg.norm(gated.x - EMITTER) < 0.25 * np.linalg.norm(plain.x - EMITTER)
    off = leave_one_out(sites, betas, np.full(len(sites), SIGMA), gate=0.0)
    assert off.used.all()
    np.testing.assert_allclose(off.x, plain.x)
