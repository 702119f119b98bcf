r"""Bearing filters: EKFT, EKFS, SKF and the cross-fed MEKF.

The three filters of the MEKF thesis (document 000) run the same Kalman step — predict
with the emitter model's ``(F, Q) = model.transition(dt)`` (:mod:`fusion.df.models`:
the theses' ``Φ = I``, ``+Q`` per bearing, or constant velocity), then a scalar
Joseph-form update (:func:`fusion.kalman.update`) — and differ only in the row ``H``,
a function of the predicted position alone; on a constant-velocity state its velocity
entries are zero (``H = [h_p, 0, 0]``). With ``Δx = x̂_e − x_k``, ``Δy = ŷ_e − y_k``,
``r² = Δx² + Δy²``, ``u = Δy/Δx`` and ``h = atan2(Δy, Δx)``::

    EKFT (linearises the bearing)   ν = wrap(β − h)    H = [−Δy, Δx] / r²
    EKFS (linearises the slope u)   ν = wrap(β − h)    H = [(−u/Δx)/x̂_e, (1/Δx)/ŷ_e]
    SKF  (pseudo-linear)            ν = wrap(β − h)    H = [0.5·h/x̂_e, 0.5·h/ŷ_e]

EKFT is the proper EKF. EKFS and SKF are implemented as printed: not derived, and
dependent on the frame origin (EKFS also on the length unit, so its row is evaluated in
km, as in the thesis, and converted). Where EKFS or SKF is singular (``Δx``, ``x̂_e`` or
``ŷ_e`` zero) the linearisation raises :class:`SingularLinearisation` and
:class:`BearingEKF` uses the EKFT row for that update, counted in ``n_fallbacks``.

:class:`MEKF`: two filters A1, A2 from the same state both process every bearing, each
taking the other's output as its next prior; A1's output is reported. With
``handoff="swap"`` covariances swap with the states, so MEKF#3 (EKFT/EKFT) and #4
(EKFS/EKFS) equal the single filter; ``"printed"`` keeps the listing's A2 covariance at
``P₀``. docs/algorithms.md ("EKFT, EKFS, SKF", "MEKF") has the decisions.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from ..angles import wrap_pi
from ..kalman import UpdateResult, predict, update
from .models import EmitterModel, bearing, bearing_jacobian, emitter_model

#: |divisor| below this fraction of the geometry's scale counts as singular.
_SINGULAR_REL = 1e-9
#: The thesis's length unit (km), in which EKFS's H is evaluated "as printed".
THESIS_UNIT = 1000.0


class SingularLinearisation(ValueError):
    """EKFS/SKF's printed ``H`` divides by a (near) zero ``Δx``, ``x̂_e`` or ``ŷ_e``."""


def _check_divisors(name: str, scale: float, **divisors: float) -> None:
    for what, v in divisors.items():
        if abs(v) <= _SINGULAR_REL * scale:
            raise SingularLinearisation(
                f"{name}: H divides by {what} = {v:.3g} m (singular at this geometry); use EKFT")


def lin_ekft(x: np.ndarray, site: np.ndarray, beta: float) -> tuple[float, np.ndarray]:
    """EKFT: ``ν = wrap(β − h(x))``, ``H = ∂h/∂x = [−Δy, Δx]/r²``."""
    return wrap_pi(beta - bearing(x, site)), bearing_jacobian(x, site)


def lin_ekfs(x: np.ndarray, site: np.ndarray, beta: float, unit: float = THESIS_UNIT) -> tuple[float, np.ndarray]:
    """EKFS as printed: ``H = [(−u/Δx)/x̂_e, (1/Δx)/ŷ_e]`` evaluated in ``unit`` (km)."""
    dx, dy = x[0] - site[0], x[1] - site[1]
    scale = float(np.hypot(dx, dy) + np.hypot(x[0], x[1]))
    _check_divisors("EKFS", scale, **{"Δx": dx, "x̂_e": x[0], "ŷ_e": x[1]})
    u = dy / dx
    dxk, xk, yk = dx / unit, x[0] / unit, x[1] / unit
    H = np.array([(-u / dxk) / xk, (1.0 / dxk) / yk]) / unit  # per km → per metre
    return wrap_pi(beta - bearing(x, site)), H


def lin_skf(x: np.ndarray, site: np.ndarray, beta: float) -> tuple[float, np.ndarray]:
    """SKF as printed: ``H = [0.5·h/x̂_e, 0.5·h/ŷ_e]`` so that ``H·x̂ = h``."""
    h = bearing(x, site)
    scale = float(np.hypot(x[0] - site[0], x[1] - site[1]) + np.hypot(x[0], x[1]))
    _check_divisors("SKF", scale, **{"x̂_e": x[0], "ŷ_e": x[1]})
    return wrap_pi(beta - h), np.array([0.5 * h / x[0], 0.5 * h / x[1]])


Linearisation = Callable[[np.ndarray, np.ndarray, float], tuple[float, np.ndarray]]
LINEARISATIONS: dict[str, Linearisation] = {"EKFT": lin_ekft, "EKFS": lin_ekfs, "SKF": lin_skf}


def bearing_step(x: np.ndarray, P: np.ndarray, site: np.ndarray, beta: float, sigma: float,
                 model, linearisation: str = "EKFT", dt: float = 0.0) -> UpdateResult:
    """One step for one bearing: predict over ``dt`` with ``model`` (an emitter model,
    or a 2×2 ``Q``: the static emitter), then update with the row of ``linearisation``.

    Raises :class:`SingularLinearisation` where EKFS/SKF are undefined.
    """
    F, Q = emitter_model(model).transition(dt)
    xp, Pp = predict(x, P, F, Q)
    nu, Hp = LINEARISATIONS[linearisation](xp, site, beta)
    H = np.zeros((1, xp.size))
    H[0, :2] = Hp
    return update(xp, Pp, np.array([nu]), H, np.array([[sigma * sigma]]))


