r"""The extended Kalman filter of one 3D track, and the EKF step it is made of.

Predict with the motion model (``x⁻ = F x``, ``P⁻ = F P Fᵀ + Q``; a state-dependent
model's ``f(x)`` and its Jacobian), update with any
:class:`fusion.measurement.models.MeasurementModel` linearised at the prediction::

    H = ∂h/∂x(x⁻),   ν = z − h(x⁻) (angle rows wrapped),   then fusion.kalman.update

(Joseph form, NIS). :func:`iterated_ekf_update` relinearises at the updated state
(Gauss–Newton on the MAP cost). :func:`ekf_update_weighted` is the weighted (PDA) update
of several plots of one scan, linearised at the prediction (:mod:`fusion.pda`).
:class:`TrackEKF` is the filter of the :class:`fusion.filters.Filter` protocol built on them.

A target's vertical speed is bounded (an airliner climbs or descends at 25 m/s at most),
and a filter that has not seen the vertical for a while (a track fed by 2D radars) has a
vertical velocity so uncertain that the next height it sees becomes a vertical speed no
aircraft has (``paris-real``: −150 m/s, the track 3 km below its aircraft). With
``max_climb`` the estimate is projected onto ``|v_up| ≤ max_climb`` after each update
(:func:`climb_projected`): the state of least ``(x̃ − x)ᵀ P⁻¹ (x̃ − x)`` on the bound,
``x̃ = x − P e (eᵀ P e)⁻¹ (eᵀ x − d)``, ``e`` the unit vector of ``v_up`` and ``d`` the
bound on its side (Simon & Chia's estimate projection), which moves every state
correlated with ``v_up`` (the height with it); ``P`` is kept, conservative.
"""

from __future__ import annotations

import numpy as np

from . import kalman
from .measurement.models import MeasurementModel
from .pda import WeightedUpdate, pda_moments


