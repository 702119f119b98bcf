r"""Accuracy and consistency metrics.

* :func:`rmse` — root-mean-square of the Euclidean error.
* :func:`nees` / :func:`nis` — ``eᵀP⁻¹e`` / ``νᵀS⁻¹ν``; :func:`chi2_bounds` — the
  two-sided acceptance interval for their average over N Monte Carlo runs:
  ``N·ANEES ~ χ²(N·d)``, so ``[χ²⁻¹(α/2; Nd)/N, χ²⁻¹(1−α/2; Nd)/N]``.
* :func:`error_ellipse` — semi-axes and orientation of a 2×2 covariance's
  probability-``p`` ellipse.
* CEP50 — three different things, named apart:

  - :func:`cep50` — the textbook CEP of a Gaussian with covariance ``P``: the radius
    ``r`` with ``P(‖e‖ ≤ r) = 0.5``, computed *exactly* (numerical integration of the
    2-D Gaussian over the disc plus a root find), not with the ``0.59(σ₁+σ₂)`` rule
    of thumb (:func:`cep50_approx`: within ~2.5 % for axis ratios σ₂/σ₁ ≥ 0.3, but
    −5 % at 0.1 and −12.5 % as the ellipse degenerates to a line).
  - :func:`empirical_cep50` — the median miss distance of a set of fixes (the
    empirical counterpart of :func:`cep50`).
  - :func:`median_point_distance` — **the thesis's "CEP 50 %" statistic**: the
    distance from truth to the *coordinate-wise median point* of the fixes. It is a
    bias measure, not a radius containing half the fixes, and is usually far smaller
    than the CEP.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from scipy.optimize import brentq
from scipy.stats import chi2, norm


def rmse(err, axis=None):
    """``√mean(‖e‖²)`` over ``axis`` of errors shaped ``(..., d)`` (last axis = components)."""
    err = np.asarray(err, dtype=float)
    return np.sqrt(np.mean(np.sum(err * err, axis=-1), axis=axis))


def nees(err, P):
    """``eᵀP⁻¹e`` for errors ``(..., d)`` and covariances ``(..., d, d)`` (broadcasts)."""
    err = np.asarray(err, dtype=float)
    P = np.asarray(P, dtype=float)
    sol = np.linalg.solve(P, err[..., None])[..., 0]
    return np.sum(err * sol, axis=-1)


def nis(nu, S):
    """``νᵀS⁻¹ν`` (the same quadratic form as :func:`nees`, on innovations)."""
    return nees(nu, S)


def chi2_bounds(dof: int, n_runs: int, prob: float = 0.95) -> tuple[float, float]:
    """Two-sided ``prob`` interval for the average of ``n_runs`` NEES/NIS of ``dof`` each."""
    if dof < 1 or n_runs < 1 or not 0.0 < prob < 1.0:
        raise ValueError(f"chi2_bounds: need dof >= 1, n_runs >= 1, 0 < prob < 1 (got {dof}, {n_runs}, {prob})")
    a = 0.5 * (1.0 - prob)
    nd = dof * n_runs
    return float(chi2.ppf(a, nd) / n_runs), float(chi2.ppf(1.0 - a, nd) / n_runs)


class Ellipse(NamedTuple):
    """Semi-major/minor axes (m) and the major axis's math angle (ccw from east,
    radians, in (−π/2, π/2])."""

    a: float
    b: float
    angle: float


def _cov2(P) -> np.ndarray:
    P = np.asarray(P, dtype=float)
    if P.shape != (2, 2) or not np.all(np.isfinite(P)):
        raise ValueError(f"expected a finite 2×2 covariance, got shape {P.shape}")
    if abs(P[0, 1] - P[1, 0]) > 1e-9 * max(1.0, abs(P).max()):
        raise ValueError("covariance is not symmetric")
    P = 0.5 * (P + P.T)
    if np.linalg.eigvalsh(P)[0] < 0:
        raise ValueError("covariance is not positive semi-definite")
    return P


def error_ellipse(P, prob: float = 0.95) -> Ellipse:
    """The ellipse ``eᵀP⁻¹e = χ²⁻¹(prob; 2)`` containing a Gaussian error with probability ``prob``."""
    P = _cov2(P)
    if not 0.0 < prob < 1.0:
        raise ValueError(f"error_ellipse: prob must be in (0, 1), got {prob}")
    w, V = np.linalg.eigh(P)
    k = np.sqrt(chi2.ppf(prob, 2))
    ang = float(np.arctan2(V[1, 1], V[0, 1]))
    if ang <= -np.pi / 2:
        ang += np.pi
    elif ang > np.pi / 2:
        ang -= np.pi
    return Ellipse(float(k * np.sqrt(w[1])), float(k * np.sqrt(max(w[0], 0.0))), ang)


def _disc_probability(r: float, s1: float, s2: float, n: int = 512) -> float:
    # P(‖e‖ ≤ r) for e ~ N(0, diag(s1², s2²)): in polar coordinates the radial integral
    # is closed-form, leaving a smooth periodic integrand in θ, for which the
    # trapezoidal rule converges geometrically.
    th = (np.arange(n) + 0.5) * (2.0 * np.pi / n)
    a = np.cos(th) ** 2 / s1 ** 2 + np.sin(th) ** 2 / s2 ** 2
    return float(np.mean((1.0 - np.exp(-0.5 * r * r * a)) / a) / (s1 * s2))


def cep(P, prob: float = 0.5) -> float:
    """Exact radius of the circle about the mean holding probability ``prob`` of
    ``N(0, P)`` (2×2). A degenerate axis (σ = 0) is handled as a 1-D normal."""
    P = _cov2(P)
    if not 0.0 < prob < 1.0:
        raise ValueError(f"cep: prob must be in (0, 1), got {prob}")
    w = np.linalg.eigvalsh(P)
    s1, s2 = np.sqrt(max(w[1], 0.0)), np.sqrt(max(w[0], 0.0))
    if s1 == 0.0:
        return 0.0
    if s2 <= 1e-4 * s1:  # a line: the minor axis changes r by O((s2/s1)²) < 1e-8
        return float(s1 * norm.ppf(0.5 + 0.5 * prob))
    n = int(min(2 ** 20, max(512, 64 * s1 / s2)))  # resolve the integrand's peak, width ~ s2/s1
    k = np.sqrt(chi2.ppf(prob, 2))
    # isotropic laws of std s2 and s1 bracket the radius
    return float(brentq(lambda r: _disc_probability(r, s1, s2, n) - prob, 0.9999 * s2 * k, 1.0001 * s1 * k,
                        xtol=1e-12 * s1, rtol=1e-13))


def cep50(P) -> float:
    """Textbook CEP50 of ``N(0, P)``, exact (see :func:`cep`)."""
    return cep(P, 0.5)


def cep50_approx(P) -> float:
    """The rule of thumb ``0.59(σ₁+σ₂)`` (principal std devs); for comparison only."""
    w = np.linalg.eigvalsh(_cov2(P))
    return float(0.59 * (np.sqrt(max(w[1], 0)) + np.sqrt(max(w[0], 0))))


def empirical_cep50(fixes, truth) -> float:
    """Median distance of the fixes ``(n, 2)`` from ``truth``: the empirical CEP50 radius."""
    d = np.asarray(fixes, dtype=float)[..., :2] - np.asarray(truth, dtype=float)[:2]
    return float(np.median(np.hypot(d[..., 0], d[..., 1])))


def median_point_distance(fixes, truth) -> float:
    """The thesis's "CEP 50 %" (seed 000): distance from truth to the coordinate-wise
    median of the fixes. A bias measure — NOT the CEP radius (see module docstring)."""
    med = np.median(np.asarray(fixes, dtype=float)[..., :2].reshape(-1, 2), axis=0)
    return float(np.hypot(*(med - np.asarray(truth, dtype=float)[:2])))