class BearingEKF:
    """One bearing filter (EKFT, EKFS or SKF) on an emitter model.

    Args:
        model: a :mod:`fusion.df.models` emitter model, or a 2×2 ``Q`` (static emitter).
    Attributes:
        x, P: current estimate (``[px, py]``, or ``[px, py, vx, vy]`` with constant
            velocity; m, m/s) and its covariance.
        linearisation: ``"EKFT"``, ``"EKFS"`` or ``"SKF"``.
        n_fallbacks: updates where EKFS/SKF were singular and EKFT's row was used.
    """

    def __init__(self, x0: np.ndarray, P0: np.ndarray, model, linearisation: str = "EKFT"):
        if linearisation not in LINEARISATIONS:
            raise ValueError(f"unknown linearisation {linearisation!r}; expected one of {sorted(LINEARISATIONS)}")
        self.model: EmitterModel = emitter_model(model)
        self.x = np.asarray(x0, dtype=float).copy()
        self.P = np.asarray(P0, dtype=float).copy()
        if self.x.shape != (self.model.n_x,) or self.P.shape != (self.model.n_x,) * 2:
            raise ValueError(f"BearingEKF: the {self.model.name} model has {self.model.n_x} states; "
                             f"x0 {self.x.shape}, P0 {self.P.shape}")
        self.linearisation = linearisation
        self.n_fallbacks = 0

    def run(self, x: np.ndarray, P: np.ndarray, site: np.ndarray, beta: float, sigma: float,
            dt: float = 0.0) -> UpdateResult:
        """The step from a given prior ``dt`` seconds before the bearing (used by the
        cross-fed and IMM schemes)."""
        try:
            return bearing_step(x, P, site, beta, sigma, self.model, self.linearisation, dt)
        except SingularLinearisation:
            self.n_fallbacks += 1
            return bearing_step(x, P, site, beta, sigma, self.model, "EKFT", dt)

    def step(self, site: np.ndarray, beta: float, sigma: float, dt: float = 0.0) -> UpdateResult:
        res = self.run(self.x, self.P, site, beta, sigma, dt)
        self.x, self.P = res.x, res.P
        return res


class CrossFed:
    """Two filters run in parallel and cross-fed: the (M)EKF/MKF scheme of the thesis.

    ``f1`` and ``f2`` map ``(x, P, *inputs) -> UpdateResult`` (the prior is passed in,
    so the same class serves the 2-D MEKF and the scalar MKF bearing smoother)::

        r1 = f1(x1, P1, z);  r2 = f2(x2, P2, z)
        swap:    (x1, P1) ← (r2.x, r2.P);   (x2, P2) ← (r1.x, r1.P)
        printed: (x1, P1) ← (r2.x, r2.P);   x2 ← r1.x, P2 stays P₀
        reported: r1 (A1's output)
    """

    HANDOFFS = ("swap", "printed")

    def __init__(self, f1: Callable[..., UpdateResult], f2: Callable[..., UpdateResult],
                 x0: np.ndarray, P0: np.ndarray, handoff: str = "swap"):
        if handoff not in self.HANDOFFS:
            raise ValueError(f"unknown MEKF handoff {handoff!r}; expected one of {self.HANDOFFS}")
        self.f1, self.f2, self.handoff = f1, f2, handoff
        self.x = np.asarray(x0, dtype=float).copy()
        self.P = np.asarray(P0, dtype=float).copy()
        self._x1, self._P1 = self.x, self.P
        self._x2, self._P2 = self.x, self.P

    def step(self, *inputs) -> UpdateResult:
        r1 = self.f1(self._x1, self._P1, *inputs)
        r2 = self.f2(self._x2, self._P2, *inputs)
        self._x1, self._P1 = r2.x, r2.P
        self._x2 = r1.x
        if self.handoff == "swap":
            self._P2 = r1.P
        self.x, self.P = r1.x, r1.P
        return r1


#: MEKF variants (A1, A2) of the thesis.
MEKF_VARIANTS: dict[int, tuple[str, str]] = {
    1: ("EKFT", "SKF"),
    2: ("EKFT", "EKFS"),
    3: ("EKFT", "EKFT"),
    4: ("EKFS", "EKFS"),
    5: ("EKFS", "EKFT"),
}


class MEKF(CrossFed):
    """Modified EKF #1..#5: two bearing filters A1, A2 (``MEKF_VARIANTS[variant]``) that
    both process every bearing, each starting its next update from the other's output;
    the estimate reported is A1's. ``handoff`` says whether covariances swap with the
    states (``"swap"``) or A2's stays at ``P0`` as in the printed listing. ``step(site,
    β, σ, dt)``: both filters predict over the same ``dt`` from their own priors."""

    def __init__(self, variant: int, x0: np.ndarray, P0: np.ndarray, model, handoff: str = "swap"):
        if variant not in MEKF_VARIANTS:
            raise ValueError(f"unknown MEKF variant {variant!r}; expected one of {sorted(MEKF_VARIANTS)}")
        self.variant = variant
        self.a1 = BearingEKF(x0, P0, model, MEKF_VARIANTS[variant][0])
        self.a2 = BearingEKF(x0, P0, model, MEKF_VARIANTS[variant][1])
        super().__init__(self.a1.run, self.a2.run, x0, P0, handoff)

    @property
    def n_fallbacks(self) -> int:
        return self.a1.n_fallbacks + self.a2.n_fallbacks
