r"""Unscented Kalman filter of one 3D track, with Merwe's scaled sigma points.

Sigma points of ``(x, P)``, ``n = dim x``::

    λ = α²(n + κ) − n,          L Lᵀ = (n + λ) P   (Cholesky, L lower)
    χ₀ = x,   χᵢ = x + Lᵢ,   χₙ₊ᵢ = x − Lᵢ        (Lᵢ the i-th column, i = 1..n)
    Wᵐ₀ = λ / (n + λ),   Wᶜ₀ = Wᵐ₀ + 1 − α² + β,   Wᵐᵢ = Wᶜᵢ = 1 / (2(n + λ))

Predict: the motion model is linear (``x ← F x``), for which the unscented transform
is exact, so ``x⁻ = F x``, ``P⁻ = F P Fᵀ + Q`` (the shared step of :mod:`fusion.kalman`).

Update with a measurement model ``h`` and its ``R``
(:class:`fusion.measurement.models.MeasurementModel`), from the sigma points χ of
``(x⁻, P⁻)`` and ``Zᵢ = h(χᵢ)``::

    ẑ = Σ Wᵐᵢ Zᵢ        (an angle row: the weighted circular mean atan2(Σ Wᵐ sin Z, Σ Wᵐ cos Z))
    S = Σ Wᶜᵢ (Zᵢ − ẑ)(Zᵢ − ẑ)ᵀ + R,    Pₓᵤ = Σ Wᶜᵢ (χᵢ − x⁻)(Zᵢ − ẑ)ᵀ
    K = Pₓᵤ S⁻¹,   ν = z − ẑ,   x⁺ = x⁻ + K ν,   P⁺ = P⁻ − K S Kᵀ,   NIS = νᵀ S⁻¹ ν

with every angle difference wrapped to (−π, π]. ``K·H`` (what a local track reports
to the fusion rules) takes the statistical linearisation ``H = Pₓᵤᵀ P⁻⁻¹``, for which
``P⁺ = (I − K H) P⁻`` exactly as for the EKF. No Jacobian is formed, so the update
does not linearise the azimuth/elevation/range geometry at one point: it matters
where the prior spans a curved part of it (a broad range prior seen by an angle
sensor). The defaults α = 0.5, β = 2, κ = 0 are Stone Soup's. The weighted (PDA)
update of several plots (:meth:`TrackUKF.update_weighted`) takes this ``ẑ``, ``S`` and
``K`` for all of them (:mod:`fusion.pda`).
"""

from __future__ import annotations

import numpy as np

from . import kalman
from .pda import WeightedUpdate, pda_moments


