r"""Accuracy and consistency metrics.

* :func:`rmse`; :func:`nees` / :func:`nis` (``eᵀP⁻¹e`` / ``νᵀS⁻¹ν``); :func:`chi2_bounds`,
  the two-sided interval of their average over N Monte Carlo runs
  (``N·ANEES ~ χ²(N·d)``); :func:`anees_series`, per time step with that interval.
* :func:`error_ellipse`: semi-axes and orientation of a 2 × 2 covariance's
  probability-``p`` ellipse.
* Three CEP statistics, named apart: :func:`cep50`, the radius ``r`` with
  ``P(‖e‖ ≤ r) = 0.5`` for a Gaussian with covariance ``P``, computed exactly (the
  ``0.59(σ₁+σ₂)`` rule of thumb, :func:`cep50_approx`, is −12.5 % off for a degenerate
  ellipse); :func:`empirical_cep50`, the median miss distance of a set of fixes; and
  :func:`median_point_distance`, the MEKF thesis's "CEP 50 %": the distance from truth to
  the coordinate-wise median point, a bias measure far smaller than the CEP.
* Set distances for many targets: :func:`ospa` (Schuhmacher, Vo & Vo 2008)::

      d = ( (1/n)·( min_π Σᵢ d_c(xᵢ, y_π(i))ᵖ + cᵖ·(n − m) ) )^(1/p),   m ≤ n

  and :func:`gospa` (Rahmathullah, García-Fernández & Svensson 2017, α = 2)::

      d = ( min_γ Σ_(i,j)∈γ d(xᵢ, y_j)ᵖ + (cᵖ/2)·(#missed + #false) )^(1/p)

  with its localisation / missed / false decomposition. Both minimise ``Σ dᵖ`` itself
  (an assignment made on ``d`` agrees only for p = 1).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from scipy.optimize import brentq, linear_sum_assignment
from scipy.special import gammaincinv, ndtri  # the χ² and normal quantiles without scipy.stats (0.25 s a process)


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


def _chi2_ppf(q: float, dof: float) -> float:
    """χ²⁻¹(q; dof) = 2·P⁻¹(dof/2, q), P the regularised lower incomplete gamma function:
    the very expression ``scipy.stats.chi2.ppf`` evaluates, bit for bit."""
    return 2.0 * gammaincinv(0.5 * dof, q)


def chi2_bounds(dof: int, n_runs: int, prob: float = 0.95) -> tuple[float, float]:
    """Two-sided ``prob`` interval for the average of ``n_runs`` NEES/NIS of ``dof`` each."""
    if dof < 1 or n_runs < 1 or not 0.0 < prob < 1.0:
        raise ValueError(f"chi2_bounds: need dof >= 1, n_runs >= 1, 0 < prob < 1 (got {dof}, {n_runs}, {prob})")
    a = 0.5 * (1.0 - prob)
    nd = dof * n_runs
    return float(_chi2_ppf(a, nd) / n_runs), float(_chi2_ppf(1.0 - a, nd) / n_runs)


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
    k = np.sqrt(_chi2_ppf(prob, 2))
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
        return float(s1 * ndtri(0.5 + 0.5 * prob))
    n = int(min(2 ** 20, max(512, 64 * s1 / s2)))  # resolve the integrand's peak, width ~ s2/s1
    k = np.sqrt(_chi2_ppf(prob, 2))
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
    """The thesis's "CEP 50 %" (document 000): distance from truth to the coordinate-wise
    median of the fixes. A bias measure — NOT the CEP radius (see module docstring)."""
    med = np.median(np.asarray(fixes, dtype=float)[..., :2].reshape(-1, 2), axis=0)
    return float(np.hypot(*(med - np.asarray(truth, dtype=float)[:2])))


def anees_series(nees_values, dof: int, prob: float = 0.95):
    """Average NEES per time step of an ``(n_runs, n_t)`` array, and the ``prob`` χ²
    interval for an average of ``n_runs`` values of ``dof`` degrees of freedom.

    Returns ``(anees (n_t,), (lo, hi))``; NaN entries (a run without an estimate at that
    step) are left out of the average, and the interval is for the full ``n_runs``.
    """
    v = np.atleast_2d(np.asarray(nees_values, dtype=float))
    return np.nanmean(v, axis=0), chi2_bounds(dof, v.shape[0], prob)


# Multi-target set distances ------------------------------------------------------------
def _point_sets(X, Y):
    """Two point sets as ``(m, d)`` and ``(n, d)`` arrays (an empty set may be ``[]``)."""
    X = np.asarray(X, dtype=float)
    Y = np.asarray(Y, dtype=float)
    dims = {A.shape[-1] for A in (X, Y) if A.size}
    if any(A.size and A.ndim != 2 for A in (X, Y)) or len(dims) > 1:
        raise ValueError(f"point sets must be (m, d) and (n, d) arrays, got shapes {X.shape} and {Y.shape}")
    d = dims.pop() if dims else 1
    return (X if X.size else np.zeros((0, d))), (Y if Y.size else np.zeros((0, d)))


def _check_cp(c: float, p: float) -> None:
    if not (np.isfinite(c) and c > 0.0) or not (p >= 1.0 and np.isfinite(p)):
        raise ValueError(f"need a cut-off c > 0 and an order 1 <= p < inf (got c={c}, p={p})")


def _distances(X, Y) -> np.ndarray:
    return np.linalg.norm(X[:, None, :] - Y[None, :, :], axis=-1)


def ospa(X, Y, c: float, p: float = 2.0) -> float:
    """OSPA distance between point sets ``X (m, d)`` and ``Y (n, d)`` (module docstring)."""
    _check_cp(c, p)
    X, Y = _point_sets(X, Y)
    m, n = len(X), len(Y)
    if m == 0 and n == 0:
        return 0.0
    if m == 0 or n == 0:
        return float(c)
    D = np.minimum(_distances(X, Y), c) ** p
    r, k = linear_sum_assignment(D)
    return float(((D[r, k].sum() + c**p * abs(m - n)) / max(m, n)) ** (1.0 / p))


class GOSPA(NamedTuple):
    """GOSPA distance and its parts: ``distance = (localisation + missed + false)^(1/p)``
    with ``localisation`` the summed ``dᵖ`` of assigned pairs and ``missed``/``false``
    the ``(cᵖ/2)``-weighted counts; ``n_missed``/``n_false`` are the counts."""

    distance: float
    localisation: float
    missed: float
    false: float
    n_missed: int
    n_false: int


def gospa(estimates, truths, c: float, p: float = 2.0) -> GOSPA:
    """GOSPA (α = 2) between ``estimates (m, d)`` and ``truths (n, d)`` (module docstring)."""
    _check_cp(c, p)
    X, Y = _point_sets(estimates, truths)
    m, n = len(X), len(Y)
    half = c**p / 2.0
    if m == 0 or n == 0:
        return GOSPA(float((half * (m + n)) ** (1.0 / p)), 0.0, half * n, half * m, n, m)
    D = _distances(X, Y) ** p
    # Assigning a pair at d^p >= c^p is never better than a miss plus a false track
    # (cost c^p): solve with costs capped at c^p and drop the capped pairs.
    r, k = linear_sum_assignment(np.minimum(D, c**p))
    keep = D[r, k] < c**p
    loc = float(D[r, k][keep].sum())
    assigned = int(keep.sum())
    n_missed, n_false = n - assigned, m - assigned
    total = loc + half * (n_missed + n_false)
    return GOSPA(float(total ** (1.0 / p)), loc, half * n_missed, half * n_false, n_missed, n_false)
