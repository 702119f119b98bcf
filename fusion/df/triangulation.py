r"""Fixes from bearings of several sites (documents 002, 003): triangulation and least squares.

Angles here are *math* bearings ``β`` (ccw from east, radians); sites are ENU ``(x, y)``
in metres; ``σ`` is a bearing standard deviation in radians. Every angular residual is
wrapped to (−π, π].

Two-bearing intersection (the thesis's ``ipu``). With ``uᵢ = (cos βᵢ, sin βᵢ)`` and
``Δ = β₂ − β₁`` the fix is ``p = s₁ + r₁u₁ = s₂ + r₂u₂`` with signed ranges
``r₁ = ((s₂−s₁) × u₂)/sin Δ``, ``r₂ = ((s₂−s₁) × u₁)/sin Δ`` (``a × b = a_x b_y − a_y b_x``),
and its Jacobian with respect to the bearings is::

    ∂p/∂β₁ =  r₁ u₂ / sin Δ,      ∂p/∂β₂ = −r₂ u₁ / sin Δ,      P = F diag(σ₁², σ₂²) Fᵀ

(the full covariance; the thesis kept only its diagonal).

Torrieri (linearised weighted LS about a reference ``x₀``)::

    Gᵢ = [−sin φ₀ᵢ, cos φ₀ᵢ] / D₀ᵢ,   N = diag(σᵢ²)
    x̂ = x₀ + (GᵀN⁻¹G)⁻¹ GᵀN⁻¹ wrap(φ − φ₀),      P = (GᵀN⁻¹G)⁻¹

One step is Torrieri's original estimator; iterating it is Gauss–Newton on the weighted
LS cost ``Σ wrap(φᵢ − h(x))²/σᵢ²`` (the ML fix for Gaussian bearing errors).

Stansfield replaces the angular residual by the perpendicular miss distance
``pᵢ = aᵢ·(x − sᵢ)``, ``aᵢ = [−sin φᵢ, cos φᵢ]`` — linear in ``x`` — weighted by
``1/(D₀ᵢ² σᵢ²)`` (``D₀ᵢ`` from the reference point). The plain perpendicular-distance LS
uses unit weights. The pairwise-intersection average (the "cocked-hat centroid" for
three bearings) is the usual reference point.
"""

from __future__ import annotations

from typing import NamedTuple, Sequence

import numpy as np
from scipy.linalg import cho_factor, cho_solve

from ..angles import wrap_pi
from ..types import Measurement
from .models import bearing, bearing_jacobian, bearing_of, stated_sigma

#: |sin Δ| below this counts as parallel bearings.
PARALLEL_TOL = 1e-9


class GeometryError(ValueError):
    """The bearings do not fix a position: parallel, diverging or collinear geometry."""


class Fix(NamedTuple):
    """A position fix: ``x`` (m), covariance ``P`` (m²), the number of iterations run,
    whether the iteration converged, the weighted residual cost (χ² with n−2 dof for
    Torrieri) and the mask of bearings used (leave-one-out may drop some)."""

    x: np.ndarray
    P: np.ndarray
    iterations: int
    converged: bool
    chi2: float
    used: np.ndarray


def _cross(a, b):
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


def _unit(beta):
    beta = np.asarray(beta, dtype=float)
    return np.stack([np.cos(beta), np.sin(beta)], axis=-1)


def _ranges(site1, beta1, site2, beta2):
    d = np.asarray(site2, dtype=float)[..., :2] - np.asarray(site1, dtype=float)[..., :2]
    u1, u2 = _unit(beta1), _unit(beta2)
    s = np.sin(np.asarray(beta2, dtype=float) - np.asarray(beta1, dtype=float))
    with np.errstate(divide="ignore", invalid="ignore"):
        r1 = _cross(d, u2) / s
        r2 = _cross(d, u1) / s
    return s, r1, r2, u1, u2


