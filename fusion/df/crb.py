r"""Cramér–Rao bound for a static emitter located from bearings.

Bearings ``βᵢ = h(p; sᵢ) + vᵢ``, ``vᵢ ~ N(0, σᵢ²)`` independent, ``sᵢ`` the observer's
position at bearing ``i`` (repeated fixed stations, or a moving observer — the formula
is the same). With ``gᵢ = ∂h/∂p = [−Δyᵢ, Δxᵢ]/rᵢ²`` the Fisher information and the bound
on any unbiased estimator's covariance are::

    J = Σᵢ gᵢᵀ gᵢ / σᵢ²,        Cov(p̂) ⪰ J⁻¹,        RMS position error ≥ √tr(J⁻¹)

No prior information is included: the filters' initial fix is itself made of bearings
of the same stream.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from .models import bearing_jacobian


def fisher_information(p, sites, sigmas) -> np.ndarray:
    """``J`` (2×2) for bearings from ``sites`` ``(n, 2|3)`` with std ``sigmas`` (n or scalar)."""
    sites = np.atleast_2d(np.asarray(sites, dtype=float))[:, :2]
    sig = np.broadcast_to(np.asarray(sigmas, dtype=float), (sites.shape[0],))
    if np.any(sig <= 0) or not np.all(np.isfinite(sig)):
        raise ValueError("fisher_information: bearing std must be finite and > 0")
    G = bearing_jacobian(np.asarray(p, dtype=float)[:2], sites)
    return (G / sig[:, None] ** 2).T @ G


def crb(p, sites, sigmas) -> np.ndarray:
    """``J⁻¹``; ValueError when the bearings cannot fix a position (e.g. one site only)."""
    J = fisher_information(p, sites, sigmas)
    if np.linalg.cond(J) > 1e12:
        raise ValueError("crb: the Fisher information is singular (bearings from one site or collinear)")
    C = np.linalg.inv(J)
    return 0.5 * (C + C.T)


def crb_rmse(p, sites, sigmas) -> float:
    """Lower bound on the RMS position error, ``√tr(J⁻¹)`` (m)."""
    return float(np.sqrt(np.trace(crb(p, sites, sigmas))))


def crb_rmse_series(p, epochs: Sequence[tuple[np.ndarray, np.ndarray | float]]) -> np.ndarray:
    """Bound after each epoch for bearings accumulated over ``epochs``.

    ``epochs`` is a sequence of ``(sites (k, 2|3), sigmas (k,) or scalar)``; returns the
    RMS bound after each, ``inf`` while the emitter is not yet observable.
    """
    J = np.zeros((2, 2))
    out = np.empty(len(epochs))
    for k, (sites, sigmas) in enumerate(epochs):
        J = J + fisher_information(p, sites, sigmas)
        out[k] = np.sqrt(np.trace(np.linalg.inv(J))) if np.linalg.cond(J) <= 1e12 else np.inf
    return out
