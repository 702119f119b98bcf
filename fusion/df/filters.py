r"""Bearing filters for a static emitter: EKFT, EKFS, SKF and the cross-fed MEKF.

All three filters of the thesis (document 000) run the same Kalman step — predict with
``Φ = I``, ``+Q``, then a scalar update through :func:`fusion.kalman.update` (Joseph
form) — and differ *only* in how the innovation ``ν`` and the row ``H`` are formed.
Write ``Δx = x̂_e − x_k``, ``Δy = ŷ_e − y_k``, ``r² = Δx² + Δy²``, ``u = Δy/Δx`` and
``h = atan2(Δy, Δx)`` (the predicted bearing)::

    EKFT (linearises the bearing)   ν = wrap(β − h)    H = [−Δy, Δx] / r²
    EKFS (linearises the slope u)   ν = wrap(β − h)    H = [(−u/Δx)/x̂_e, (1/Δx)/ŷ_e]
    SKF  (pseudo-linear)            ν = wrap(β − h)    H = [0.5·h/x̂_e, 0.5·h/ŷ_e]

EKFT is the proper EKF (the source documents' ``[−u/((1+u²)Δx), 1/((1+u²)Δx)]`` multiplied out,
which removes its singularity at ``Δx = 0``). EKFS and SKF are implemented *as printed*
in the thesis; they are not derived and are not invariant:

* EKFS divides by the *absolute* state coordinates, and ``(1/Δx)/ŷ_e`` has units of
  1/length², so it depends on the frame origin and on the length unit. The thesis
  works in km with the origin at DF1; we evaluate its ``H`` in that unit
  (``unit = 1000`` m) and convert the row to per-metre, so it behaves as printed.
* SKF satisfies ``H·x̂ = h`` (that is what makes it "pseudo-linear"); it is unit
  invariant but depends on the origin.
* Unlike the printed code (``atan``, mod π) every ``h`` here is the full ``atan2``
  bearing and every ``ν`` is wrapped to (−π, π].

Singularities: EKFS needs ``Δx ≠ 0``, ``x̂_e ≠ 0``, ``ŷ_e ≠ 0``; SKF needs ``x̂_e ≠ 0``,
``ŷ_e ≠ 0``. There the linearisation raises :class:`SingularLinearisation` (a
ValueError). :class:`BearingEKF` then falls back, *for that one update*, to the EKFT
row (the well-defined one), and counts it in ``n_fallbacks`` — documented, never silent.

MEKF (Chui–Chen's parallel scheme as the thesis applies it): two filters A1, A2 start
from the same state and both process every bearing; after each update A1's next prior
is A2's output and A2's next prior is A1's output; the reported estimate is A1's
output. **[decision]** covariances are swapped together with the states
(``handoff="swap"``). ``handoff="printed"`` reproduces the printed listing, whose typo
(``PK1PK1 = Pkk``) leaves A2's prior covariance at the initial ``P₀`` for ever.
Consequence of the swap: a pair of identical filters (MEKF#3 = EKFT/EKFT, #4 =
EKFS/EKFS) is *exactly* the single filter, since both halves see the same prior.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from ..angles import wrap_pi
from ..kalman import UpdateResult, predict, update
from .models import bearing, bearing_jacobian

_I2 = np.eye(2)
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
                 Q: np.ndarray, linearisation: str = "EKFT") -> UpdateResult:
    """One thesis step for one bearing: predict (``Φ = I``, ``+Q``), then update.

    Raises :class:`SingularLinearisation` where EKFS/SKF are undefined.
    """
    xp, Pp = predict(x, P, _I2, Q)
    nu, H = LINEARISATIONS[linearisation](xp, site, beta)
    return update(xp, Pp, np.array([nu]), H[None, :], np.array([[sigma * sigma]]))


class BearingEKF:
    """One bearing filter (EKFT, EKFS or SKF) on a static emitter.

    Attributes:
        x, P: current estimate ``[px, py]`` (m) and its covariance (m²).
        linearisation: ``"EKFT"``, ``"EKFS"`` or ``"SKF"``.
        n_fallbacks: updates where EKFS/SKF were singular and EKFT's row was used.
    """

    def __init__(self, x0: np.ndarray, P0: np.ndarray, Q: np.ndarray, linearisation: str = "EKFT"):
        if linearisation not in LINEARISATIONS:
            raise ValueError(f"unknown linearisation {linearisation!r}; expected one of {sorted(LINEARISATIONS)}")
        self.x = np.asarray(x0, dtype=float).copy()
        self.P = np.asarray(P0, dtype=float).copy()
        self.Q = np.asarray(Q, dtype=float)
        self.linearisation = linearisation
        self.n_fallbacks = 0

    def run(self, x: np.ndarray, P: np.ndarray, site: np.ndarray, beta: float, sigma: float) -> UpdateResult:
        """The step from a given prior (used by the cross-fed and IMM schemes)."""
        try:
            return bearing_step(x, P, site, beta, sigma, self.Q, self.linearisation)
        except SingularLinearisation:
            self.n_fallbacks += 1
            return bearing_step(x, P, site, beta, sigma, self.Q, "EKFT")

    def step(self, site: np.ndarray, beta: float, sigma: float) -> UpdateResult:
        res = self.run(self.x, self.P, site, beta, sigma)
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
    states (``"swap"``) or A2's stays at ``P0`` as in the printed listing."""

    def __init__(self, variant: int, x0: np.ndarray, P0: np.ndarray, Q: np.ndarray, handoff: str = "swap"):
        if variant not in MEKF_VARIANTS:
            raise ValueError(f"unknown MEKF variant {variant!r}; expected one of {sorted(MEKF_VARIANTS)}")
        self.variant = variant
        self.a1 = BearingEKF(x0, P0, Q, MEKF_VARIANTS[variant][0])
        self.a2 = BearingEKF(x0, P0, Q, MEKF_VARIANTS[variant][1])
        super().__init__(self.a1.run, self.a2.run, x0, P0, handoff)

    @property
    def n_fallbacks(self) -> int:
        return self.a1.n_fallbacks + self.a2.n_fallbacks