def motion_predict(motion, x: np.ndarray, P: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Time update over ``dt`` with a motion model: ``F(dt) x``, ``F P Fᵀ + Q(dt)``; for a
    state-dependent model (one with ``transition(x, dt) -> (f(x), ∂f/∂x, Q)``) its ``f(x)``
    and ``J P Jᵀ + Q`` with the Jacobian at ``x``."""
    step = getattr(motion, "transition", None)
    if step is None:
        return kalman.predict(x, P, motion.F(dt), motion.Q(dt))
    fx, J, Q = step(x, dt)
    return fx, kalman.symmetrise(J @ P @ J.T + Q)


def ekf_predict(motion, x: np.ndarray, P: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """:func:`motion_predict` over ``dt`` (``dt = 0``: unchanged)."""
    if dt == 0.0:
        return x, P
    return motion_predict(motion, x, P, dt)


def _ekf_update(model, x, P, z) -> tuple[kalman.UpdateResult, np.ndarray]:
    nu, H = model.innovation_and_jacobian(z, x)
    return kalman.update(x, P, nu, H, model.R), H


def iterated_ekf_update(model: MeasurementModel, x: np.ndarray, P: np.ndarray, z: np.ndarray,
                        iterations: int, tol: float = 1e-9) -> tuple[kalman.UpdateResult, np.ndarray]:
    r"""Iterated EKF update: Gauss–Newton steps on the MAP cost
    ``(x − x̄)ᵀ P̄⁻¹ (x − x̄) + (z − h(x))ᵀ R⁻¹ (z − h(x))``, relinearising ``h`` at each
    iterate ``xᵢ``:

        Hᵢ = ∂h/∂x(xᵢ),   νᵢ = [z − h(xᵢ)]_wrapped − Hᵢ (x̄ − xᵢ),   xᵢ₊₁ = x̄ + Kᵢ νᵢ,

    with ``Kᵢ`` the Kalman gain of ``Hᵢ`` about the prior ``(x̄, P̄)``; the covariance is
    the Joseph form with the last ``H``. One iteration is the EKF. It matters where the
    prediction lies far from the measurement's linear regime, e.g. an accurate range
    across a cross-range spread of hundreds of metres (docs/consistency.md §4).

    The returned ν, S and NIS are the first iteration's: those of the prediction, which
    is what a consistency (NIS) test and a gate are about. Stops early once a step moves
    the state by less than ``tol`` relative to its size. Returns the result and the last ``H``.
    """
    first, H = _ekf_update(model, x, P, z)
    res = first
    for _ in range(int(iterations) - 1):
        nu, H = model.innovation_and_jacobian(z, res.x)
        step = kalman.update(x, P, nu - H @ (x - res.x), H, model.R)
        moved = float(np.max(np.abs(step.x - res.x)))
        res = step
        if moved <= tol * (1.0 + float(np.max(np.abs(res.x)))):
            break
    return kalman.UpdateResult(res.x, res.P, first.nu, first.S, first.nis, res.K), H


def ekf_update(model: MeasurementModel, x: np.ndarray, P: np.ndarray, z: np.ndarray) -> kalman.UpdateResult:
    """Measurement update linearised at ``x``: ``H = ∂h/∂x(x)``, wrapped ``ν = z − h(x)``,
    Joseph form and NIS via :func:`kalman.update`."""
    return _ekf_update(model, x, P, z)[0]


def ekf_innovations(model: MeasurementModel, x: np.ndarray, P: np.ndarray,
                    Z: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(νs (m, n_z), S, H)``: the angle-wrapped innovations of the plots ``Z (m, n_z)``
    of ``model`` against the prediction ``(x, P)``, their covariance ``S = H P Hᵀ + R``
    and ``H = ∂h/∂x(x)``."""
    Z = np.atleast_2d(np.asarray(Z, dtype=float))
    if len(Z) == 0:
        raise ValueError("innovations of no plot")
    pairs = [model.innovation_and_jacobian(z, x) for z in Z]
    H = pairs[0][1]  # linearised at x: one H for every plot
    return np.array([nu for nu, _ in pairs]), kalman.symmetrise(H @ P @ H.T + model.R), H


def ekf_update_weighted(model: MeasurementModel, x: np.ndarray, P: np.ndarray, Z: np.ndarray, beta,
                        beta0: float) -> tuple[WeightedUpdate, np.ndarray]:
    """The weighted (PDA) update of the prediction ``(x, P)`` with the plots ``Z (m, n_z)``
    of one sensor ``model``, linearised at ``x`` (one ``H``, wrapped ``νⱼ``; ``K`` and
    ``Pᶜ`` those of :func:`fusion.kalman.update`, Joseph form): the result and ``H``."""
    nus, _, H = ekf_innovations(model, x, P, Z)
    one = kalman.update(x, P, np.zeros(nus.shape[1]), H, model.R)  # K, S and Pᶜ at x
    x_new, P_new, nu = pda_moments(x, P, one.K, one.P, nus, beta, beta0)
    return WeightedUpdate(x_new, P_new, nus, nu, one.S, one.K), H


V_UP = 5  # the index of the vertical velocity in a 3D track's state [p v (a)]


def climb_projected(x: np.ndarray, P: np.ndarray, max_climb: float) -> np.ndarray:
    """``x`` projected onto ``|v_up| ≤ max_climb`` in the metric of ``P`` (module
    docstring); ``x`` itself if it is inside."""
    v = float(x[V_UP])
    if abs(v) <= max_climb:
        return x
    return x - P[:, V_UP] / P[V_UP, V_UP] * (v - np.copysign(max_climb, v))


class TrackEKF:
    r"""Extended Kalman filter of one 3D track.

    Holds ``(x, P, t)``. :meth:`predict` moves it to a later time with the motion
    model (``x ← F x``, ``P ← F P Fᵀ + Q``); :meth:`update` linearises a measurement
    model (:class:`~fusion.measurement.models.MeasurementModel`) at the predicted state and
    applies the shared Kalman step (angle-wrapped innovation, Joseph form, NIS; see
    :mod:`fusion.kalman`). ``max_climb`` (m/s): the bound each update's estimate is
    projected onto (:func:`climb_projected`); None: none.
    """

    def __init__(self, motion, x: np.ndarray, P: np.ndarray, t: float, iterations: int = 1,
                 max_climb: float | None = None):
        self.motion = motion
        self.iterations = int(iterations)  # > 1: iterated EKF updates (iterated_ekf_update)
        self.max_climb = max_climb
        self.set_state(x, P, t)

    def set_state(self, x: np.ndarray, P: np.ndarray, t: float) -> None:
        x = self.motion.check_state(x)
        P = np.asarray(P, dtype=float)
        if P.shape != (x.size, x.size):
            raise ValueError(f"covariance must be {x.size}×{x.size}, got shape {P.shape}")
        self.x, self.P, self.t = x, P, float(t)

    def predicted(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """The prediction to time ``t`` (>= the filter's time), without changing the filter."""
        if t < self.t:
            raise ValueError(f"cannot predict backwards from t={self.t} to t={t}")
        return ekf_predict(self.motion, self.x, self.P, t - self.t)

    def predict(self, t: float) -> None:
        self.x, self.P = self.predicted(t)
        self.t = float(t)

    def update(self, model: MeasurementModel, z: np.ndarray) -> kalman.UpdateResult:
        """Update at the filter's current time; returns the Kalman step's result (ν, S, NIS, K).

        The Jacobian used is kept in ``self.H`` (a local track reports ``K·H``).
        """
        if self.iterations > 1:
            res, self.H = iterated_ekf_update(model, self.x, self.P, z, self.iterations)
        else:
            res, self.H = _ekf_update(model, self.x, self.P, z)
        self.x, self.P, self._K = self._bounded(res.x, res.P), res.P, res.K
        return res

    def _bounded(self, x: np.ndarray, P: np.ndarray) -> np.ndarray:
        return x if self.max_climb is None else climb_projected(x, P, self.max_climb)

    def innovations(self, model: MeasurementModel, Z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The plots' innovations against the filter's state and their covariance ``S``
        (:func:`ekf_innovations`), without changing the filter."""
        return ekf_innovations(model, self.x, self.P, Z)[:2]

    def update_weighted(self, model: MeasurementModel, Z: np.ndarray, beta, beta0: float) -> WeightedUpdate:
        """The weighted (PDA) update at the filter's current time with the plots ``Z`` of
        one scan, ``beta`` each and ``beta0`` for none (:mod:`fusion.pda`); linearised
        once at the prediction, whatever ``iterations``. ``K·H`` is then the gain of the
        combined innovation."""
        res, self.H = ekf_update_weighted(model, self.x, self.P, Z, beta, beta0)
        self.x, self.P, self._K = self._bounded(res.x, res.P), res.P, res.K
        return res

    @property
    def KH(self) -> np.ndarray:
        """``K·H`` of the last update (what a local track reports to the fusion rules)."""
        return self._K @ self.H
