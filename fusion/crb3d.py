r"""Posterior Cramér–Rao bounds for the evaluation.

**3D tracking.** For ``x_{k+1} = F_k x_k + w_k``, ``w_k ~ N(0, Q_k)`` and ``z = h(x) + v``,
``v ~ N(0, R)``, the posterior CRB (Tichavský, Muravchik & Nehorai 1998) is, in
information form::

    J_{k+1} = (Q_k + F_k J_k⁻¹ F_kᵀ)⁻¹ + E[H_{k+1}ᵀ R⁻¹ H_{k+1}]

with ``H = ∂h/∂x`` at the true state and the expectation over the true trajectories; any
estimator's MSE matrix is ``⪰ J⁻¹``. :func:`posterior_crb` runs it in covariance form
(``C⁻ = F C Fᵀ + Q``, then ``C = (C⁻⁻¹ + Ī)⁻¹`` by Woodbury on a square root of ``Ī``):
the same recursion, without inverting the singular discrete ``Q`` and without losing the
digits that 10⁴ m positions next to 10⁻² m/s² accelerations would cost. ``J₀ = P₀⁻¹``,
the trackers' own initial covariance (docs/algorithms.md, "Posterior bound").
:func:`expected_information` averages ``Σ_j w_j H_jᵀ R_j⁻¹ H_j`` over truth samples,
``w_j`` a detection probability.

**Non-Gaussian noise.** For ``z = h + v`` with ``v`` of density ``f`` the information is
the location Fisher information ``I_f = ∫ f'(v)²/f(v) dv``, in place of ``1/σ²``;
:func:`noise_fisher_information` computes it for ``(1 − p)·N(0, σ₁²) + p·outlier(σ₂)``.
``I_f ≥ 1/Var(v)``, with equality only for the Gaussian. Uniform outliers make ``f``
jump, which violates the bound's regularity conditions: the value is the integral over
the smooth parts, reported as ``regular=False``.
"""

from __future__ import annotations

from typing import NamedTuple, Sequence

import numpy as np
from scipy import integrate

__all__ = [
    "expected_information",
    "posterior_crb",
    "block_rmse",
    "NoiseInformation",
    "noise_fisher_information",
    "effective_std",
]


def expected_information(models: Sequence, states, weights: Sequence[float] | None = None) -> np.ndarray:
    """``E[Σ_j w_j H_jᵀ R_j⁻¹ H_j]`` over the true states.

    Args:
        models: measurement models with ``jacobian(x)`` (n_z × n_x) and ``R`` (n_z × n_z),
            e.g. :class:`fusion.measurement.models.SphericalModel`.
        states: one true state (n_x,) or samples (n_mc, n_x); the mean is over samples.
        weights: per-model factor (detection probability), default 1.
    """
    X = np.atleast_2d(np.asarray(states, dtype=float))
    n_x = X.shape[1]
    w = np.ones(len(models)) if weights is None else np.asarray(weights, dtype=float)
    if w.shape != (len(models),) or np.any(w < 0) or np.any(w > 1):
        raise ValueError(f"weights must be {len(models)} probabilities in [0, 1], got {weights!r}")
    info = np.zeros((n_x, n_x))
    for model, wj in zip(models, w):
        if wj == 0.0:
            continue
        Rinv = np.linalg.inv(np.asarray(model.R, dtype=float))
        for x in X:
            H = model.jacobian(x)
            info += wj * (H.T @ Rinv @ H)
    info /= X.shape[0]
    return 0.5 * (info + info.T)


def _add_information(C: np.ndarray, info: np.ndarray) -> np.ndarray:
    """``(C⁻¹ + info)⁻¹`` without inverting C: Woodbury on ``info = GᵀG``."""
    w, V = np.linalg.eigh(0.5 * (info + info.T))
    tol = 1e-12 * max(float(w.max(initial=0.0)), 0.0)
    keep = w > tol
    if not np.any(keep):
        return C
    G = np.sqrt(w[keep])[:, None] * V[:, keep].T  # r × n, GᵀG = info
    CG = C @ G.T
    S = G @ CG + np.eye(G.shape[0])
    C_new = C - CG @ np.linalg.solve(S, CG.T)
    return 0.5 * (C_new + C_new.T)


def posterior_crb(P0, times, motion, information) -> np.ndarray:
    """The PCRB ``C_k = J_k⁻¹`` at each of ``times`` (see the module docstring).

    Args:
        P0: the initial bound ``J₀⁻¹`` at ``times[0]`` (the tracker's initial covariance).
        times: increasing times (n_t,).
        motion: the *true* motion model: ``F(dt)``, ``Q(dt)`` (:mod:`fusion.motion`).
        information: (n_t, n_x, n_x) expected measurement information at each time;
            ``information[0]`` is added to ``P0⁻¹`` (pass zeros when P0 already holds it).
    Returns:
        (n_t, n_x, n_x) bounds.
    """
    t = np.asarray(times, dtype=float)
    info = np.asarray(information, dtype=float)
    C = np.asarray(P0, dtype=float)
    n_x = C.shape[0]
    if C.shape != (n_x, n_x) or info.shape != (t.size, n_x, n_x):
        raise ValueError(f"posterior_crb: P0 {C.shape} and information {info.shape} do not fit {t.size} times")
    if t.size and np.any(np.diff(t) < 0):
        raise ValueError("posterior_crb: times must be increasing")
    out = np.empty((t.size, n_x, n_x))
    for k in range(t.size):
        if k:
            dt = float(t[k] - t[k - 1])
            if dt > 0.0:
                F, Q = motion.F(dt), motion.Q(dt)
                C = F @ C @ F.T + Q
                C = 0.5 * (C + C.T)
        C = _add_information(C, info[k])
        out[k] = C
    return out


