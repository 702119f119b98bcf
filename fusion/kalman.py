r"""The Kalman step every filter in zfusion shares.

Predict::

    x⁻ = F x,          P⁻ = F P Fᵀ + Q

Update with innovation ν = z − h(x⁻) (angular components wrapped to (−π, π]) and
measurement Jacobian H::

    S = H P⁻ Hᵀ + R,   K = P⁻ Hᵀ S⁻¹,   x⁺ = x⁻ + K ν
    P⁺ = (I − K H) P⁻ (I − K H)ᵀ + K R Kᵀ          (Joseph form)

The Joseph form keeps P⁺ symmetric positive semi-definite under round-off and for
any (even sub-optimal) gain; the result is symmetrised once more. NIS = νᵀ S⁻¹ ν.

Filters (EKF variants, MEKF, IMM, the patent's methods) differ in how they form
``ν`` and ``H``; they all call :func:`predict` and :func:`update` here.
"""

from __future__ import annotations

from typing import NamedTuple

import math

import numpy as np
from scipy.linalg import cho_factor, cho_solve

from .angles import wrap_pi


class UpdateResult(NamedTuple):
    x: np.ndarray
    P: np.ndarray
    nu: np.ndarray
    S: np.ndarray
    nis: float
    K: np.ndarray


def symmetrise(P: np.ndarray) -> np.ndarray:
    return 0.5 * (P + P.T)


def gaussian_mixture(w: np.ndarray, xs: np.ndarray, Ps: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mean and covariance of the mixture ``Σ wⱼ N(xⱼ, Pⱼ)`` (``w`` sums to 1)."""
    x = w @ xs
    d = xs - x
    P = np.einsum("j,jab->ab", w, Ps) + np.einsum("j,ja,jb->ab", w, d, d)
    return x, symmetrise(P)


def predict(x: np.ndarray, P: np.ndarray, F: np.ndarray, Q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Linear(ised) time update ``x⁻ = F x``, ``P⁻ = F P Fᵀ + Q``."""
    return F @ x, symmetrise(F @ P @ F.T + Q)


def innovation(z: np.ndarray, z_pred: np.ndarray, angles: np.ndarray | None = None) -> np.ndarray:
    """``z − z_pred`` with the components flagged in ``angles`` wrapped to (−π, π]."""
    nu = np.asarray(z, dtype=float) - np.asarray(z_pred, dtype=float)
    if angles is not None and np.any(angles):
        nu = np.where(angles, wrap_pi(nu), nu)
    return nu


_IDENTITY: dict[int, np.ndarray] = {}


def _identity(n: int) -> np.ndarray:
    """``I`` (n × n), built once per size (read-only)."""
    eye = _IDENTITY.get(n)
    if eye is None:
        eye = _IDENTITY[n] = np.eye(n)
        eye.setflags(write=False)
    return eye


SMALL_S = 3  # innovation covariances up to this size are factorised on Python floats


def inverse_cholesky_factor(S: np.ndarray) -> np.ndarray:
    """``L⁻¹`` of the Cholesky factor ``S = L Lᵀ``; ``LinAlgError`` unless S is positive
    definite (only S's lower triangle is read).

    A sensor's S is 1 × 1 to 3 × 3. numpy's ``cholesky`` and ``inv`` each spend about
    4 µs handling arguments for a few flops, so up to ``SMALL_S`` rows the factor and its
    inverse (forward substitution) are computed on Python floats; larger S go to numpy.
    """
    n = S.shape[0]
    if n > SMALL_S:
        return np.linalg.inv(np.linalg.cholesky(S))
    s = S.tolist()
    L = [[0.0] * n for _ in range(n)]
    W = [[0.0] * n for _ in range(n)]  # L⁻¹
    for i in range(n):
        Li = L[i]
        for j in range(i + 1):
            acc = s[i][j]
            for k in range(j):
                acc -= Li[k] * L[j][k]
            if j < i:
                Li[j] = acc / L[j][j]
            elif acc <= 0.0:
                raise np.linalg.LinAlgError("innovation covariance is not positive definite")
            else:  # (a NaN passes through, as in numpy's cholesky)
                Li[i] = math.sqrt(acc)
        Wi = W[i]
        Wi[i] = 1.0 / Li[i]
        for j in range(i):
            acc = 0.0
            for k in range(j, i):
                acc += Li[k] * W[k][j]
            Wi[j] = -acc * Wi[i]
    return np.array(W)


def update(x: np.ndarray, P: np.ndarray, nu: np.ndarray, H: np.ndarray, R: np.ndarray) -> UpdateResult:
    """Measurement update given an innovation ``nu`` (already wrapped) and Jacobian ``H``.

    ``S⁻¹`` comes from the Cholesky factor ``S = L Lᵀ`` as ``L⁻ᵀ L⁻¹`` (raises
    ``LinAlgError`` unless S is positive definite, which it is whenever R is; see
    :func:`inverse_cholesky_factor`), and ``NIS = |L⁻¹ ν|²``, never negative. Then the
    Joseph form, symmetrised.
    """
    nu = np.asarray(nu, dtype=float)
    if nu.ndim != 1:
        nu = np.atleast_1d(nu)
    if not (isinstance(H, np.ndarray) and H.ndim == 2):
        H = np.atleast_2d(H)
    if not (isinstance(R, np.ndarray) and R.ndim == 2):
        R = np.atleast_2d(R)
    PHt = P @ H.T
    S = H @ PHt
    S += R
    S = symmetrise(S)
    L_inv = inverse_cholesky_factor(S)
    K = PHt @ (L_inv.T @ L_inv)
    x_new = x + K @ nu
    IKH = _identity(P.shape[0]) - K @ H
    P_new = IKH @ P @ IKH.T
    P_new += K @ R @ K.T
    P_new = symmetrise(P_new)
    w = L_inv @ nu
    return UpdateResult(x_new, P_new, nu, S, float(w @ w), K)


def gaussian_likelihood(nu: np.ndarray, S: np.ndarray) -> float:
    """N(ν; 0, S), the model likelihood used by the IMM."""
    nu = np.atleast_1d(nu)
    S = np.atleast_2d(S)
    c = cho_factor(S, lower=True, check_finite=False)
    m = float(nu @ cho_solve(c, nu, check_finite=False))
    log_det = 2.0 * float(np.sum(np.log(np.diag(c[0]))))
    return float(np.exp(-0.5 * (m + log_det + nu.size * np.log(2.0 * np.pi))))


def gaussian_loglikelihood(nu: np.ndarray, S: np.ndarray) -> float:
    """log N(ν; 0, S) = −½(νᵀS⁻¹ν + log det S + n log 2π), computed without forming the
    density, so it stays finite where :func:`gaussian_likelihood` underflows to 0.0 (for a
    scalar innovation, beyond about 38 standard deviations). Raises LinAlgError if S is
    not positive definite."""
    nu = np.atleast_1d(np.asarray(nu, dtype=float))
    S = np.atleast_2d(np.asarray(S, dtype=float))
    if S.shape == (1, 1):  # scalar innovation (every bearing update): no factorisation needed
        s = float(S[0, 0])
        if not s > 0.0:
            raise np.linalg.LinAlgError(f"gaussian_loglikelihood: S = {s} is not positive")
        return -0.5 * (float(nu[0]) ** 2 / s + np.log(2.0 * np.pi * s))
    c = cho_factor(S, lower=True, check_finite=False)
    m = float(nu @ cho_solve(c, nu, check_finite=False))
    log_det = 2.0 * float(np.sum(np.log(np.diag(c[0]))))
    return -0.5 * (m + log_det + nu.size * np.log(2.0 * np.pi))
