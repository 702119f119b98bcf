r"""Cramér–Rao bounds for an emitter located from bearings.

Bearings ``βᵢ = h(p; sᵢ) + vᵢ``, ``vᵢ ~ N(0, σᵢ²)`` independent, ``sᵢ`` the observer's
position at bearing ``i`` (repeated fixed stations, or a moving observer — the formula
is the same), ``gᵢ = ∂h/∂p = [−Δyᵢ, Δxᵢ]/rᵢ²``.

**Static emitter.** The Fisher information and the bound on any unbiased estimator's
covariance are::

    J = Σᵢ gᵢᵀ gᵢ / σᵢ²,        Cov(p̂) ⪰ J⁻¹,        RMS position error ≥ √tr(J⁻¹)

No prior information is included: the filters' initial fix is itself made of bearings
of the same stream.

**Moving emitter** (:func:`moving_emitter_pcrb`). For the constant-velocity state
``x = [p, v]``, ``x_{k+1} = F_k x_k + w_k``, ``w_k ~ N(0, Q_k)``
(:class:`fusion.df.models.ConstantVelocityEmitter`), Tichavský's recursive posterior
CRB is::

    J_{k+1} = (Q_k + F_k J_k⁻¹ F_kᵀ)⁻¹ + Σ_{i at k+1} Hᵢᵀ Hᵢ / σᵢ²,    Hᵢ = [gᵢ, 0, 0]

with ``gᵢ`` at the true position (:func:`fusion.crb3d.posterior_crb` runs it). ``J₀``
holds the first epoch's bearings and the filters' velocity prior ``N(0, σ_v² I)``, no
position prior: ``J₀ = diag(0, 0, σ_v⁻², σ_v⁻²) + Σ_{i at 0} Hᵢᵀ Hᵢ / σᵢ²``. With
``q = 0`` it is the batch bound on the trajectory's parameters.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from ..crb3d import posterior_crb
from .models import ConstantVelocityEmitter, bearing_jacobian


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


def bearing_information(x, sites, sigmas, n_x: int = 2) -> np.ndarray:
    """``Σᵢ Hᵢᵀ Hᵢ / σᵢ²`` (n_x × n_x) of bearings from ``sites`` on an emitter whose
    state ``x`` starts with its position: the static block, zero-padded."""
    J = np.zeros((n_x, n_x))
    J[:2, :2] = fisher_information(np.asarray(x, dtype=float)[:2], sites, sigmas)
    return J


def moving_emitter_pcrb(model: ConstantVelocityEmitter, times: Sequence[float], positions,
                        epochs: Sequence[tuple[np.ndarray, np.ndarray | float]], vel_std: float) -> np.ndarray:
    """The posterior CRB (module docstring) after each epoch, ``(n_t, 4, 4)``.

    Args:
        model: the constant-velocity emitter model (its ``F(dt)``, ``Q(dt)``).
        times: epoch times (increasing); positions: the true position at each ``(n_t, 2)``.
        epochs: per epoch ``(sites (k, 2|3), sigmas (k,) or scalar)`` of its bearings
            (``k = 0``: no bearing; the Fisher information is then zero).
        vel_std: the velocity prior's std per axis (m/s), > 0.
    Raises ValueError when the first epoch's bearings cannot fix a position.
    """
    t = np.asarray(times, dtype=float)
    X = np.asarray(positions, dtype=float)
    if not vel_std > 0:
        raise ValueError(f"moving_emitter_pcrb: vel_std must be > 0, got {vel_std}")
    if len(epochs) != t.size or X.shape[0] != t.size:
        raise ValueError("moving_emitter_pcrb: times, positions and epochs disagree in length")
    info = np.array([bearing_information(X[k], *epochs[k], n_x=4) if np.size(epochs[k][0]) else np.zeros((4, 4))
                     for k in range(t.size)])
    J0 = info[0] + np.diag([0.0, 0.0, vel_std ** -2, vel_std ** -2])
    if np.linalg.cond(J0[:2, :2]) > 1e12:
        raise ValueError("moving_emitter_pcrb: the first epoch's bearings do not fix a position")
    info[0] = 0.0
    return posterior_crb(np.linalg.inv(J0), t, model, info)