def block_rmse(C: np.ndarray, block: slice | Sequence[int]) -> np.ndarray:
    """``√tr`` of a diagonal block of bounds (…, n, n): e.g. position ``slice(0, 3)``."""
    C = np.asarray(C, dtype=float)
    idx = np.arange(C.shape[-1])[block]
    return np.sqrt(np.sum(C[..., idx, idx], axis=-1))


# Non-Gaussian measurement noise -------------------------------------------------------
class NoiseInformation(NamedTuple):
    """Location Fisher information ``I`` (1/unit²) of a noise density; ``regular`` is False
    when the density has jumps (the CRB's regularity conditions fail)."""

    info: float
    regular: bool

    @property
    def effective_std(self) -> float:
        return float(1.0 / np.sqrt(self.info)) if self.info > 0.0 else float("inf")


def _phi(v, s):
    return np.exp(-0.5 * (v / s) ** 2) / (np.sqrt(2.0 * np.pi) * s)


def noise_fisher_information(sigma1: float, p: float = 0.0, sigma2: float | None = None,
                             law: str = "laplacian") -> NoiseInformation:
    """Location Fisher information ``I_f = ∫ f'(v)²/f(v) dv`` of the noise density
    ``f = (1 − p)·N(0, σ₁²) + p·outlier(σ₂)``, outliers ``law`` (Laplacian or uniform); it
    replaces ``1/σ²`` in the bound. For uniform outliers the density jumps, the bound's
    regularity conditions fail, and the result says ``regular=False``."""
    s1 = float(sigma1)
    p = float(p)
    if not (np.isfinite(s1) and s1 > 0.0) or not 0.0 <= p <= 1.0:
        raise ValueError(f"noise_fisher_information: need σ₁ > 0 and 0 <= p <= 1 (got {sigma1}, {p})")
    if p == 0.0:
        return NoiseInformation(1.0 / s1**2, True)
    if sigma2 is None or not (np.isfinite(sigma2) and sigma2 > 0.0):
        raise ValueError(f"noise_fisher_information: outliers need σ₂ > 0 (got {sigma2})")
    s2 = float(sigma2)
    q = 1.0 - p
    if law == "laplacian":
        b = s2 / np.sqrt(2.0)

        def integrand(v):
            av = abs(v)
            lap = np.exp(-av / b) / (2.0 * b)
            f = q * _phi(v, s1) + p * lap
            df = -q * v / s1**2 * _phi(v, s1) - p * np.sign(v) * lap / b
            return df * df / f if f > 0.0 else 0.0

        if p == 1.0:
            return NoiseInformation(1.0 / b**2, True)
        L = 40.0 * max(s1, b)
        pts = sorted({0.0, *(k * s1 for k in (-8, -4, -2, -1, 1, 2, 4, 8))})
        pts = [x for x in pts if -L < x < L]
        val = 0.0
        edges = [-L, *pts, L]
        for lo, hi in zip(edges[:-1], edges[1:]):
            val += integrate.quad(integrand, lo, hi, limit=200, epsabs=0.0, epsrel=1e-10)[0]
        return NoiseInformation(float(val), True)
    if law == "uniform":
        a = np.sqrt(3.0) * s2
        u = p / (2.0 * a)

        def inside(v):
            g = q * _phi(v, s1)
            dg = -v / s1**2 * g
            return dg * dg / (g + u)

        def outside(v):  # the Gaussian alone: its own integrand v²/σ₁⁴ φ
            return q * v * v / s1**4 * _phi(v, s1)

        L = max(a, 40.0 * s1)
        pts = [x for x in (-4 * s1, -s1, 0.0, s1, 4 * s1) if -a < x < a]
        edges = [-a, *pts, a]
        val = sum(integrate.quad(inside, lo, hi, limit=200, epsabs=0.0, epsrel=1e-10)[0]
                  for lo, hi in zip(edges[:-1], edges[1:]))
        if L > a:
            val += 2.0 * integrate.quad(outside, a, L, limit=200, epsabs=0.0, epsrel=1e-10)[0]
        return NoiseInformation(float(val), False)
    raise ValueError(f"unknown outlier law {law!r}; expected 'laplacian' or 'uniform'")


def effective_std(sigma1: float, p: float = 0.0, sigma2: float | None = None, law: str = "laplacian") -> float:
    """``1/√I`` of :func:`noise_fisher_information`: the Gaussian std with the same information."""
    return noise_fisher_information(sigma1, p, sigma2, law).effective_std