def intersect_bearings(site1, beta1, site2, beta2):
    """Intersection of two bearing rays (broadcasts over leading axes).

    Raises :class:`GeometryError` when the bearings are parallel or the rays do not meet ahead of
    both sites (diverging bearings: no fix in the direction either DF looks).
    """
    s, r1, r2, u1, _ = _ranges(site1, beta1, site2, beta2)
    if np.any(np.abs(s) < PARALLEL_TOL):
        raise GeometryError("intersect_bearings: the two bearings are parallel (no intersection)")
    if np.any(r1 <= 0.0) or np.any(r2 <= 0.0):
        raise GeometryError("intersect_bearings: the bearing rays diverge (they meet behind a site)")
    return np.asarray(site1, dtype=float)[..., :2] + r1[..., None] * u1


def intersection_jacobian(site1, beta1, site2, beta2):
    """``F = [∂p/∂β₁, ∂p/∂β₂]`` (shape ``(..., 2, 2)``, columns per bearing)."""
    s, r1, r2, u1, u2 = _ranges(site1, beta1, site2, beta2)
    if np.any(np.abs(s) < PARALLEL_TOL):
        raise GeometryError("intersection_jacobian: the two bearings are parallel")
    c1 = r1[..., None] * u2 / s[..., None]
    c2 = -r2[..., None] * u1 / s[..., None]
    return np.stack([c1, c2], axis=-1)


def ipu(site1, beta1, sigma1: float, site2, beta2, sigma2: float, diagonal: bool = False):
    """Initial position and uncertainty from two bearings: ``(p, P)``.

    ``P = F diag(σ₁², σ₂²) Fᵀ`` in full; ``diagonal=True`` keeps only its diagonal, as
    the thesis did. Raises :class:`GeometryError` (a ValueError) for parallel or diverging bearings.
    """
    if not (sigma1 > 0 and sigma2 > 0):
        raise ValueError(f"ipu: bearing std must be > 0, got {sigma1}, {sigma2}")
    p = intersect_bearings(site1, beta1, site2, beta2)
    F = intersection_jacobian(site1, beta1, site2, beta2)
    P = F @ np.diag([sigma1 ** 2, sigma2 ** 2]) @ F.T
    P = 0.5 * (P + P.T)
    return p, (np.diag(np.diag(P)) if diagonal else P)


def _as_arrays(sites, betas, sigmas):
    sites = np.atleast_2d(np.asarray(sites, dtype=float))[:, :2]
    betas = np.atleast_1d(np.asarray(betas, dtype=float))
    sigmas = np.broadcast_to(np.asarray(sigmas, dtype=float), betas.shape)
    if sites.shape[0] != betas.shape[0]:
        raise ValueError(f"{sites.shape[0]} sites but {betas.shape[0]} bearings")
    if np.any(~np.isfinite(sigmas)) or np.any(sigmas <= 0):
        raise ValueError("bearing std must be finite and > 0")
    if betas.size < 2:
        raise ValueError("a fix needs at least two bearings")
    return sites, betas, sigmas


def pairwise_intersection_mean(sites, betas) -> np.ndarray:
    """Average of the intersections of all pairs of bearings from distinct sites.

    Parallel and diverging pairs are skipped; raises ValueError if no pair intersects.
    """
    sites = np.atleast_2d(np.asarray(sites, dtype=float))[:, :2]
    betas = np.atleast_1d(np.asarray(betas, dtype=float))
    if len(betas) < 2 or len(sites) != len(betas):
        raise ValueError("pairwise_intersection_mean: needs at least two bearings, one site each")
    i, j = np.triu_indices(len(betas), k=1)
    s, r1, r2, u1, _ = _ranges(sites[i], betas[i], sites[j], betas[j])
    ok = (np.abs(s) >= PARALLEL_TOL) & (r1 > 0) & (r2 > 0) & np.any(sites[i] != sites[j], axis=1)
    if not np.any(ok):
        raise GeometryError("pairwise_intersection_mean: no pair of bearings intersects ahead of its sites")
    return np.mean(sites[i][ok] + r1[ok, None] * u1[ok], axis=0)


def _information(x, sites, sigmas):
    G = bearing_jacobian(x, sites)
    W = 1.0 / sigmas ** 2
    return G, W, (G * W[:, None]).T @ G


def _cost(x, sites, betas, sigmas):
    return float(np.sum((wrap_pi(betas - bearing(x, sites)) / sigmas) ** 2))


def _chol(A, what):
    try:
        return cho_factor(A, lower=True)
    except np.linalg.LinAlgError:
        raise GeometryError(f"{what}: the bearings do not determine a position (collinear geometry)") from None


