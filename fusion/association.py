r"""Measurement-to-track association and track management for many targets.

Pure functions and small classes that :mod:`fusion.mtt`, :mod:`fusion.network` and
:mod:`fusion.df.multi` put around their per-track filters.

*Gating.* A track predicted to ``(x, P)`` and a plot ``z`` of a sensor with model ``h``
give ``ν = z − h(x)`` (angles wrapped) and ``S = H P Hᵀ + R``; if the pair is right
``d² = νᵀ S⁻¹ ν`` is χ²(n_z), so the gate ``d² ≤ G = χ²⁻¹(P_G; n_z)`` keeps the true plot
with probability ``P_G``. ``H`` and ``S`` do not depend on ``z``, so :func:`mahalanobis2`
scores a whole scan against a track at once.

*Sequential gating.* The sensors of one frame are gated one after another: a track that
took a plot of one sensor is gated for the next at its state updated with that plot
(:func:`gating_update`). A track born or coasting with a broad covariance (an unknown
velocity spreads a second's prediction over hundreds of metres) is narrowed by its
first plot before the next sensor's plots compete for it, so a neighbour's plot that
fits the broad prediction no longer fits.

*Global nearest neighbour* (:func:`gnn`): the least-cost assignment with one "miss"
column of cost ``G`` per track, ``linear_sum_assignment`` on ``[D | diag(G)]``.

*Track-to-track distance* (:func:`track_distance2`): two estimates of one state differ by
``Δ = x₁ − x₂`` with covariance ``T = P₁ + P₂ − P₁₂ − P₁₂ᵀ`` (``P₁₂ = 0`` when unknown,
which only widens the gate); ``d² = Δᵀ T⁺ Δ`` with the rank of ``T`` as its degrees of
freedom (``T`` is singular when the two share a prior).

*Track management*: :class:`TrackLogic` (tentative → confirmed by M-of-N, deleted after
K misses), :class:`DuplicateWatch` (the later of two tracks that agree for ``F`` frames
is deleted), :class:`TrackIds` (published ids in order of confirmation, never reused).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import lru_cache

import numpy as np
from scipy.linalg import cho_factor, cho_solve
from scipy.optimize import linear_sum_assignment
from scipy.special import chdtri  # χ²⁻¹ without importing scipy.stats (0.3 s a process)

from . import kalman
from .angles import wrap_pi

TENTATIVE, CONFIRMED, DELETED = "tentative", "confirmed", "deleted"


# Gating --------------------------------------------------------------------------------
@lru_cache(maxsize=64)
def gate_threshold(dof: int, prob: float) -> float:
    """``G = χ²⁻¹(prob; dof)``: a true plot falls inside ``d² ≤ G`` with probability ``prob``."""
    if not 0.0 < prob < 1.0:
        raise ValueError(f"gate probability must lie in (0, 1), got {prob}")
    if dof < 1:
        raise ValueError(f"gate needs dof >= 1, got {dof}")
    return float(chdtri(dof, 1.0 - prob))


def mahalanobis2(model, x: np.ndarray, P: np.ndarray, Z: np.ndarray) -> np.ndarray:
    """``d²`` of each row of ``Z (n, n_z)`` (plots of one sensor) against the track ``(x, P)``.

    ``model`` is the sensor's :class:`~fusion.measurement.models.MeasurementModel`. Returns ``(n,)``;
    ``inf`` for every plot when the geometry is undefined (track over the site).
    """
    Z = np.atleast_2d(np.asarray(Z, dtype=float))
    try:
        z_pred = model.h(x)
        H = model.jacobian(x)
    except ValueError:
        return np.full(len(Z), np.inf)
    nu = Z - z_pred
    nu[:, model.angles] = wrap_pi(nu[:, model.angles])
    S = H @ P @ H.T + model.R
    c = cho_factor(0.5 * (S + S.T), lower=True, check_finite=False)
    return np.einsum("ij,ji->i", nu, cho_solve(c, nu.T, check_finite=False))


def gating_update(model, x: np.ndarray, P: np.ndarray, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(x, P)`` after the EKF update with one plot ``z`` of the sensor ``model``: the
    state a frame's next sensor is gated against (sequential gating, module docstring)."""
    nu, H = model.innovation_and_jacobian(np.asarray(z, dtype=float), x)
    res = kalman.update(x, P, nu, H, model.R)
    return res.x, res.P


