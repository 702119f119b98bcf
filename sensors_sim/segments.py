r"""Motion segments: how a target flies from the state the previous segment ended in.

A target (:class:`sensors_sim.spec.TargetSpec`) is an initial state ``x0 = [p, v, a]``
(ENU, 9 states) and a tuple of these segments, flown one after another by
:mod:`sensors_sim.trajectories`; each plans its :class:`Piece` from its start state:

* ``Static``: ``p(τ) = p₀``, ``v = a = 0`` (emitters);
* ``ConstantVelocity``: ``p(τ) = p₀ + v τ``, ``a = 0``;
* ``ConstantAcceleration``: ``p(τ) = p₀ + v₀ τ + a τ²/2``, ``v(τ) = v₀ + a τ``;
* ``CoordinatedTurn``: constant speed, turn rate ω (> 0 turns right) and climb rate;
  with Ω = −ω, ``v_h(τ) = Rot(Ωτ) v_h₀``,
  ``p_h(τ) = p_h₀ + [sin Ωτ, −(1 − cos Ωτ); 1 − cos Ωτ, sin Ωτ] v_h₀ / Ω``;
* ``Waypoints``: straight legs at constant speed through the given points;
* ``Orbit``: an endless elliptical racetrack at constant altitude, entered mid-way
  along a long side: e₁ the compass heading of the long axis, n the unit vector to the
  centre c = p₀ + b·n, Ω = 2π/T (T the lap), ``p = c + a sin Ωτ e₁ − b cos Ωτ n``,
  ``v = Ω(a cos Ωτ e₁ + b sin Ωτ n)``, ``a = −Ω²(p − c)``: closed form, C^∞, periodic.

A leaf module (numpy only), so the scenario's specification can name its segments
without the trajectories that fly them.
"""

from __future__ import annotations

import math
from bisect import bisect_right
from dataclasses import dataclass
from typing import Callable, NamedTuple

import numpy as np

class Piece(NamedTuple):
    """A segment planned from its start state: duration (None: open-ended) and the
    state at local time τ ≥ 0."""

    duration: float | None
    state: Callable[[float], np.ndarray]


def _state(p, v, a) -> np.ndarray:
    return np.concatenate([p, v, a]).astype(float)


_ZERO3 = np.zeros(3)


@dataclass(frozen=True)
class Static:
    duration: float | None = None

    def plan(self, x: np.ndarray) -> Piece:
        x0 = _state(x[:3], _ZERO3, _ZERO3)
        return Piece(self.duration, lambda tau: x0.copy())


@dataclass(frozen=True)
class ConstantVelocity:
    duration: float | None = None
    vel: np.ndarray | None = None

    def plan(self, x: np.ndarray) -> Piece:
        p0 = x[:3].copy()
        v = x[3:6].copy() if self.vel is None else np.asarray(self.vel, dtype=float)
        return Piece(self.duration, lambda tau: _state(p0 + v * tau, v, _ZERO3))


@dataclass(frozen=True)
class ConstantAcceleration:
    duration: float | None = None
    acc: np.ndarray | None = None

    def plan(self, x: np.ndarray) -> Piece:
        p0, v0 = x[:3].copy(), x[3:6].copy()
        a = x[6:9].copy() if self.acc is None else np.asarray(self.acc, dtype=float)
        return Piece(self.duration, lambda tau: _state(p0 + v0 * tau + 0.5 * a * tau * tau, v0 + a * tau, a))


@dataclass(frozen=True)
class CoordinatedTurn:
    rate: float  # rad/s, > 0 turns right (clockwise seen from above)
    duration: float | None = None

    def plan(self, x: np.ndarray) -> Piece:
        p0, v0 = x[:3].copy(), x[3:6].copy()
        om = -self.rate  # counter-clockwise rate in the ENU (math) plane

        def state(tau: float) -> np.ndarray:
            c, s = math.cos(om * tau), math.sin(om * tau)
            vx, vy = v0[0], v0[1]
            v = np.array([c * vx - s * vy, s * vx + c * vy, v0[2]])
            dp = np.array([(s * vx - (1.0 - c) * vy) / om, ((1.0 - c) * vx + s * vy) / om, v0[2] * tau])
            a = np.array([-om * v[1], om * v[0], 0.0])
            return _state(p0 + dp, v, a)

        return Piece(self.duration, state)


@dataclass(frozen=True, eq=False)
class Waypoints:
    points: np.ndarray  # (n, 3) ENU
    speed: float  # m/s

    def plan(self, x: np.ndarray) -> Piece:
        p = np.vstack([x[:3], self.points])
        legs = np.diff(p, axis=0)
        lengths = np.linalg.norm(legs, axis=1)
        keep = lengths > 0.0  # a repeated point is a leg of zero length: skip it
        starts, legs, lengths = p[:-1][keep], legs[keep], lengths[keep]
        if len(lengths) == 0:  # already at the only point: hold still
            return Static().plan(x)
        vels = legs / lengths[:, None] * self.speed
        t_leg = np.concatenate([[0.0], np.cumsum(lengths / self.speed)])

        def state(tau: float) -> np.ndarray:
            i = min(bisect_right(t_leg, tau) - 1, len(vels) - 1)  # past the end: fly on
            return _state(starts[i] + vels[i] * (tau - t_leg[i]), vels[i], _ZERO3)

        return Piece(float(t_leg[-1]), state)


@dataclass(frozen=True)
class Orbit:
    """An endless elliptical racetrack (module docstring): semi-axes ``a`` along the
    heading ``heading`` (compass, rad) and ``b`` across it, ``lap`` seconds a lap,
    turning ``left`` (counter-clockwise seen from above) or right."""

    a: float
    b: float
    lap: float
    heading: float
    left: bool = True
    duration: float | None = None

    def plan(self, x: np.ndarray) -> Piece:
        e1 = np.array([math.sin(self.heading), math.cos(self.heading), 0.0])
        n = np.array([-e1[1], e1[0], 0.0]) if self.left else np.array([e1[1], -e1[0], 0.0])
        om = 2.0 * math.pi / self.lap
        c = x[:3] + self.b * n

        def state(tau: float) -> np.ndarray:
            s, co = math.sin(om * tau), math.cos(om * tau)
            d = self.a * s * e1 - self.b * co * n  # p − c
            return _state(c + d, om * (self.a * co * e1 + self.b * s * n), -om * om * d)

        return Piece(self.duration, state)


Segment = Static | ConstantVelocity | ConstantAcceleration | CoordinatedTurn | Waypoints | Orbit
