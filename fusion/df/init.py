r"""Robust initialisation of the recursive bearing filters (EKF, MEKF, IMM).

The theses start every recursive filter from ``ipu``, the crossing of the *first two*
bearings (:func:`fusion.df.triangulation.ipu`). Under jamming each bearing is an outlier
with probability ``p``, so that pair holds one with probability ``1 − (1 − p)²``: the
filter then starts kilometres off with a covariance that claims a few hundred metres.

The robust initialiser keeps the ``ipu`` fix and its covariance and only chooses *which*
pair, from the first ``K`` epochs (an exhaustive MLESAC over two-bearing samples):

1. hypotheses: the crossing ``x_ab`` of every pair of bearings from distinct sites that
   meet ahead of both in a well-conditioned fix (the ``ipu`` test, ``max_rel``);
2. score: the log-likelihood of *all* the window's bearings under the contamination
   model the IMM assumes::

       L(x) = Σᵢ log[(1 − p) N(rᵢ; 0, σᵢ²) + p N(rᵢ; 0, σ₂²)],   rᵢ = wrap(βᵢ − h(x))

3. choice: the highest score (ties: the earliest pair in arrival order).

Every hypothesis fits its own two bearings exactly, so the score compares the fits of
the others; no threshold or gate is needed. The chosen pair is consumed by ``ipu`` and
the window's other bearings are replayed through the filter, so none is counted twice.
Cost: ``O(n²)`` pairs scored against the window's ``n`` bearings. docs/algorithms.md
("Initialisation") says how the streaming methods use it, docs/notes.md why ``K = 5``.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from scipy.special import logsumexp

from ..angles import wrap_pi
from .models import bearing
from .triangulation import PARALLEL_TOL, GeometryError, _ranges, intersection_jacobian

#: sites closer than this (m) count as one site when pairing bearings.
SAME_SITE = 1e-6


class PairChoice(NamedTuple):
    """The pair chosen by :func:`robust_pair`: indices ``i < j`` into the bearings, their
    intersection ``x``, its score (mixture log-likelihood of all bearings at ``x``) and
    the number of usable pairs that were scored."""

    i: int
    j: int
    x: np.ndarray
    loglik: float
    n_candidates: int


def mixture_loglik(x, sites, betas, sigmas, p: float, sigma2: float) -> np.ndarray:
    r"""``Σᵢ log[(1 − p) N(rᵢ; 0, σᵢ²) + p N(rᵢ; 0, σ₂²)]`` with ``rᵢ = wrap(βᵢ − h(x))``.

    ``x`` may be one point ``(2,)`` or a stack ``(m, 2)``; the result has shape ``()``
    or ``(m,)``. Computed in the log domain (no underflow for residuals of any size).
    """
    if not 0.0 < p < 1.0:
        raise ValueError(f"mixture_loglik: outlier probability p must be in (0, 1), got {p}")
    if not sigma2 > 0:
        raise ValueError(f"mixture_loglik: outlier std must be > 0, got {sigma2}")
    x = np.asarray(x, dtype=float)
    sites = np.atleast_2d(np.asarray(sites, dtype=float))[:, :2]
    betas = np.atleast_1d(np.asarray(betas, dtype=float))
    sigmas = np.broadcast_to(np.asarray(sigmas, dtype=float), betas.shape)
    r = wrap_pi(betas - bearing(x[..., None, :], sites))          # (..., n)

    def log_normal(s):
        return -0.5 * (r / s) ** 2 - np.log(s) - 0.5 * np.log(2.0 * np.pi)

    terms = logsumexp(np.stack([np.log1p(-p) + log_normal(sigmas), np.log(p) + log_normal(sigma2)]), axis=0)
    return np.sum(terms, axis=-1)


def usable_pairs(sites, betas, sigmas, max_rel: float = 1.0, new_from: int = 0):
    """Index pairs ``(i, j)``, ``i < j``, of bearings from distinct sites that give a
    usable ``ipu`` fix, and those fixes: ``(i, j, x)`` with ``x`` of shape ``(m, 2)``.

    Usable: not parallel, rays meeting ahead of both sites, and (``max_rel > 0``) a 1σ
    semi-major axis of ``F diag(σᵢ², σⱼ²) Fᵀ`` at most ``max_rel`` × the range from the
    nearer site — the test the ``ipu`` initialisation applies to the first pair.
    ``new_from``: only the pairs whose later bearing ``j`` is at index ``>= new_from``
    (an incremental check after new bearings arrived).
    """
    sites = np.atleast_2d(np.asarray(sites, dtype=float))[:, :2]
    betas = np.atleast_1d(np.asarray(betas, dtype=float))
    sigmas = np.broadcast_to(np.asarray(sigmas, dtype=float), betas.shape)
    n, new_from = len(betas), max(int(new_from), 0)
    if new_from == 0:
        i, j = np.triu_indices(n, k=1)
    else:
        later = np.arange(new_from, n)
        j = np.repeat(later, later)                                   # each later j with every i < j
        i = np.arange(len(j)) - np.repeat(np.cumsum(later) - later, later)
        order = np.lexsort((j, i))                                    # (i, j) order, as triu_indices
        i, j = i[order], j[order]
    distinct = np.linalg.norm(sites[i] - sites[j], axis=1) > SAME_SITE
    i, j = i[distinct], j[distinct]
    s, r1, r2, u1, _ = _ranges(sites[i], betas[i], sites[j], betas[j])
    ok = (np.abs(s) >= PARALLEL_TOL) & (r1 > 0) & (r2 > 0)
    i, j, r1, r2, u1 = i[ok], j[ok], r1[ok], r2[ok], u1[ok]
    x = sites[i] + r1[:, None] * u1
    if max_rel > 0 and len(i):
        F = intersection_jacobian(sites[i], betas[i], sites[j], betas[j])
        P = np.einsum("mak,mk,mbk->mab", F, np.stack([sigmas[i] ** 2, sigmas[j] ** 2], axis=1), F)
        axis = np.sqrt(np.linalg.eigvalsh(P)[:, -1])
        well = axis <= max_rel * np.minimum(r1, r2)
        i, j, x = i[well], j[well], x[well]
    return i, j, x


def ranked_pairs(sites, betas, sigmas, p: float, sigma2: float, max_rel: float = 1.0) -> list[PairChoice]:
    """Every usable pair (:func:`usable_pairs`) with its score, best first (ties: the
    earliest pair in ``(i, j)`` order). Empty if no pair is usable."""
    i, j, x = usable_pairs(sites, betas, sigmas, max_rel)
    if len(i) == 0:
        return []
    score = mixture_loglik(x, sites, betas, sigmas, p, sigma2)
    order = np.argsort(-score, kind="stable")
    return [PairChoice(int(i[k]), int(j[k]), x[k], float(score[k]), len(i)) for k in order]


def robust_pair(sites, betas, sigmas, p: float, sigma2: float, max_rel: float = 1.0) -> PairChoice:
    """The pair of bearings whose intersection best explains all the bearings under the
    contamination model ``(p, σ₂)`` (see the module docstring).

    Args:
        sites: ``(n, 2)`` sites (m); betas: ``(n,)`` math bearings (rad); sigmas: clean std
            per bearing (rad); p: outlier probability; sigma2: outlier std (rad);
            max_rel: conditioning bound of :func:`usable_pairs` (0 = accept any crossing).
    Raises :class:`GeometryError` if no pair is usable.
    """
    ranked = ranked_pairs(sites, betas, sigmas, p, sigma2, max_rel)
    if not ranked:
        raise GeometryError("robust_pair: no two bearings from distinct sites give a usable fix")
    return ranked[0]
