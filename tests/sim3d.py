"""A small test-only simulator for the 3D tracking tests: truth drawn from the filters'
own motion model (so the filters are matched) and measurements from the sensor models.

Defaults are the decided ``patent-3d`` parameters: sensors co-located at the ENU
origin; "radar2d" σ_az = 1.0°, σ_range = 20 m; "angle" σ_az = σ_el = 0.05°; both period
1 s from t = 0 for 30 s; CA truth with white-noise jerk q = 0.01 m²/s⁵ from
x0 = [6000, 8000, 2000, -120, -60, 5, 0.5, 1.0, -0.05]. Monte Carlo runs are drawn
all at once (vectorised over runs). ``x0`` may also be one initial state per run
(``(n_runs, 9)``). As in ``patent-3d`` the initial state is fixed, not drawn from the
trackers' zero-mean velocity/acceleration prior: see docs/consistency.md for what that
means for NEES.

Also here, for the consistency tests (tests/fusion/test_patent_consistency.py):

* :func:`scenario_runs`: Monte Carlo runs of a built-in scenario from its own generators
  (``sensors_sim``: truth with its process noise, sensor emulators), i.e. the runs
  ``zfusion eval`` scores;
* :class:`LinearAnalogue`: the linear-Gaussian filter a method's EKF is a linearisation
  of (Jacobians along the noise-free trajectory). Its covariances do not depend on the
  data, so it gives exact, cheap answers to "what NEES would an exactly consistent
  filter show here" and "how much does the prior still weigh at scan k".
"""

from __future__ import annotations

import dataclasses
import heapq
from dataclasses import dataclass, field

import numpy as np

from fusion.angles import wrap_2pi
from fusion.motion import ConstantAcceleration
from fusion.measurement.kinds import model_for
from fusion.types import Estimate, Measurement

DEG = np.pi / 180.0
X0 = np.array([6000.0, 8000.0, 2000.0, -120.0, -60.0, 5.0, 0.5, 1.0, -0.05])
Q = 0.01
DURATION = 30.0


@dataclass(frozen=True)
class SensorSpec:
    id: str
    kind: str
    std: tuple
    site: tuple = (0.0, 0.0, 0.0)
    period: float = 1.0
    t0: float = 0.0


ANGLE = SensorSpec("angle", "azel", (0.05 * DEG, 0.05 * DEG))
RADAR2D = SensorSpec("radar2d", "range_az", (1.0 * DEG, 20.0))
RADAR3D = SensorSpec("radar3d", "az_el_range", (1.0 * DEG, 1.0 * DEG, 20.0))  # the baseline's 3D radar
PATENT_SENSORS = (ANGLE, RADAR2D)


@dataclass
class SimRuns:
    times: np.ndarray  # (n_t,) all measurement times
    truth: np.ndarray  # (n_runs, n_t, 9)
    measurements: list[list[Measurement]] = field(repr=False)  # per run, in (t, sensor, seq) order

    def truth_at(self, run: int, t: float) -> np.ndarray:
        return self.truth[run, int(np.searchsorted(self.times, t))]


def sensor_times(s: SensorSpec, duration: float) -> np.ndarray:
    n = int(np.floor((duration - s.t0) / s.period + 1e-9)) + 1
    return s.t0 + s.period * np.arange(n)


def simulate(n_runs: int, seed: int, sensors=PATENT_SENSORS, x0=X0, q=Q, duration=DURATION) -> SimRuns:
    rng = np.random.default_rng(seed)
    motion = ConstantAcceleration(q)
    per_sensor = {s.id: sensor_times(s, duration) for s in sensors}
    times = np.unique(np.concatenate(list(per_sensor.values())))
    truth = np.empty((n_runs, times.size, 9))
    truth[:, 0] = x0  # one state, or one per run
    for k in range(1, times.size):
        truth[:, k] = motion.sample(truth[:, k - 1], times[k] - times[k - 1], rng)
    meas: list[list[Measurement]] = [[] for _ in range(n_runs)]
    for s in sensors:
        model = model_for(s.kind, s.site, s.std)
        idx = np.searchsorted(times, per_sensor[s.id])
        z = model.h(truth[:, idx]) + rng.standard_normal((n_runs, idx.size, model.n_z)) * model.std
        z[..., model.angles & (model.codes == 0)] = wrap_2pi(z[..., model.angles & (model.codes == 0)])
        std, site = np.array(s.std, float), np.array(s.site, float)
        for r in range(n_runs):
            for k, t in enumerate(per_sensor[s.id]):
                meas[r].append(Measurement(float(t), s.id, s.kind, z[r, k], std, site, k))
    for r in range(n_runs):
        meas[r].sort(key=lambda m: m.order_key)
    return SimRuns(times, truth, meas)