# Global nearest neighbour ---------------------------------------------------------------
def gnn(d2: np.ndarray, gate: float) -> list[tuple[int, int]]:
    """Least-cost assignment of tracks (rows) to plots (columns) from their ``d²``: each
    track takes at most one plot and each plot goes to at most one track, a track left
    without a plot costs ``gate``, and pairs with ``d² > gate`` are forbidden.

    Returns the assigned ``(row, column)`` pairs in row order; a row not listed is a
    missed track, a column not listed a plot no track takes.
    """
    d2 = np.atleast_2d(np.asarray(d2, dtype=float))
    n, m = d2.shape
    if n == 0 or m == 0:
        return []
    allowed = d2 <= gate
    if not allowed.any():
        return []
    # Forbidden pairs cost more than every track missing (n·G): never chosen over a miss.
    big = gate * (n + 1) + 1.0
    cost = np.full((n, m + n), big)
    cost[:, :m] = np.where(allowed, d2, big)
    cost[np.arange(n), m + np.arange(n)] = gate
    rows, cols = linear_sum_assignment(cost)
    return [(int(r), int(c)) for r, c in zip(rows, cols) if c < m and allowed[r, c]]


# Track-to-track association ---------------------------------------------------------------
_PINV_RTOL = 1e-10  # eigenvalues of an equilibrated PSD matrix below this count as zero


def track_distance2(x1, P1, x2, P2, P12=None, dims=None) -> tuple[float, int]:
    """``(d², rank)`` of the difference of two estimates of one state (module docstring).

    ``dims`` selects the compared components (default: all); ``P12 = Cov(e₁, e₂)`` or None.
    ``rank`` is 0 (and ``d² = 0``) when ``T`` vanishes: identical tracks."""
    idx = np.arange(len(x1)) if dims is None else np.asarray(dims)
    d = (np.asarray(x1, float) - np.asarray(x2, float))[idx]
    T = np.asarray(P1, float) + np.asarray(P2, float)
    if P12 is not None:
        C = np.asarray(P12, float)
        T = T - C - C.T
    T = T[np.ix_(idx, idx)]
    # Pseudo-inverse of the equilibrated T (components of ~10⁴ m next to ~1 m/s).
    s = np.sqrt(np.clip(np.diag(T), 0.0, None))
    s = np.where(s > 1e-300, s, 1.0)
    w, V = np.linalg.eigh(0.5 * (T + T.T) / s[:, None] / s[None, :])
    keep = w > _PINV_RTOL * max(float(w.max(initial=0.0)), 1e-300)
    y = V[:, keep].T @ (d / s)
    return float(np.sum(y * y / w[keep])), int(keep.sum())


