r"""The weighted (PDA) update: a track's Gaussian updated with one scan's plots, each
weighted by the probability that it is the track's.

An associator that answers with weights (PDA, JPDA, JIPDA:
:class:`fusion.tracking.associators.Weights`) gives, for a track and a scan, ``βⱼ`` that
plot ``j`` is the track's (over the plots in its gate) and ``β₀`` that none is
(``β₀ + Σ βⱼ = 1``). With the plots' innovations ``νⱼ = zⱼ − ẑ`` against the prediction
``(x⁻, P⁻)``, the filter's gain ``K`` and innovation covariance ``S`` there (one for
all the plots of the scan), and ``Pᶜ = P⁻ − K S Kᵀ``, the covariance one plot would
leave::

    ν̄  = Σⱼ βⱼ νⱼ                                           (combined innovation)
    x⁺ = x⁻ + K ν̄
    P⁺ = β₀ P⁻ + (1 − β₀) Pᶜ + K (Σⱼ βⱼ νⱼ νⱼᵀ − ν̄ ν̄ᵀ) Kᵀ   (the last: spread of innovations)

These are the mean and covariance of the mixture of the hypotheses "plot ``j`` is the
track's" (``N(x⁻ + K νⱼ, Pᶜ)``, weight ``βⱼ``) and "none is" (``N(x⁻, P⁻)``, weight
``β₀``), moment-matched (Bar-Shalom, Daum and Huang 2009). One plot with ``β₁ = 1`` is
the filter's own update; ``β₀ = 1`` leaves the prediction.

:func:`pda_moments` is the combination given any filter's ``K`` and ``Pᶜ``; each filter's
``update_weighted`` forms them its own way (:func:`fusion.ekf.ekf_update_weighted`: ``H``
at ``x⁻``, ``Pᶜ`` in Joseph form; :meth:`fusion.ukf.TrackUKF.update_weighted`: sigma
points; :meth:`fusion.imm.TrackIMM.update_weighted`: per model, with the mode
probabilities). Tested against the mixture and against Stone Soup's ``PDAUpdater``
(tests/fusion/test_pda.py).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from . import kalman


class WeightedUpdate(NamedTuple):
    """A weighted update's result: the posterior ``(x, P)``, the plots' innovations
    ``nus (m, n_z)``, the combined innovation ``nu``, and ``S``, ``K`` of the update."""

    x: np.ndarray
    P: np.ndarray
    nus: np.ndarray
    nu: np.ndarray
    S: np.ndarray
    K: np.ndarray


def check_weights(beta, beta0: float, m: int) -> np.ndarray:
    """``β`` as an array of the ``m`` plots' weights; ``β ≥ 0``, ``β₀ ≥ 0`` and
    ``β₀ + Σ β = 1`` (to 1e-9), else ``ValueError``."""
    beta = np.asarray(beta, dtype=float).reshape(-1)
    if beta.shape != (m,):
        raise ValueError(f"need one weight per plot ({m}), got {beta.shape[0]}")
    if np.any(beta < 0.0) or beta0 < 0.0 or abs(float(beta0) + float(beta.sum()) - 1.0) > 1e-9:
        raise ValueError(f"association weights must be >= 0 and sum to 1 with the miss weight, "
                         f"got beta0 = {beta0}, sum(beta) = {beta.sum()}")
    return beta


def pda_moments(x: np.ndarray, P: np.ndarray, K: np.ndarray, P_c: np.ndarray, nus: np.ndarray, beta,
                beta0: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(x⁺, P⁺, ν̄)`` from the prediction ``(x, P)``, the gain ``K`` and single-plot
    covariance ``P_c`` of the filter's update, the plots' innovations ``nus (m, n_z)`` and
    their weights ``beta (m,)``, ``beta0`` (module docstring)."""
    nus = np.atleast_2d(np.asarray(nus, dtype=float))
    beta = check_weights(beta, beta0, len(nus))
    nu = beta @ nus
    spread = np.einsum("j,ja,jb->ab", beta, nus, nus) - np.outer(nu, nu)
    P_new = beta0 * P + (1.0 - beta0) * P_c + K @ spread @ K.T
    return x + K @ nu, kalman.symmetrise(P_new), nu
