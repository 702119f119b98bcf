r"""Traffic: aircraft entering and leaving a box at random, endlessly, generated lazily.

A ``[traffic]`` table (:class:`sensors_sim.spec.TrafficSpec`) describes a population, not
a list of targets. Births form a Poisson process of rate λ: the gaps are exponential,
``Δ ~ Exp(λ)``. Each aircraft enters the box ``[x₀, x₁] × [y₀, y₁]`` at a point uniform
on one of its four edges (each edge with probability ¼) and leaves at a point uniform on
the opposite edge, at constant ground speed ``v ~ U(v_lo, v_hi)`` from the altitude
``h ~ U(h_lo, h_hi)``. By default it flies the straight line, level: alive on
``[t₀, t₁)``, ``t₁ = t₀ + L/v``, L the line's length.

Manoeuvres (optional keys): ``waypoints`` N puts N points on the line at fractions
``i/(N+1)``, each moved across it by ``U(−o, o)``; the aircraft flies the polyline with a
fly-by turn at each point, at a rate ``ω ~ U(ω_lo, ω_hi)`` (turning by Δ it starts
``D = R·tan(|Δ|/2)`` before the point, ``R = v/ω``; ``D`` is capped at 0.45 of the
shorter neighbouring leg by turning faster), so its path is lines and circular arcs:
on an arc from heading ψ₀ (compass) at ``p₀``, ``p(τ) = p₀ + (v/ω)·(cos ψ₀ − cos ψ,
sin ψ − sin ψ₀)``, ``ψ = ψ₀ + ωτ`` (``ω > 0`` turns right), ``a = vω·(cos ψ, −sin ψ)``.
``level_changes`` K cuts the life into K equal slices; in slice j the aircraft starts,
at a uniform time of the slice's first half, a climb or descent at ``U(r_lo, r_hi)`` m/s
to a new level ``U(h_lo, h_hi)`` (stopped at the slice's end if not reached).

The process starts one longest life before 0 (``(√(w² + h²) + 2·N·o)/v_lo`` bounds every
life, ``w × h`` the box), not at 0: at t = 0 the sky already holds the stationary population. A birth while
``max_alive`` aircraft fly is dropped (counted in ``dropped``). Every birth draws the gap
and ``5 + 2N + 3K`` uniforms from ``process_rng(seed, "traffic", run)``, kept or not, so
the population is a deterministic function of (seed, run) and the same in every process
(N = K = 0: six draws a birth, the straight crossings of the first version).

:class:`Traffic` is a cursor over time: :meth:`Traffic.fleet` answers for
non-decreasing times with the alive aircraft as arrays (:class:`Fleet`, evaluated for all
of them at once), :meth:`Traffic.alive` as :class:`Aircraft` objects; asking for an
earlier time replays from the start. It keeps the alive aircraft (at most
``max_alive``), a heap of their ends and the births drawn ahead, so memory is bounded
whatever the run's length.
"""

from __future__ import annotations

import heapq
import math
from dataclasses import dataclass

import numpy as np

from fusion.angles import wrap_pi

from .noise import process_rng
from .spec import TrafficSpec

TRAFFIC_PROCESS = "traffic"  # the name its random stream is derived from
_CHUNK = 256  # births drawn and planned at once
_CAP = 0.45  # a turn's lead distance D is at most this fraction of its shorter leg