class TrackUKF:
    """Unscented Kalman filter of one 3D track (module docstring): holds ``(x, P, t)``.

    Args:
        motion: a linear motion model (``F(dt)``, ``Q(dt)``, ``check_state``).
        x, P, t: the initial state, its covariance and its time.
        alpha, beta, kappa: the sigma-point parameters (α > 0, n + κ > 0).
    """

    def __init__(self, motion, x: np.ndarray, P: np.ndarray, t: float,
                 alpha: float = 0.5, beta: float = 2.0, kappa: float = 0.0):
        self.motion = motion
        self.x = motion.check_state(x)
        self.P = np.asarray(P, dtype=float)
        if self.P.shape != (self.x.size,) * 2:
            raise ValueError(f"covariance must be {self.x.size}×{self.x.size}, got shape {self.P.shape}")
        self.t = float(t)
        n = self.x.size
        if not alpha > 0.0 or not n + kappa > 0.0:
            raise ValueError(f"sigma points need alpha > 0 and n + kappa > 0, got alpha={alpha}, kappa={kappa}")
        lam = alpha**2 * (n + kappa) - n
        self._c = n + lam
        self.Wm = np.full(2 * n + 1, 0.5 / self._c)
        self.Wm[0] = lam / self._c
        self.Wc = self.Wm.copy()
        self.Wc[0] += 1.0 - alpha**2 + beta
        self._KH = np.zeros((n, n))

    def set_state(self, x: np.ndarray, P: np.ndarray, t: float) -> None:
        """Restart from ``(x, P)`` at ``t`` (a fed-back prior)."""
        x = self.motion.check_state(x)
        P = np.asarray(P, dtype=float)
        if P.shape != (x.size,) * 2:
            raise ValueError(f"covariance must be {x.size}×{x.size}, got shape {P.shape}")
        self.x, self.P, self.t = x, P, float(t)

    def sigma_points(self) -> np.ndarray:
        """The ``2n + 1`` sigma points of ``(x, P)``, one per row. A covariance that is
        only semi-definite (an IMM's constant-velocity model holds the acceleration with
        zero variance) has no Cholesky factor; any ``L Lᵀ = P`` will do, so it takes the
        symmetric square root ``V √Λ`` of its eigen-decomposition instead."""
        try:
            L = np.linalg.cholesky(self.P)
        except np.linalg.LinAlgError:
            w, V = np.linalg.eigh(self.P)
            if w.min() < -1e-9 * max(w.max(), 1.0):
                raise
            L = V * np.sqrt(np.clip(w, 0.0, None))
        L = L * np.sqrt(self._c)
        return np.vstack([self.x, self.x + L.T, self.x - L.T])

    def predicted(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """The prediction to time ``t`` (>= the filter's time), without changing the filter."""
        if t < self.t:
            raise ValueError(f"cannot predict backwards from t={self.t} to t={t}")
        if t == self.t:
            return self.x, self.P
        dt = t - self.t
        return kalman.predict(self.x, self.P, self.motion.F(dt), self.motion.Q(dt))

    def predict(self, t: float) -> None:
        self.x, self.P = self.predicted(t)
        self.t = float(t)

    def _transform(self, model) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """``(ẑ, S, Pₓᵤ, angles)`` of ``model`` at the filter's state (module docstring)."""
        chi = self.sigma_points()
        Z = model.h(chi)  # (2n + 1, n_z)
        angles = np.asarray(model.angles, dtype=bool)
        z_hat = self.Wm @ Z
        z_hat[angles] = np.arctan2(self.Wm @ np.sin(Z[:, angles]), self.Wm @ np.cos(Z[:, angles]))
        dZ = kalman.innovation(Z, z_hat, angles)
        dX = chi - self.x
        S = kalman.symmetrise((dZ.T * self.Wc) @ dZ + model.R)
        Pxz = (dX.T * self.Wc) @ dZ
        return z_hat, S, Pxz, angles

    def _set_KH(self, K: np.ndarray, Pxz: np.ndarray) -> None:
        try:
            self._KH = K @ np.linalg.solve(self.P, Pxz).T  # K Pₓᵤᵀ P⁻⁻¹ (P⁻ symmetric)
        except np.linalg.LinAlgError:  # a semi-definite P⁻ (sigma_points): its pseudo-inverse
            self._KH = K @ (np.linalg.pinv(self.P, hermitian=True) @ Pxz).T

    def update(self, model, z: np.ndarray) -> kalman.UpdateResult:
        """Update at the filter's current time with ``z`` of ``model``; returns the step's
        ν, S, NIS and K."""
        z = np.asarray(z, dtype=float)
        if z.shape != (model.n_z,):
            raise ValueError(f"measurement must have shape ({model.n_z},) for {model.components}, got {z.shape}")
        z_hat, S, Pxz, angles = self._transform(model)
        L_inv = kalman.inverse_cholesky_factor(S)
        S_inv = L_inv.T @ L_inv
        K = Pxz @ S_inv
        nu = kalman.innovation(z, z_hat, angles)
        w = L_inv @ nu
        x = self.x + K @ nu
        P = kalman.symmetrise(self.P - K @ S @ K.T)
        self._set_KH(K, Pxz)
        self.x, self.P = x, P
        return kalman.UpdateResult(x, P, nu, S, float(w @ w), K)

    def innovations(self, model, Z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The plots' innovations ``Zⱼ − ẑ`` (angle rows wrapped) and their covariance
        ``S``, without changing the filter."""
        z_hat, S, _, angles = self._transform(model)
        return kalman.innovation(np.atleast_2d(np.asarray(Z, dtype=float)), z_hat, angles), S

    def update_weighted(self, model, Z: np.ndarray, beta, beta0: float) -> WeightedUpdate:
        """The weighted (PDA) update at the filter's current time with the plots ``Z`` of
        one scan, ``beta`` each and ``beta0`` for none (:mod:`fusion.pda`): the unscented
        ``ẑ``, ``S``, ``K`` above, ``νⱼ = Zⱼ − ẑ``, ``Pᶜ = P⁻ − K S Kᵀ``."""
        Z = np.atleast_2d(np.asarray(Z, dtype=float))
        if len(Z) == 0:
            raise ValueError("a weighted update needs at least one plot (no plot: the prediction)")
        z_hat, S, Pxz, angles = self._transform(model)
        L_inv = kalman.inverse_cholesky_factor(S)
        K = Pxz @ (L_inv.T @ L_inv)
        nus = kalman.innovation(Z, z_hat, angles)
        x, P, nu = pda_moments(self.x, self.P, K, kalman.symmetrise(self.P - K @ S @ K.T), nus, beta, beta0)
        self._set_KH(K, Pxz)
        self.x, self.P = x, P
        return WeightedUpdate(x, P, nus, nu, S, K)

    @property
    def KH(self) -> np.ndarray:
        """``K·H`` of the last update, ``H = Pₓᵤᵀ P⁻⁻¹`` (module docstring)."""
        return self._KH