def torrieri(sites, betas, sigmas, x0=None, iterations: int = 0, max_iter: int = 100,
             tol: float = 1e-12) -> Fix:
    """Torrieri's weighted LS fix.

    Args:
        sites: ``(n, 2)`` site positions (m); betas: ``(n,)`` math bearings; sigmas: std.
        x0: reference point; default the pairwise-intersection average.
        iterations: 1 = Torrieri's one-step estimator (pure linearised step); k > 1 =
            k such steps; 0 = Gauss–Newton to convergence (step ≤ tol·(1+‖x‖), with
            step halving if a full step would raise the cost).
    Returns a :class:`Fix` whose ``P = (GᵀN⁻¹G)⁻¹`` is evaluated at the returned ``x``.
    """
    sites, betas, sigmas = _as_arrays(sites, betas, sigmas)
    if iterations < 0:
        raise ValueError(f"torrieri: iterations must be >= 0, got {iterations}")
    x = pairwise_intersection_mean(sites, betas) if x0 is None else np.asarray(x0, dtype=float)[:2].copy()
    n_max = iterations if iterations > 0 else max_iter
    converged = False
    it = 0
    for it in range(1, n_max + 1):
        G, W, A = _information(x, sites, sigmas)
        resid = wrap_pi(betas - bearing(x, sites))
        step = cho_solve(_chol(A, "torrieri"), G.T @ (W * resid))
        if iterations > 0:
            x = x + step
            converged = bool(np.linalg.norm(step) <= tol * (1.0 + np.linalg.norm(x)))
            continue
        c0, lam = _cost(x, sites, betas, sigmas), 1.0
        while lam > 1e-6 and _cost(x + lam * step, sites, betas, sigmas) > c0:
            lam *= 0.5
        x = x + lam * step
        if np.linalg.norm(lam * step) <= tol * (1.0 + np.linalg.norm(x)):
            converged = True
            break
    _, _, A = _information(x, sites, sigmas)
    P = cho_solve(_chol(A, "torrieri"), np.eye(2))
    return Fix(x, 0.5 * (P + P.T), it, converged, _cost(x, sites, betas, sigmas), np.ones(len(betas), bool))


def _line_ls(sites, betas, weights):
    """Weighted LS intersection of the bearing *lines*: min Σ wᵢ (aᵢ·(x − sᵢ))²."""
    a = np.stack([-np.sin(betas), np.cos(betas)], axis=-1)
    b = np.sum(a * sites, axis=-1)
    A = (a * weights[:, None]).T @ a
    c = _chol(A, "line LS")
    return cho_solve(c, (a * weights[:, None]).T @ b), a, c


def stansfield(sites, betas, sigmas, x0=None, iterations: int = 1, max_iter: int = 100,
               tol: float = 1e-12) -> Fix:
    """Stansfield's fix: perpendicular miss distances weighted by ``1/(D₀ᵢ² σᵢ²)``.

    ``iterations=1`` is Stansfield's estimator with ranges from the reference ``x0``
    (default the pairwise-intersection average); ``0`` re-evaluates the ranges at the
    new fix until it stops moving. ``P = (AᵀWA)⁻¹``.
    """
    sites, betas, sigmas = _as_arrays(sites, betas, sigmas)
    x = pairwise_intersection_mean(sites, betas) if x0 is None else np.asarray(x0, dtype=float)[:2].copy()
    n_max = iterations if iterations > 0 else max_iter
    converged = False
    it = 0
    for it in range(1, n_max + 1):
        D2 = np.sum((x - sites) ** 2, axis=1)
        x_new, a, c = _line_ls(sites, betas, 1.0 / (D2 * sigmas ** 2))
        moved = np.linalg.norm(x_new - x)
        x = x_new
        converged = bool(moved <= tol * (1.0 + np.linalg.norm(x)))
        if iterations == 0 and converged:
            break
    P = cho_solve(c, np.eye(2))
    return Fix(x, 0.5 * (P + P.T), it, converged, _cost(x, sites, betas, sigmas), np.ones(len(betas), bool))