@dataclass(frozen=True, eq=False)
class Fleet:
    """Aircraft as arrays, one row each (``A`` rows), in birth order.

    Horizontal path: legs ``j`` from ``leg_t[:, j]`` (absolute time), each from
    ``leg_p`` (A, L, 2) with velocity ``leg_v`` (straight legs) or from heading
    ``leg_psi`` at turn rate ``leg_w`` (arcs; 0 on straight legs). Vertical: from
    ``alt_t[:, m]`` the altitude ``alt_h[:, m] + alt_r[:, m]·(t − alt_t[:, m])``.
    """

    index: np.ndarray
    t0: np.ndarray
    t1: np.ndarray
    speed: np.ndarray
    leg_t: np.ndarray
    leg_p: np.ndarray
    leg_v: np.ndarray
    leg_psi: np.ndarray
    leg_w: np.ndarray
    alt_t: np.ndarray
    alt_h: np.ndarray
    alt_r: np.ndarray

    _ARRAYS = ("index", "t0", "t1", "speed", "leg_t", "leg_p", "leg_v", "leg_psi", "leg_w", "alt_t", "alt_h", "alt_r")

    def __len__(self) -> int:
        return len(self.index)

    @property
    def ids(self) -> list[str]:
        """``A<birth index>``, as the truth and the scores name them."""
        return [aircraft_id(i) for i in self.index]

    def take(self, rows) -> "Fleet":
        """The aircraft of ``rows`` (a boolean mask, indices or a slice), in that order."""
        return Fleet(*(getattr(self, k)[rows] for k in self._ARRAYS))

    @staticmethod
    def concat(parts: list["Fleet"]) -> "Fleet":
        return Fleet(*(np.concatenate([getattr(p, k) for p in parts]) for k in Fleet._ARRAYS))

    def kinematics(self, t, rows=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Position, velocity and acceleration (A, 3) at ``t`` (a scalar, or one time per
        aircraft), from the leg and the altitude segment each is on; ``rows``: of those
        aircraft only (indices, repeats allowed), ``t`` then one time per row."""
        rows = np.arange(len(self.t0)) if rows is None else np.asarray(rows, dtype=int)
        t = np.broadcast_to(np.asarray(t, dtype=float), rows.shape)
        j = (t[:, None] >= self.leg_t[rows, 1:]).sum(axis=1)
        tau = t - self.leg_t[rows, j]
        p0, v0 = self.leg_p[rows, j], self.leg_v[rows, j]
        w, psi0, speed = self.leg_w[rows, j], self.leg_psi[rows, j], self.speed[rows]
        turning = w != 0.0
        p = p0 + v0 * tau[:, None]  # straight legs (and, below, arcs replaced)
        v = v0.copy()
        a = np.zeros((len(t), 3))
        if turning.any():
            k = np.flatnonzero(turning)
            psi = psi0[k] + w[k] * tau[k]
            r = speed[k] / w[k]
            sin0, cos0, sin1, cos1 = np.sin(psi0[k]), np.cos(psi0[k]), np.sin(psi), np.cos(psi)
            p[k, 0] = p0[k, 0] + r * (cos0 - cos1)
            p[k, 1] = p0[k, 1] + r * (sin1 - sin0)
            v[k, 0], v[k, 1] = speed[k] * sin1, speed[k] * cos1
            a[k, 0], a[k, 1] = speed[k] * w[k] * cos1, -speed[k] * w[k] * sin1
        m = (t[:, None] >= self.alt_t[rows, 1:]).sum(axis=1)
        rate = self.alt_r[rows, m]
        z = self.alt_h[rows, m] + rate * (t - self.alt_t[rows, m])
        return np.column_stack([p, z]), np.column_stack([v, rate]), a

    def positions(self, t) -> np.ndarray:
        """(A, 3) ENU positions at ``t`` (scalar or per aircraft)."""
        return self.kinematics(t)[0]

    def states(self, t) -> np.ndarray:
        """(A, 9) states ``[p, v, a]`` at ``t``."""
        return np.concatenate(self.kinematics(t), axis=1)


def aircraft_id(index: int) -> str:
    """The id of the aircraft born ``index``-th."""
    return f"A{index:05d}"


class Aircraft:
    """One aircraft: alive on ``[t0, t1)``, entering at ``p0`` (a one-row :class:`Fleet`)."""

    __slots__ = ("id", "t0", "t1", "p0", "_fleet")

    def __init__(self, fleet: Fleet):
        self._fleet = fleet
        self.id, self.t0, self.t1 = aircraft_id(fleet.index[0]), float(fleet.t0[0]), float(fleet.t1[0])
        self.p0 = np.array([*fleet.leg_p[0, 0], fleet.alt_h[0, 0]])

    def __repr__(self) -> str:
        return f"Aircraft({self.id!r}, t0={self.t0:g}, t1={self.t1:g})"

    def state(self, t: float) -> np.ndarray:
        """``[p, v, a]`` (9,) at ``t``."""
        return self._fleet.states(t)[0]

    def position(self, t: float) -> np.ndarray:
        return self._fleet.positions(t)[0]

    def states(self, times) -> np.ndarray:
        """(N, 9) states at the N ``times``."""
        times = np.atleast_1d(np.asarray(times, dtype=float))
        return np.concatenate(self._fleet.kinematics(times, np.zeros(len(times), dtype=int)), axis=1)


def longest_life(spec: TrafficSpec) -> float:
    """A bound on every life: the box's diagonal, plus twice the waypoints' offsets, at the
    lowest speed (s)."""
    x0, x1, y0, y1 = spec.box
    return (math.hypot(x1 - x0, y1 - y0) + 2.0 * spec.waypoints * spec.waypoint_offset) / spec.speed[0]


def draws_per_birth(spec: TrafficSpec) -> int:
    """Uniforms a birth draws after its gap: five for the crossing, two per waypoint (its
    offset, its turn rate), three per level change (start, level, rate)."""
    return 5 + 2 * spec.waypoints + 3 * spec.level_changes


def plan(spec: TrafficSpec, first: int, t0: np.ndarray, u: np.ndarray) -> Fleet:
    """The aircraft born ``first``-th, ... at times ``t0`` (n,), from their uniforms ``u``
    (n, :func:`draws_per_birth`) (module docstring)."""
    n = len(t0)
    x0, x1, y0, y1 = spec.box
    edge = np.minimum((u[:, 0] * 4).astype(int), 3)  # 0 west, 1 east, 2 south, 3 north: enters there
    a, b = u[:, 1], u[:, 2]  # fractions along the entry and exit edges
    ya, yb, xa, xb = y0 + a * (y1 - y0), y0 + b * (y1 - y0), x0 + a * (x1 - x0), x0 + b * (x1 - x0)
    entry = np.select([edge[:, None] == k for k in range(4)],
                      [np.column_stack(c) for c in ((np.full(n, x0), ya), (np.full(n, x1), ya),
                                                    (xa, np.full(n, y0)), (xa, np.full(n, y1)))])
    exit_ = np.select([edge[:, None] == k for k in range(4)],
                      [np.column_stack(c) for c in ((np.full(n, x1), yb), (np.full(n, x0), yb),
                                                    (xb, np.full(n, y1)), (xb, np.full(n, y0)))])
    speed = spec.speed[0] + u[:, 3] * (spec.speed[1] - spec.speed[0])
    alt = spec.alt[0] + u[:, 4] * (spec.alt[1] - spec.alt[0])
    W, K = spec.waypoints, spec.level_changes  # (N and K of the module docstring)
    uw, ur = u[:, 5:5 + W], u[:, 5 + W:5 + 2 * W]
    uk = u[:, 5 + 2 * W:].reshape(n, K, 3)

    # the polyline: entry, the waypoints moved across the line, exit
    d = exit_ - entry
    normal = np.column_stack([-d[:, 1], d[:, 0]]) / np.hypot(d[:, 0], d[:, 1])[:, None]
    frac = np.arange(1, W + 1) / (W + 1)
    offset = (2.0 * uw - 1.0) * spec.waypoint_offset
    points = np.concatenate([entry[:, None], entry[:, None] + frac[None, :, None] * d[:, None]
                             + offset[:, :, None] * normal[:, None], exit_[:, None]], axis=1)
    seg = np.diff(points, axis=1)  # (n, W+1, 2)
    length = np.hypot(seg[..., 0], seg[..., 1])
    unit = seg / length[..., None]
    heading = np.arctan2(unit[..., 0], unit[..., 1])
    # fly-by turns at the waypoints: turn by delta at rate w, lead D = R tan(|delta|/2)
    delta = wrap_pi(heading[:, 1:] - heading[:, :-1]) if W else np.zeros((n, 0))
    w = spec.turn_rate[0] + ur * (spec.turn_rate[1] - spec.turn_rate[0])
    half = np.tan(np.abs(delta) / 2.0)
    room = _CAP * np.minimum(length[:, :-1], length[:, 1:])
    lead = np.minimum(speed[:, None] / w * half, room)
    w = np.where(half > 0, speed[:, None] * half / np.maximum(lead, 1e-300), w) * np.where(delta < 0, -1.0, 1.0)
    before = np.pad(lead, ((0, 0), (0, 1)))  # lead of the turn ending each straight leg
    after = np.pad(lead, ((0, 0), (1, 0)))  # ... and of the turn starting it
    straight_len = length - before - after

    # legs: straight 0, arc 1, straight 1, ..., straight W
    L = 2 * W + 1
    leg_p = np.empty((n, L, 2))
    leg_v = np.zeros((n, L, 2))
    leg_psi = np.zeros((n, L))
    leg_w = np.zeros((n, L))
    durations = np.empty((n, L))
    leg_p[:, 0::2] = points[:, :-1] + after[..., None] * unit
    leg_v[:, 0::2] = unit * speed[:, None, None]
    leg_psi[:, 0::2] = heading
    durations[:, 0::2] = straight_len / speed[:, None]
    if W:
        leg_p[:, 1::2] = points[:, 1:-1] - lead[..., None] * unit[:, :-1]
        leg_psi[:, 1::2] = heading[:, :-1]
        leg_w[:, 1::2] = w
        durations[:, 1::2] = np.abs(delta) / np.abs(w)
        leg_t = t0[:, None] + np.concatenate([np.zeros((n, 1)), np.cumsum(durations, axis=1)[:, :-1]], axis=1)
        t1 = t0 + durations.sum(axis=1)
    else:  # one straight line: t1 = t0 + L/v, as ever
        leg_t = t0[:, None]
        t1 = t0 + length[:, 0] / speed

    # altitude: K level changes, one per slice of the life
    alt_t = np.empty((n, 1 + 2 * K))
    alt_h = np.empty((n, 1 + 2 * K))
    alt_r = np.zeros((n, 1 + 2 * K))
    alt_t[:, 0], alt_h[:, 0] = t0, alt
    life = t1 - t0
    h = alt
    for k in range(K):
        start = t0 + life * k / K
        slice_end = t0 + life * (k + 1) / K
        ts = start + uk[:, k, 0] * 0.5 * (slice_end - start)
        target = spec.alt[0] + uk[:, k, 1] * (spec.alt[1] - spec.alt[0])
        rate = spec.climb_rate[0] + uk[:, k, 2] * (spec.climb_rate[1] - spec.climb_rate[0])
        te = np.minimum(ts + np.abs(target - h) / rate, slice_end)
        signed = np.sign(target - h) * rate
        alt_t[:, 1 + 2 * k], alt_h[:, 1 + 2 * k], alt_r[:, 1 + 2 * k] = ts, h, signed
        h = h + signed * (te - ts)
        alt_t[:, 2 + 2 * k], alt_h[:, 2 + 2 * k] = te, h
    return Fleet(np.arange(first, first + n), t0, t1, speed, leg_t, leg_p, leg_v, leg_psi, leg_w, alt_t, alt_h, alt_r)


class Traffic:
    """The aircraft of one run, lazily, as time goes on (module docstring).

    Args:
        spec: the ``[traffic]`` table.
        seed, run: the scenario's seed and the Monte Carlo run (0: distributed run).

    Attributes:
        births, dropped: births up to the latest time asked, and those dropped for
            ``max_alive``.
    """

    def __init__(self, spec: TrafficSpec, seed: int, run: int = 0):
        self.spec, self._seed, self._run = spec, seed, run
        self._reset()

    def _reset(self) -> None:
        self._rng = process_rng(self._seed, TRAFFIC_PROCESS, self._run)
        self._t = -math.inf
        self.births = self.dropped = 0
        self._next = -longest_life(self.spec) + self._gap()
        self._ahead = self._empty()  # the chunk of births drawn ahead of the time asked
        self._pos = 0  # its first birth not yet reached
        self._ends: list[float] = []  # heap: ends of the kept aircraft
        self._fleet = self._empty()
        self._objects: dict[int, Aircraft] = {}

    def _empty(self) -> Fleet:
        return plan(self.spec, 0, np.empty(0), np.empty((0, draws_per_birth(self.spec))))

    def _gap(self) -> float:
        return float(self._rng.exponential(1.0 / self.spec.rate))

    def _draw(self) -> None:
        """The next chunk of births: gaps and uniforms in the fixed order, then planned."""
        k = draws_per_birth(self.spec)
        times, u = np.empty(_CHUNK), np.empty((_CHUNK, k))
        for i in range(_CHUNK):
            times[i], u[i] = self._next, self._rng.random(k)
            self._next += self._gap()
        self._ahead = plan(self.spec, self.births, times, u)
        self._pos = 0

    def fleet(self, t: float) -> Fleet:
        """The aircraft alive at ``t`` (``t0 <= t < t1``), in birth order."""
        if t < self._t:
            self._reset()
        self._t = t
        kept = [self._fleet]
        while True:
            if self._pos == len(self._ahead):
                self._draw()
            ahead, first = self._ahead, self._pos
            n = int(np.searchsorted(ahead.t0, t, side="right"))  # born by t
            keep = []
            for i in range(first, n):
                born = ahead.t0[i]
                while self._ends and self._ends[0] <= born:
                    heapq.heappop(self._ends)
                if len(self._ends) < self.spec.max_alive:
                    heapq.heappush(self._ends, float(ahead.t1[i]))
                    keep.append(i)
                else:
                    self.dropped += 1
            self.births += max(n - first, 0)
            self._pos = max(n, first)
            if keep:
                kept.append(ahead.take(np.array(keep)))
            if self._pos < len(ahead):
                break
        fleet = Fleet.concat(kept) if len(kept) > 1 else kept[0]
        if (fleet.t1 <= t).any():
            fleet = fleet.take(fleet.t1 > t)
        self._fleet = fleet
        return fleet

    def alive(self, t: float) -> list[Aircraft]:
        """The aircraft alive at ``t`` as objects, in birth order."""
        fleet = self.fleet(t)
        objects = {}
        for i, index in enumerate(fleet.index.tolist()):
            objects[index] = self._objects.get(index) or Aircraft(fleet.take([i]))
        self._objects = objects
        return list(objects.values())


def population(scenario, run: int = 0):
    """The cursor over the scenario's aircraft beyond its listed targets, for one run: a
    ``[traffic]`` stream's (:class:`Traffic`), a recording's (``[truth] file``: it is its
    own, :class:`sensors_sim.recorded.RecordedTraffic`), or None. Either answers
    ``fleet(t)`` with a fleet of the aircraft alive at ``t``, ``fleet.ids`` their names."""
    spec = scenario.traffic
    if spec is None:
        return None
    return Traffic(spec, scenario.seed, run) if isinstance(spec, TrafficSpec) else spec
