r"""Sensor emulators: the measurement stream of one sensor, as a pure function of
(scenario, sensor, run).

A sensor scans at ``start + k·period`` up to the scenario's duration. At each scan, for
each object it observes (targets; for DF kinds also jammers, which are emitters while
on; then the ``[traffic]`` aircraft alive at the scan, :mod:`sensors_sim.traffic`), in
its configured order, it yields one :class:`SensorEvent`:

1. draw the scan's variates (:class:`sensors_sim.noise.ScanDraws`: always the same
   pattern, so streams stay aligned whatever is detected or jammed; a traffic aircraft
   that cannot be in coverage draws nothing and yields no event);
2. coverage: azimuth sector, elevation limits, instrumented range (a jammer must be on);
3. detection: ``u_detect < P_D``;
4. noise: ``z = h(x) + σ_J·n``, ``σ_J = σ·√gain`` when jammed (:mod:`sensors_sim.jammer`),
   and with probability ``p_outlier`` the components replaced by outliers;
5. azimuth wrapped to [0, 2π), elevation clipped to [−π/2, π/2].

Clutter (``clutter_rate`` λ > 0): ``n ~ Poisson(λ)`` false alarms per scan, uniform over
the coverage in measurement space (the constant clutter density λ/V), then a random
order of all the scan's plots, which is the order of their ``seq``: nothing on the wire
tells a false alarm from a target. With λ = 0 nothing extra is drawn.

The published :class:`fusion.types.Measurement` carries the sensor's *stated* std (the
trackers must not know about the jamming); the truth of a plot (target, jammed,
outlier) is only in its :class:`SensorEvent`. Bearings on a jammer are never
contaminated: the jammer's own signal is what is being measured.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Iterator

import numpy as np

from fusion.measurement.kinds import KINDS
from fusion.types import Measurement

from .geometry import coverage_mask, coverage_span, finish_measurement, in_coverage, observe
from .spec import SensorSpec
from .jammer import jam_effect, switched_on_at
from .noise import ScanDraws, outlier_from_uniform, process_rng
from .spec import Scenario
from .traffic import Traffic, aircraft_id
from .trajectories import iter_times, sample_times, truth_trajectories


@dataclass(frozen=True, eq=False)
class SensorEvent:
    """One scan of one object by one sensor.

    Attributes:
        t: scan time.
        measurement: what is published, or None (missed, out of coverage).
        jammed: a jammer acted on this scan of this object.
        outlier: the published measurement is a jamming outlier.
        detected: a measurement was produced (in coverage and the detection draw won).
        target: the observed object (target or jammer id).
        in_coverage: the object was in the field of view and range (before P_D).
        clutter: the measurement is a false alarm (``target`` is then ``""``).
    """

    t: float
    measurement: Measurement | None
    jammed: bool
    outlier: bool
    detected: bool
    target: str = ""
    in_coverage: bool = True
    clutter: bool = False


def scan_times(scenario: Scenario, sensor_id: str) -> np.ndarray:
    """The sensor's scan times: ``start + k·period`` up to the duration."""
    s = scenario.sensor(sensor_id)
    return sample_times(s.start, s.period, scenario.duration)


def sensor_events(scenario: Scenario, sensor_id: str, run: int = 0) -> Iterator[SensorEvent]:
    """The sensor's events in time order: at each scan, per object in view, coverage,
    detection, jamming and noise from the scan's fixed pattern of draws, then the
    scan's clutter, with ``seq`` in publication order."""
    sensor = scenario.sensor(sensor_id)
    kind = sensor.measurement_kind
    is_range = ~KINDS[kind].angles  # lengths: a jammer's range outliers, if it has any
    n = len(sensor.components)
    rng = process_rng(scenario.seed, sensor_id, run)
    truths = truth_trajectories(scenario, run)
    seq = 0
    traffic = Traffic(scenario.traffic, scenario.seed, run) if scenario.traffic is not None else None
    for t in iter_times(sensor.start, sensor.period, scenario.duration):  # lazily: an endless scenario's too
        t = float(t)
        site = sensor.site.position(t)
        scan: list[tuple[SensorEvent, np.ndarray | None]] = []  # (event without measurement, z)
        aircraft: dict[str, np.ndarray] = {}
        if traffic is not None:
            fleet = traffic.fleet(t)
            positions = fleet.positions(t)
            near = coverage_mask(sensor, positions - site, margin=1e-6)  # the others cannot be in view
            aircraft = {aircraft_id(i): p for i, p in zip(fleet.index[near], positions[near])}
        for obj in (*sensor.targets, *aircraft):
            draws = ScanDraws(rng, n)
            if obj in truths or obj in aircraft:
                position, emitting = (truths[obj].position(t) if obj in truths else aircraft[obj]), True
                effect = jam_effect(scenario, sensor_id, t, position)
            else:  # a jammer, seen by a DF only while it transmits
                jammer = scenario.jammers[obj]
                position, emitting = jammer.site.position(t), switched_on_at(jammer, t) is not None
                effect = None
            d = position - site
            covered = emitting and in_coverage(sensor, d)
            detected = covered and draws.detect < sensor.p_detect
            outlier = detected and effect is not None and draws.outlier < effect.p_outlier
            z = None
            if detected:
                gain = 1.0 if effect is None else math.sqrt(effect.variance_gain)
                error = sensor.std * gain * draws.gauss
                if outlier:
                    std2 = np.where(is_range, effect.outlier_std_range or 0.0, effect.outlier_std)
                    replaced = ~is_range | (effect.outlier_std_range is not None)
                    error = np.where(replaced, outlier_from_uniform(draws.law, std2, effect.outlier_law), error)
                z = finish_measurement(kind, observe(kind, position, site) + error)
            scan.append((SensorEvent(t, None, effect is not None, outlier, detected, obj, covered), z))
        if sensor.clutter_rate > 0.0:  # λ = 0 draws nothing: clutter-free streams stay identical
            false_alarm = SensorEvent(t, None, False, False, True, "", True, clutter=True)
            scan = _shuffled(rng, scan + [(false_alarm, z) for z in clutter_plots(rng, sensor)])
        for ev, z in scan:  # seq in publication order
            if z is None:
                yield ev
                continue
            m = Measurement(t=t, sensor=sensor_id, kind=kind, z=z, std=sensor.std.copy(), site=site, seq=seq)
            seq += 1
            yield dataclasses.replace(ev, measurement=m)


def clutter_plots(rng: np.random.Generator, sensor: SensorSpec) -> list[np.ndarray]:
    """One scan's false alarms: ``n ~ Poisson(clutter_rate)`` measurement vectors, each
    component uniform over the coverage (module docstring)."""
    count = int(rng.poisson(sensor.clutter_rate))
    u = rng.random((count, len(sensor.components)))
    z = np.empty_like(u)
    for i, c in enumerate(sensor.components):
        origin, extent = coverage_span(sensor, c)
        z[:, i] = origin + extent * u[:, i]
    return [finish_measurement(sensor.measurement_kind, row) for row in z]


def _shuffled(rng: np.random.Generator, scan: list) -> list:
    """The scan's ``(event, z)`` plots in a random order (missed objects, which publish
    nothing, last)."""
    plots = [p for p in scan if p[1] is not None]
    return [plots[i] for i in rng.permutation(len(plots))] + [p for p in scan if p[1] is None]
