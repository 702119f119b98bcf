r"""Ground truth: targets moving along motion segments, plus optional white-noise jerk.

A target starts from ``x0 = [p, v, a]`` (ENU, 9 states) and flies its segments
(:mod:`sensors_sim.segments`) one after another, each from the state the previous one
ended in; the last runs on past its duration.

Process noise: with ``jerk_psd`` q > 0 the truth is ``x(t) = x_nom(t) + e(t)``, ``e`` the
white-noise-jerk process of :mod:`sensors_sim.noise` from ``e(0) = 0`` on the grid
``t_k = k·truth_dt``; ``q·Q₁(dt)`` is its exact discretisation, so a sensor sampling on
the grid sees exactly the CA model with white jerk at its own period (the loader
requires every scan to fall on the grid; between nodes ``e(t) = F(t − t_k) e_k``). The
noise comes from ``process_rng(seed, "truth", run)``, targets drawing in file order, so
the truth is a deterministic function of (scenario, run) that every process computes
alike.
"""

from __future__ import annotations

import math
from bisect import bisect_right
from functools import lru_cache
from typing import Iterator, NamedTuple

import numpy as np

from fusion.motion import ConstantAcceleration as _CA

from .noise import jerk_deviation, process_rng
from .segments import Piece
from .spec import TRUTH_PROCESS, Scenario, TargetSpec
from .traffic import population

_CA_TRANSITION = _CA(0.0)  # only its F₁(τ) is used, to carry the deviation between nodes
# Relative tolerance for "this time is on that grid node" (float round-off of k·dt).
_TIME_TOL = 1e-9


def sample_times(start: float, period: float, end: float) -> np.ndarray:
    """``start + k·period`` for k = 0, 1, ... up to and including ``end`` (round-off
    tolerant). Computed by multiplication, so there is no drift over long runs."""
    if period <= 0:
        raise ValueError(f"period must be > 0, got {period}")
    if start > end * (1 + _TIME_TOL) + _TIME_TOL:
        return np.empty(0)
    n = math.floor((end - start) / period + _TIME_TOL) + 1
    return start + period * np.arange(n)


def iter_times(start: float, period: float, end: float) -> Iterator[float]:
    """:func:`sample_times` lazily, as floats (the same values); ``end`` may be infinite."""
    if period <= 0:
        raise ValueError(f"period must be > 0, got {period}")
    if start > end * (1 + _TIME_TOL) + _TIME_TOL:
        return
    n = math.inf if math.isinf(end) else math.floor((end - start) / period + _TIME_TOL) + 1
    k = 0
    while k < n:
        yield float(start + period * k)
        k += 1


# --- trajectories -----------------------------------------------------------------------


class Trajectory:
    """The true state of one target at any scenario time ``t ≥ 0``.

    Args:
        target: the target's spec.
        deviation: (N+1, 9) process-noise deviation on the grid ``k·dt``, or None.
        dt: the grid step (needed with ``deviation``).
    """

    def __init__(self, target: TargetSpec, deviation: np.ndarray | None = None, dt: float | None = None):
        if deviation is not None and not (dt and dt > 0):
            raise ValueError("a process-noise deviation needs its grid step dt > 0")
        self.target = target.id
        self._deviation = deviation
        self._dt = dt
        self._starts: list[float] = []
        self._pieces: list[Piece] = []
        x, t = np.asarray(target.x0, dtype=float), 0.0
        for seg in target.segments:
            piece = seg.plan(x)
            self._starts.append(t)
            self._pieces.append(piece)
            if piece.duration is None:  # open-ended: nothing after it can start
                break
            x, t = piece.state(piece.duration), t + piece.duration

    def nominal(self, t: float) -> np.ndarray:
        """The deterministic (segment) part of the state."""
        i = bisect_right(self._starts, t) - 1
        return self._pieces[i].state(t - self._starts[i])

    def deviation(self, t: float) -> np.ndarray:
        """The process-noise part of the state (zeros without process noise)."""
        if self._deviation is None:
            return np.zeros(9)
        dt = self._dt
        k = min(math.floor(t / dt + _TIME_TOL), len(self._deviation) - 1)
        tau = t - k * dt
        e = self._deviation[k]
        if abs(tau) <= _TIME_TOL * dt:
            return e.copy()
        # no new noise between nodes: carry the node's deviation forward
        return (_CA_TRANSITION.F_axis(tau) @ e.reshape(3, 3)).reshape(9)

    def state(self, t: float) -> np.ndarray:
        """``[px py pz vx vy vz ax ay az]`` at scenario time ``t``."""
        if not t >= 0.0:
            raise ValueError(f"truth of {self.target!r} asked at t = {t}; scenario time starts at 0")
        return self.nominal(t) + self.deviation(t)

    def position(self, t: float) -> np.ndarray:
        return self.state(t)[:3]

    def states(self, times) -> np.ndarray:
        return np.array([self.state(float(t)) for t in np.atleast_1d(times)])


@lru_cache(maxsize=16)
def truth_trajectories(scenario: Scenario, run: int = 0) -> dict[str, Trajectory]:
    """Every target's trajectory for one run (cached: the scenario is immutable)."""
    rng = process_rng(scenario.seed, TRUTH_PROCESS, run)
    out = {}
    for tid, spec in scenario.targets.items():  # file order: fixes who draws what
        deviation = None
        if spec.jerk_psd > 0.0:
            dt = scenario.truth_dt
            steps = math.ceil(scenario.duration / dt - _TIME_TOL)
            deviation = jerk_deviation(rng, spec.jerk_psd, dt, steps)
        out[tid] = Trajectory(spec, deviation, scenario.truth_dt)
    return out


def truth_trajectory(scenario: Scenario, target_id: str, run: int = 0) -> Trajectory:
    """The trajectory of ``target_id`` in Monte Carlo run ``run`` (0: distributed run)."""
    scenario.target(target_id)  # a clear KeyError for an unknown id
    return truth_trajectories(scenario, run)[target_id]


class TruthSample(NamedTuple):
    t: float
    target: str
    x: np.ndarray


def truth_events(scenario: Scenario, run: int = 0, period: float | None = None) -> Iterator[TruthSample]:
    """Every target's true state at ``0, period, 2·period, ...`` up to the duration
    (default period: the fastest sensor's), in time order, targets in file order, then
    the ``[traffic]`` aircraft alive at that time in birth order."""
    if period is None:
        period = min(s.period for s in scenario.sensors.values())
    trajectories = truth_trajectories(scenario, run)
    traffic = population(scenario, run)
    for t in iter_times(0.0, period, scenario.duration):
        for tid, traj in trajectories.items():
            yield TruthSample(float(t), tid, traj.state(float(t)))
        if traffic is not None:
            fleet = traffic.fleet(float(t))
            for name, x in zip(fleet.ids, fleet.states(float(t))):
                yield TruthSample(float(t), name, x)
