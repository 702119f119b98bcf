"""A small test-only simulator for the 3D tracking tests: truth drawn from the filters'
own motion model (so the filters are matched) and measurements from the sensor models.

Defaults are the decided ``patent-3d`` parameters: sensors co-located at the ENU
origin; "radar2d" σ_az = 1.0°, σ_range = 20 m; "angle" σ_az = σ_el = 0.05°; both period
1 s from t = 0 for 30 s; CA truth with white-noise jerk q = 0.01 m²/s⁵ from
x0 = [6000, 8000, 2000, -120, -60, 5, 0.5, 1.0, -0.05]. Monte Carlo runs are drawn
all at once (vectorised over runs).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from fusion.angles import wrap_2pi
from fusion.motion import ConstantAcceleration
from fusion.sensors3d import MODEL_BY_KIND
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
    truth[:, 0] = x0
    for k in range(1, times.size):
        truth[:, k] = motion.sample(truth[:, k - 1], times[k] - times[k - 1], rng)
    meas: list[list[Measurement]] = [[] for _ in range(n_runs)]
    for s in sensors:
        model = MODEL_BY_KIND[s.kind](s.site, s.std)
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