def run_method(method, measurements, advance_every: int | None = None) -> list[Estimate]:
    """Drive a streaming method over one run; optionally send a watermark after every
    ``advance_every``-th measurement: halfway to the next measurement time, when that
    is later (a watermark promises that nothing at or before it will still come)."""
    out: list[Estimate] = []
    for i, m in enumerate(measurements):
        out += method.process(m)
        nxt = measurements[i + 1].t if i + 1 < len(measurements) else m.t + 1.0
        if advance_every and (i + 1) % advance_every == 0 and nxt > m.t:
            out += method.advance(0.5 * (m.t + nxt))
    out += method.finish()
    return out


def centre_track(estimates: list[Estimate]):
    """Times, states and covariances of the centre estimates, stacked."""
    c = [e for e in estimates if e.node == "centre"]
    return np.array([e.t for e in c]), np.array([e.x for e in c]), np.array([e.P for e in c])


def nees(truth: np.ndarray, x: np.ndarray, P: np.ndarray) -> np.ndarray:
    """eᵀP⁻¹e over the last axes: truth, x (..., n) and P (..., n, n)."""
    e = x - truth
    return np.einsum("...i,...i->...", e, np.linalg.solve(P, e[..., None])[..., 0])


# Runs of a built-in scenario ---------------------------------------------------------
def scenario_runs(name: str, n_runs: int, seed: int | None = None) -> SimRuns:
    """Runs ``0 … n_runs−1`` of a one-target scenario from its own generators (truth
    trajectories and sensor emulators of ``sensors_sim``), ``seed`` replacing the
    file's. Truth is sampled at every measurement time."""
    from sensors_sim import load_scenario, scan_times, sensor_events
    from sensors_sim.trajectories import truth_trajectories

    sc = load_scenario(name)
    if seed is not None:
        sc = dataclasses.replace(sc, seed=int(seed))
    (target,) = sc.targets  # one target: its truth is what every estimate is scored against
    times = np.unique(np.concatenate([scan_times(sc, s) for s in sc.sensors]))
    truth = np.empty((n_runs, times.size, 9))
    meas: list[list[Measurement]] = []
    for run in range(n_runs):
        streams = [(ev.measurement for ev in sensor_events(sc, s, run=run) if ev.measurement is not None) for s in sc.sensors]
        meas.append(list(heapq.merge(*streams, key=lambda m: m.order_key)))
        truth[run] = truth_trajectories(sc, run)[target].states(times)
    return SimRuns(times, truth, meas)