# Track management -----------------------------------------------------------------------
class DuplicateWatch:
    """Finds tracks that follow a target another track already holds (module docstring).

    Args:
        frames: consecutive frames a pair must agree before the later track goes
            (0: never).
        gate_prob: χ² gate probability of the agreement test.
        dims: the compared state components (position and velocity).
    """

    def __init__(self, frames: int, gate_prob: float, dims=(0, 1, 2, 3, 4, 5)):
        if frames < 0:
            raise ValueError(f"merge_frames must be >= 0, got {frames}")
        self.frames = frames
        self.gate_prob = gate_prob
        self.dims = np.asarray(dims)
        self._streak: dict[tuple, int] = {}

    def duplicates(self, tracks) -> list:
        """One frame: ``tracks`` are ``(key, x, P)`` at the frame's time, the track that
        keeps priority first (confirmed in id order, then tentative in birth order).
        Returns the keys of the tracks to delete."""
        if not self.frames or len(tracks) < 2:
            self._streak = {}
            return []
        keys = [k for k, _, _ in tracks]
        X = np.array([np.asarray(x, float)[self.dims] for _, x, _ in tracks])
        T = np.array([np.trace(np.asarray(P, float)[np.ix_(self.dims[:3], self.dims[:3])]) for _, _, P in tracks])
        # d² ≥ |Δpos|² / tr(T_pos): pairs farther apart than that bound allows cannot agree.
        D2 = np.sum((X[:, None, :3] - X[None, :, :3]) ** 2, axis=-1)
        bound = gate_threshold(len(self.dims), self.gate_prob) * (T[:, None] + T[None, :])
        streak: dict[tuple, int] = {}
        gone: set[int] = set()
        for i, j in zip(*np.nonzero(np.triu(D2 <= bound, 1))):
            (ki, xi, Pi), (kj, xj, Pj) = tracks[i], tracks[j]
            d2, rank = track_distance2(xi, Pi, xj, Pj, dims=self.dims)
            if rank and d2 > gate_threshold(rank, self.gate_prob):
                continue
            n = streak[(ki, kj)] = self._streak.get((ki, kj), 0) + 1
            if n >= self.frames and i not in gone:
                gone.add(j)
        self._streak = {k: n for k, n in streak.items() if not ({k[0], k[1]} & {keys[g] for g in gone})}
        return [keys[g] for g in sorted(gone)]


@dataclass(frozen=True)
class ManagementRule:
    """M-of-N confirmation and K-miss deletion: a track is confirmed once it has
    ``confirm_m`` hits (birth included) within its first ``confirm_n`` frames, and a
    confirmed track is deleted after ``delete_misses`` consecutive missed frames; any
    track is deleted once its position σ (√trace P_pos) exceeds ``max_pos_std``."""

    confirm_m: int = 3
    confirm_n: int = 4
    delete_misses: int = 3
    max_pos_std: float = math.inf

    def __post_init__(self):
        if not 1 <= self.confirm_m <= self.confirm_n:
            raise ValueError(f"need 1 <= confirm_m <= confirm_n, got M={self.confirm_m}, N={self.confirm_n}")
        if self.delete_misses < 1:
            raise ValueError(f"delete_misses must be >= 1, got {self.delete_misses}")


@dataclass
class TrackLogic:
    """One track's status; :meth:`record` is called once per frame after its birth.

    Attributes:
        status: ``tentative``, ``confirmed`` or ``deleted``.
        hits: hits over the frames seen so far (birth counts as one).
        frames: frames seen so far, birth included.
        misses: consecutive missed frames (reset by a hit).
    """

    rule: ManagementRule
    status: str = TENTATIVE
    hits: int = 1
    frames: int = 1
    misses: int = 0

    def __post_init__(self):
        self._settle()

    def record(self, hit: bool, P_pos: np.ndarray | None = None) -> str:
        """One more frame, with the track's position covariance ``P_pos`` after it (for
        ``max_pos_std``); returns the new status."""
        if self.status == DELETED:
            raise ValueError("a deleted track records no more frames")
        self.frames += 1
        self.hits += int(hit)
        self.misses = 0 if hit else self.misses + 1
        self._settle()
        if P_pos is not None and self.status != DELETED and math.sqrt(float(np.trace(P_pos))) > self.rule.max_pos_std:
            self.status = DELETED
        return self.status

    def _settle(self) -> None:
        r = self.rule
        if self.status == TENTATIVE:
            if self.hits >= r.confirm_m:
                self.status = CONFIRMED
            elif self.hits + (r.confirm_n - self.frames) < r.confirm_m:
                self.status = DELETED  # M cannot be reached within N frames any more
        elif self.status == CONFIRMED and self.misses >= r.delete_misses:
            self.status = DELETED


@dataclass
class TrackIds:
    """Issues ``T1, T2, …`` (``prefix`` + counter), one per confirmed track, never reused."""

    prefix: str = "T"
    issued: int = field(default=0)

    def next(self) -> str:
        self.issued += 1
        return f"{self.prefix}{self.issued}"
