"""Accuracy and consistency metrics."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import chi2

from fusion.kalman import predict, update
from fusion.metrics import (
    cep,
    cep50,
    cep50_approx,
    chi2_bounds,
    empirical_cep50,
    error_ellipse,
    median_point_distance,
    nees,
    nis,
    rmse,
)

P_CORR = np.array([[900.0, -420.0], [-420.0, 400.0]])


def test_rmse_and_nees_by_hand():
    e = np.array([[3.0, 4.0], [0.0, 0.0]])
    assert rmse(e) == pytest.approx(np.sqrt(12.5))
    assert nees(np.array([2.0, 0.0]), np.diag([4.0, 1.0])) == pytest.approx(1.0)
    assert nis(np.array([1.0]), np.array([[4.0]])) == pytest.approx(0.25)


def test_chi2_bounds_cover_the_average_of_n_chi2_draws():
    lo, hi = chi2_bounds(2, 50, 0.95)
    assert (lo, hi) == pytest.approx((chi2.ppf(0.025, 100) / 50, chi2.ppf(0.975, 100) / 50))
    draws = np.random.default_rng(3).chisquare(2, size=(40_000, 50)).mean(axis=1)
    assert np.mean((draws >= lo) & (draws <= hi)) == pytest.approx(0.95, abs=0.005)


def _linear_kf_nees(scale: float, runs=100, steps=30, seed=5):
    """Constant-velocity KF on linear-Gaussian position measurements, all runs at once
    (the gain sequence is data independent, so one covariance recursion serves all)."""
    rng = np.random.default_rng(seed)
    F = np.array([[1.0, 1.0], [0.0, 1.0]])
    Q = 0.05 * np.array([[1 / 3, 1 / 2], [1 / 2, 1.0]])
    H, R = np.array([[1.0, 0.0]]), np.array([[4.0]])
    P0 = np.diag([25.0, 4.0])
    truth = rng.multivariate_normal([0.0, 1.0], P0, size=runs)
    x = np.tile([0.0, 1.0], (runs, 1))
    P = P0
    for _ in range(steps):
        truth = truth @ F.T + rng.multivariate_normal([0, 0], Q, size=runs)
        z = truth @ H.T + 2.0 * rng.standard_normal((runs, 1))
        xp, P = predict(x[0], P, F, Q)
        res = update(xp, P, (z[0] - H @ xp), H, R)   # the gain, from the shared kalman step
        x = x @ F.T
        x = x + (z - x @ H.T) @ res.K.T
        P = res.P
    return np.mean(nees(truth - x, np.broadcast_to(scale * P, (runs, 2, 2))))


def test_nees_of_a_linear_kf_averages_to_the_state_dimension():
    lo, hi = chi2_bounds(2, 100)
    assert lo <= _linear_kf_nees(1.0) <= hi
    assert not lo <= _linear_kf_nees(0.5) <= hi   # an over-confident covariance is caught


def test_cep50_matches_the_median_radius_of_samples():
    rng = np.random.default_rng(7)
    for P in (P_CORR, np.diag([100.0, 1.0]), np.eye(2) * 9.0):
        s = rng.multivariate_normal([0.0, 0.0], P, size=200_000)
        assert cep50(P) == pytest.approx(np.median(np.hypot(*s.T)), rel=0.01)
        assert empirical_cep50(s + [5.0, -2.0], [5.0, -2.0]) == pytest.approx(cep50(P), rel=0.01)


def test_cep_closed_forms():
    assert cep50(np.eye(2) * 4.0) == pytest.approx(2.0 * np.sqrt(2 * np.log(2)), rel=1e-10)  # Rayleigh
    assert cep(np.eye(2), 0.9) == pytest.approx(np.sqrt(-2 * np.log(0.1)), rel=1e-10)
    assert cep50(np.diag([9.0, 0.0])) == pytest.approx(3.0 * 0.6744897501960817, rel=1e-10)  # a line
    assert cep50(np.diag([9.0, 1e-6])) == pytest.approx(3.0 * 0.6744897501960817, rel=1e-6)
    # the rule of thumb is labelled as such: good when circular, 12 % off for a line
    assert cep50_approx(np.eye(2)) == pytest.approx(cep50(np.eye(2)), rel=0.01)
    assert cep50_approx(np.diag([1.0, 1e-8])) < 0.9 * cep50(np.diag([1.0, 1e-8]))


def test_error_ellipse_axes_orientation_and_coverage():
    th = np.radians(30.0)
    Rm = np.array([[np.cos(th), -np.sin(th)], [np.sin(th), np.cos(th)]])
    P = Rm @ np.diag([16.0, 1.0]) @ Rm.T
    el = error_ellipse(P, 0.95)
    k = np.sqrt(chi2.ppf(0.95, 2))
    assert (el.a, el.b) == pytest.approx((4 * k, 1 * k))
    assert el.angle == pytest.approx(th)
    s = np.random.default_rng(2).multivariate_normal([0, 0], P, size=100_000)
    u = s @ Rm  # into the ellipse's axes
    inside = (u[:, 0] / el.a) ** 2 + (u[:, 1] / el.b) ** 2 <= 1
    assert inside.mean() == pytest.approx(0.95, abs=0.004)
    with pytest.raises(ValueError, match="symmetric"):
        error_ellipse(np.array([[1.0, 0.5], [0.0, 1.0]]))


def test_thesis_median_point_is_not_the_cep():
    fixes = np.array([[1.0, 0.0], [0.0, 2.0], [3.0, 3.0]])
    assert empirical_cep50(fixes, [0, 0]) == pytest.approx(2.0)               # distances 1, 2, 4.24
    assert median_point_distance(fixes, [0, 0]) == pytest.approx(np.sqrt(5))  # median point (1, 2)
    ring = np.array([[10.0, 0.0], [-10.0, 0.0], [0.0, 10.0], [0.0, -10.0], [0.0, 0.0]])
    assert median_point_distance(ring, [0, 0]) == 0.0 and empirical_cep50(ring, [0, 0]) == 10.0