# The linear-Gaussian analogue of an EKF -----------------------------------------------
class LinearAnalogue:
    """A Kalman filter on ``x_{k+1} = F x_k + w``, ``z_k = H_k x_k + v`` with the CA model
    of rate ``q``, scans every ``dt`` and ``H_k = ∂h/∂x`` of ``model`` (a
    :class:`~fusion.measurement.models.SphericalModel`) along the noise-free trajectory from
    ``x0``. ``P0`` is the filter's initial covariance (``initial_state`` of a
    noise-free first scan, so the same as the EKF's up to linearisation), ``E0`` the
    true second moment of the initial error: its position block is ``P0``'s (the first
    scan's noise), its velocity/acceleration block is ``m mᵀ`` with ``m`` the truth's
    fixed velocity/acceleration, since the prior is centred on zero.
    """

    def __init__(self, model, x0, P0, q=Q, n_scans: int = 31, dt: float = 1.0):
        motion = ConstantAcceleration(q)
        self.F, self.Q, self.R = np.asarray(motion.F(dt)), np.asarray(motion.Q(dt)), model.R
        x = np.asarray(x0, float)
        self.H = []
        for _ in range(n_scans):
            self.H.append(model.jacobian(x))
            x = self.F @ x
        self.P0 = np.asarray(P0, float)
        self.m = np.asarray(x0, float)[3:]
        self.E0 = self.P0.copy()
        self.E0[3:, 3:] = np.outer(self.m, self.m)
        self.P, self.K = [self.P0], [None]  # posterior covariances, gains
        P = self.P0
        for H in self.H[1:]:
            P = self.F @ P @ self.F.T + self.Q
            S = H @ P @ H.T + self.R
            K = np.linalg.solve(S, H @ P).T
            A = np.eye(9) - K @ H
            P = A @ P @ A.T + K @ self.R @ K.T
            self.P.append(P)
            self.K.append(K)

    @classmethod
    def of_scenario(cls, name: str, config: dict | None = None) -> "LinearAnalogue":
        """The analogue of SS (every sensor's measurement stacked) on a built-in
        one-target scenario, with the scenario's ``[tracker]`` table updated by ``config``."""
        from fusion.methods import method_config
        from fusion.init3d import initial_state
        from fusion.patent import TrackerConfig
        from fusion.measurement.models import SphericalModel
        from sensors_sim import load_scenario

        sc = load_scenario(name)
        (target,) = sc.targets.values()
        cfg = TrackerConfig.from_dict(method_config(sc.tracker, None, config))  # the common table + config
        x0 = np.asarray(target.x0, float)
        scan, models = [], []
        for sid, s in sc.sensors.items():
            model = model_for(s.measurement_kind, s.site.position(0.0), s.std)
            scan.append(Measurement(0.0, sid, s.measurement_kind, model.h(x0), np.asarray(s.std, float), s.site.position(0.0)))
            models.append(model)
        _, P0 = initial_state(scan, 9, cfg.priors())
        n_scans = int(round(sc.duration / min(s.period for s in sc.sensors.values()))) + 1
        return cls(SphericalModel.stack(models), x0, P0, cfg.q, n_scans)

    def prior_deficit(self) -> np.ndarray:
        """Per scan, ``9 − E[NEES]`` when the truth's initial state is fixed:
        ``tr(P_k⁻¹ Φ_k (P0 − E0) Φ_kᵀ)`` with ``Φ_k`` the filter's error transition
        since scan 0. Zero if the prior were a distribution the truth is drawn from,
        or if it no longer weighs; positive: conservative."""
        Phi, out = np.eye(9), [np.trace(np.linalg.solve(self.P0, self.P0 - self.E0))]
        for H, K, P in zip(self.H[1:], self.K[1:], self.P[1:]):
            Phi = (np.eye(9) - K @ H) @ self.F @ Phi
            out.append(np.trace(np.linalg.solve(P, Phi @ (self.P0 - self.E0) @ Phi.T)))
        return np.array(out)

    def nees(self, n_runs: int, rng: np.random.Generator, consistent_start: bool = True) -> np.ndarray:
        """NEES ``(n_runs, n_scans)`` of Monte Carlo runs of this linear filter; with
        ``consistent_start`` the initial error is drawn from ``P0`` (an exactly
        consistent filter), else from ``E0`` (fixed truth, zero-mean prior)."""
        E = np.linalg.cholesky(self.P0) @ rng.standard_normal((9, n_runs))  # errors, one column per run
        if not consistent_start:  # the velocity/acceleration error is the fixed 0 − m
            E[3:] = -self.m[:, None]
        Lq = np.linalg.cholesky(self.Q)
        sr = np.sqrt(np.diag(self.R))[:, None]
        out = [np.einsum("ir,ir->r", E, np.linalg.solve(self.P0, E))]
        for H, K, P in zip(self.H[1:], self.K[1:], self.P[1:]):
            E = self.F @ E - Lq @ rng.standard_normal((9, n_runs))  # prediction error
            E = E + K @ (sr * rng.standard_normal((sr.size, n_runs)) - H @ E)  # update
            out.append(np.einsum("ir,ir->r", E, np.linalg.solve(P, E)))
        return np.array(out).T