def perpendicular_ls(sites, betas, sigmas) -> Fix:
    """Unweighted perpendicular-distance LS: min Σ (aᵢ·(x − sᵢ))².

    The estimator ignores ``sigmas``; they serve its covariance, the sandwich
    ``(AᵀA)⁻¹ Aᵀ diag(Dᵢ²σᵢ²) A (AᵀA)⁻¹`` with ranges ``Dᵢ`` at the fix.
    """
    sites, betas, sigmas = _as_arrays(sites, betas, sigmas)
    x, a, c = _line_ls(sites, betas, np.ones(len(betas)))
    D2 = np.sum((x - sites) ** 2, axis=1)
    B = cho_solve(c, a.T)  # (AᵀA)⁻¹Aᵀ
    P = (B * (D2 * sigmas ** 2)) @ B.T
    return Fix(x, 0.5 * (P + P.T), 1, True, _cost(x, sites, betas, sigmas), np.ones(len(betas), bool))


def studentised_residuals(x, P, sites, betas, sigmas) -> np.ndarray:
    r"""Leave-one-out residuals of a weighted LS bearing fix, in standard deviations.

    For the fit linearised at ``x`` the residual of bearing ``i`` against the fit
    *without* it is ``rᵢ/(1 − hᵢᵢ)`` with variance ``σᵢ²/(1 − hᵢᵢ)``, where
    ``hᵢᵢ = gᵢ P gᵢᵀ/σᵢ²`` is the leverage; so ``tᵢ = rᵢ / (σᵢ √(1 − hᵢᵢ))``. (Exact for
    the linearised problem; no refit per bearing.) A bearing the fit cannot do without
    (``hᵢᵢ → 1``) cannot be tested and gets ``t = 0``.
    """
    sites, betas, sigmas = _as_arrays(sites, betas, sigmas)
    G = bearing_jacobian(x, sites)
    h = np.einsum("ij,jk,ik->i", G, P, G) / sigmas ** 2
    r = wrap_pi(betas - bearing(x, sites))
    free = 1.0 - h
    t = np.zeros_like(r)
    ok = free > 1e-9
    t[ok] = r[ok] / (sigmas[ok] * np.sqrt(free[ok]))
    return t


def leave_one_out(sites, betas, sigmas, gate: float, x0=None, iterations: int = 0) -> Fix:
    """Leave-one-out outlier rejection (document 003) around Torrieri's fix.

    Fit; if the largest |studentised leave-one-out residual| exceeds ``gate`` (in
    standard deviations), drop that bearing and refit; repeat while at least three
    bearings remain. ``gate <= 0`` disables rejection. ``Fix.used`` marks the kept
    bearings.
    """
    sites, betas, sigmas = _as_arrays(sites, betas, sigmas)
    used = np.ones(len(betas), dtype=bool)
    fix = torrieri(sites, betas, sigmas, x0=x0, iterations=iterations)
    while gate > 0 and used.sum() >= 3:
        idx = np.flatnonzero(used)
        t = np.abs(studentised_residuals(fix.x, fix.P, sites[idx], betas[idx], sigmas[idx]))
        worst = int(np.argmax(t))
        if t[worst] <= gate:
            break
        dropped = idx[worst]
        used[dropped] = False
        keep = np.flatnonzero(used)
        try:
            fix = torrieri(sites[keep], betas[keep], sigmas[keep], x0=fix.x, iterations=iterations)
        except GeometryError:  # the rest no longer fixes a position: keep this bearing, stop
            used[dropped] = True
            break
    return fix._replace(used=used)


def fix_from_bearings(bearings: Sequence[Measurement], sigma: float | None = None, gate: float = 0.0,
                      x0=None, iterations: int = 0) -> Fix:
    """Torrieri (with optional leave-one-out gate) on bearing Measurements.

    This is the *centre* of KF+TR / MKF+TR: feed it the latest smoothed bearing of each
    station (themselves bearing Measurements, see :mod:`fusion.df.smoothing`), or any
    raw bearings. ``sigma=None`` uses each measurement's stated std.
    """
    parts = [bearing_of(m) for m in bearings]
    sites = np.array([p[0] for p in parts]).reshape(-1, 2)
    betas = np.array([p[1] for p in parts])
    sig = np.array([stated_sigma(m) for m in bearings]) if sigma is None else np.full(len(parts), float(sigma))
    return leave_one_out(sites, betas, sig, gate, x0=x0, iterations=iterations)
