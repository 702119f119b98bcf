r"""Traffic: aircraft entering and leaving a box at random, endlessly, generated lazily.

A ``[traffic]`` table (:class:`sensors_sim.spec.TrafficSpec`) describes a population, not
a list of targets. Births form a Poisson process of rate λ: the gaps are exponential,
``Δ ~ Exp(λ)``. Each aircraft enters the box ``[x₀, x₁] × [y₀, y₁]`` at a point uniform
on one of its four edges (each edge with probability ¼), flies a straight line at
constant speed ``v ~ U(v_lo, v_hi)`` and altitude ``h ~ U(h_lo, h_hi)`` to a point uniform
on the opposite edge, and leaves there: alive on ``[t₀, t₁)``, ``t₁ = t₀ + L/v`` with L the
line's length, so every lifetime is at most ``L_max = √(W² + H²)/v_lo``.

The process starts at ``−L_max``, not 0: at t = 0 the sky already holds the stationary
population (mean λ·E[L/v] aircraft) instead of filling up. A birth while
``max_alive`` aircraft fly is dropped (counted in ``dropped``), so at most ``max_alive``
exist at any time. Every birth draws exactly six numbers (the gap and five uniforms)
from ``process_rng(seed, "traffic", run)``, whether it is kept or not, so the whole
population is a deterministic function of (seed, run) and the same in every process.

:class:`Traffic` is a cursor over time: :meth:`Traffic.alive` answers for
non-decreasing times, keeping only the aircraft alive at the last time asked (at most
``max_alive``) and the next birth; asking for an earlier time replays from the start.
Memory is bounded whatever the run's length; a day at λ = 4/min is ~5,800 births.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from .noise import process_rng
from .spec import TrafficSpec

TRAFFIC_PROCESS = "traffic"  # the name its random stream is derived from


class Aircraft(NamedTuple):
    """One crossing: alive on ``[t0, t1)``, at ``p0 + v·(t − t0)``."""

    id: str
    t0: float
    t1: float
    p0: np.ndarray
    v: np.ndarray

    def state(self, t: float) -> np.ndarray:
        """``[p, v, a]`` (9,) at ``t`` (straight and level: a = 0)."""
        return np.concatenate([self.p0 + self.v * (t - self.t0), self.v, np.zeros(3)])

    def position(self, t: float) -> np.ndarray:
        return self.p0 + self.v * (t - self.t0)


def longest_life(spec: TrafficSpec) -> float:
    """``L_max``: the box's diagonal at the lowest speed (s)."""
    x0, x1, y0, y1 = spec.box
    return math.hypot(x1 - x0, y1 - y0) / spec.speed[0]


def crossing(spec: TrafficSpec, index: int, t0: float, u: np.ndarray) -> Aircraft:
    """The aircraft born ``index``-th at ``t0`` from five uniforms ``u``."""
    x0, x1, y0, y1 = spec.box
    edge = min(int(u[0] * 4), 3)  # 0 west, 1 east, 2 south, 3 north: enters there
    a, b = u[1], u[2]  # fractions along the entry and exit edges
    if edge < 2:
        ya, yb = y0 + a * (y1 - y0), y0 + b * (y1 - y0)
        entry, exit_ = ((x0, ya), (x1, yb)) if edge == 0 else ((x1, ya), (x0, yb))
    else:
        xa, xb = x0 + a * (x1 - x0), x0 + b * (x1 - x0)
        entry, exit_ = ((xa, y0), (xb, y1)) if edge == 2 else ((xa, y1), (xb, y0))
    speed = spec.speed[0] + u[3] * (spec.speed[1] - spec.speed[0])
    alt = spec.alt[0] + u[4] * (spec.alt[1] - spec.alt[0])
    d = np.array([exit_[0] - entry[0], exit_[1] - entry[1]])
    length = float(np.hypot(*d))
    v = np.array([*(d / length * speed), 0.0])
    return Aircraft(f"A{index:05d}", t0, t0 + length / speed, np.array([entry[0], entry[1], alt]), v)


class Traffic:
    """The aircraft of one run, lazily, as time goes on (module docstring).

    Args:
        spec: the ``[traffic]`` table.
        seed, run: the scenario's seed and the Monte Carlo run (0: distributed run).

    Attributes:
        births, dropped: births drawn so far, and those dropped for ``max_alive``.
    """

    def __init__(self, spec: TrafficSpec, seed: int, run: int = 0):
        self.spec, self._seed, self._run = spec, seed, run
        self._reset()

    def _reset(self) -> None:
        self._rng = process_rng(self._seed, TRAFFIC_PROCESS, self._run)
        self._alive: list[Aircraft] = []
        self._t = -math.inf
        self.births = self.dropped = 0
        self._next = -longest_life(self.spec) + self._gap()

    def _gap(self) -> float:
        return float(self._rng.exponential(1.0 / self.spec.rate))

    def alive(self, t: float) -> list[Aircraft]:
        """The aircraft alive at ``t`` (``t0 <= t < t1``), in birth order."""
        if t < self._t:
            self._reset()
        self._t = t
        while self._next <= t:
            born, u = self._next, self._rng.random(5)
            self._next = born + self._gap()
            self._alive = [a for a in self._alive if a.t1 > born]
            if len(self._alive) < self.spec.max_alive:
                self._alive.append(crossing(self.spec, self.births, born, u))
            else:
                self.dropped += 1
            self.births += 1
        self._alive = [a for a in self._alive if a.t1 > t]
        return list(self._alive)
