r"""Sensor emulators: the measurement stream of one sensor, as a pure function of
(scenario, sensor, run), in the batches it is published in (:class:`Batch`).

**Snapshot sensors** scan at ``start + k·period`` up to the scenario's duration, every
plot of a scan at the scan's time, published as one batch. At each scan, for each
object it observes (targets; for DF kinds also jammers, which are emitters while on;
then the ``[traffic]`` aircraft alive at the scan, :mod:`sensors_sim.traffic`), in its
configured order, it yields one :class:`SensorEvent`:

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

**Rotating radars** (``sectors`` > 0): the beam points north at ``t_k = start + k·T``
and turns clockwise, at azimuth ``β(t) = 2π(t − t_k)/T`` in turn k. A plot's time is
when the beam crossed the target: the root of ``f(t) = t − t_k − T·a(t)/2π``, ``a`` the
target's azimuth unwrapped near its value at ``t_k``, found by Newton's method
(``f′ = 1 − T·ȧ/2π``, ``ȧ = (n·v_e − e·v_n)/(e² + n²)``), or, for a target slower
than the beam by less than half (passing within ``v·T/π`` of the radar), by sampling
and bisection (:func:`beam_crossings`). A target crossing north westwards is crossed
twice in one turn, one crossing it eastwards maybe not at all; only roots in
``[t_k, t_k + T)`` count, so each crossing belongs to exactly one turn. Per turn the radar draws one row of variates per crossing (targets,
then aircraft in birth order; :meth:`ScanDraws.rows`), applies steps 2–5 at the
crossing's time, and draws ``Poisson(λ)`` false alarms per turn, each at the time of its
azimuth, ``t_k + T·az/2π``. The turn is cut into ``sectors`` equal sectors by time;
each sector's plots, in time order (which is their ``seq``), are one batch, published
when the beam leaves the sector. Only crossings in coverage yield events.

The published :class:`fusion.types.Measurement` carries the sensor's *stated* std (the
trackers must not know about the jamming); the truth of a plot (target, jammed,
outlier) is only in its :class:`SensorEvent`. Bearings on a jammer are never
contaminated: the jammer's own signal is what is being measured.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Callable, Iterator

import numpy as np

from fusion.angles import TWO_PI, wrap_2pi, wrap_pi
from fusion.measurement.kinds import KINDS
from fusion.types import Identity, Measurement

from .geometry import az_el_range_arrays, coverage_mask, coverage_span, finish_measurement, in_coverage, observe
from .spec import SensorSpec
from .jammer import jam_effect, switched_on_at
from .noise import ScanDraws, outlier_from_uniform, process_rng
from .spec import Scenario
from .traffic import population
from .trajectories import iter_times, sample_times, truth_trajectories

_NEWTON_STEPS = 12
_NEWTON_TOL = 1e-9  # s: a crossing time to this


@dataclass(frozen=True, eq=False)
class SensorEvent:
    """One scan of one object by one sensor.

    Attributes:
        t: time of validity (the scan's time; a rotating radar's beam crossing).
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


@dataclass(frozen=True, eq=False)
class Batch:
    """What a sensor publishes at once, followed by its watermark: a snapshot sensor's
    scan (``t0 = t1``, the scan's time) or a rotating radar's sector (its events at
    ``t0 <= t < t1``, complete when the beam leaves it at ``t1``)."""

    t0: float
    t1: float
    events: list[SensorEvent]


def scan_times(scenario: Scenario, sensor_id: str) -> np.ndarray:
    """The sensor's scan times: ``start + k·period`` up to the duration (a rotating
    radar's north crossings)."""
    s = scenario.sensor(sensor_id)
    return sample_times(s.start, s.period, scenario.duration)


def sensor_events(scenario: Scenario, sensor_id: str, run: int = 0) -> Iterator[SensorEvent]:
    """The sensor's events in time order, with ``seq`` in publication order."""
    for batch in sensor_batches(scenario, sensor_id, run):
        yield from batch.events


def sensor_batches(scenario: Scenario, sensor_id: str, run: int = 0) -> Iterator[Batch]:
    """The sensor's stream as it is published: scans, or a rotating radar's sectors."""
    sensor = scenario.sensor(sensor_id)
    if sensor.sectors:
        return _sectors(scenario, sensor, run)
    return _scans(scenario, sensor, run)


def _scans(scenario: Scenario, sensor: SensorSpec, run: int) -> Iterator[Batch]:
    """A snapshot sensor's scans (module docstring): per object in view, coverage,
    detection, jamming and noise from the scan's fixed pattern of draws, then the scan's
    clutter."""
    sensor_id = sensor.id
    kind = sensor.measurement_kind
    is_range = ~KINDS[kind].angles  # lengths: a jammer's range outliers, if it has any
    n = len(sensor.components)
    rng = process_rng(scenario.seed, sensor_id, run)
    truths = truth_trajectories(scenario, run)
    seq = 0
    traffic = population(scenario, run)
    reports = _reporting(scenario, sensor, traffic)
    identity: dict[str, Identity] = {}
    for t in iter_times(sensor.start, sensor.period, scenario.duration):  # lazily: an endless scenario's too
        t = float(t)
        site = sensor.site.position(t)
        scan: list[tuple[SensorEvent, np.ndarray | None]] = []  # (event without measurement, z)
        aircraft: dict[str, np.ndarray] = {}
        if traffic is not None:
            fleet = traffic.fleet(t)
            positions = fleet.positions(t)
            near = coverage_mask(sensor, positions - site, margin=1e-6)  # the others cannot be in view
            ids = fleet.ids
            if reports is not None:
                near &= np.fromiter((i in reports for i in ids), bool, len(ids))
                identity = {ids[i]: reports[ids[i]] for i in np.flatnonzero(near)}
            aircraft = {ids[i]: positions[i] for i in np.flatnonzero(near)}
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
                error = _error(sensor, effect, outlier, draws.gauss, draws.law, is_range)
                z = finish_measurement(kind, observe(kind, position, site) + error)
            scan.append((SensorEvent(t, None, effect is not None, outlier, detected, obj, covered), z))
        if sensor.clutter_rate > 0.0:  # λ = 0 draws nothing: clutter-free streams stay identical
            false_alarm = SensorEvent(t, None, False, False, True, "", True, clutter=True)
            scan = _shuffled(rng, scan + [(false_alarm, z) for z in clutter_plots(rng, sensor)])
        events = []
        for ev, z in scan:  # seq in publication order
            if z is not None:
                m = Measurement(t=t, sensor=sensor_id, kind=kind, z=z, std=sensor.std.copy(), site=site, seq=seq,
                                identity=identity.get(ev.target))
                seq += 1
                ev = dataclasses.replace(ev, measurement=m)
            events.append(ev)
        yield Batch(t, t, events)


def _reporting(scenario: Scenario, sensor: SensorSpec, traffic) -> dict[str, Identity] | None:
    """An ADS-B receiver's view of a recording: the aircraft that send ADS-B (all but the
    recording's ``without_adsb`` share, drawn from the seed), each with the identity its
    reports carry (its address and last callsign); None: every aircraft, no identity."""
    if sensor.kind != "adsb" or not hasattr(traffic, "equipped"):
        return None
    equipped = traffic.equipped(scenario.seed)
    return {a: Identity(a, c or None) for a, c in zip(traffic.ids.tolist(), traffic.callsigns.tolist())
            if a in equipped}


def _error(sensor: SensorSpec, effect, outlier: bool, gauss: np.ndarray, law: np.ndarray,
           is_range: np.ndarray) -> np.ndarray:
    """A detected plot's noise: ``σ·√gain·n``, its components replaced by outliers when it
    is one (module docstring, step 4)."""
    gain = 1.0 if effect is None else math.sqrt(effect.variance_gain)
    error = sensor.std * gain * gauss
    if outlier:
        std2 = np.where(is_range, effect.outlier_std_range or 0.0, effect.outlier_std)
        replaced = ~is_range | (effect.outlier_std_range is not None)
        error = np.where(replaced, outlier_from_uniform(law, std2, effect.outlier_law), error)
    return error


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


# --- rotating radars ---------------------------------------------------------------------

# (object ids, kinematics(rows, t) -> (positions, velocities) at one time per row)
Kinematics = Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]


def beam_crossings(kinematics: Kinematics, n: int, site: np.ndarray, t_north: float, period: float,
                   reach: float = math.inf) -> tuple[np.ndarray, np.ndarray]:
    """When a clockwise beam, north at ``t_north``, crossed each of ``n`` objects in the
    turn ``[t_north, t_north + period)`` (module docstring): ``(rows, times)``, by row
    then time (a row twice when crossed twice). Objects farther than ``reach`` (m,
    horizontally) from ``site`` throughout the turn are left out.

    Newton's method on ``f(t) = t − t_north − T·a(t)/2π`` needs the target slower in
    azimuth than the beam (``|ȧ| ≤ v/r < 2π/T``): it is used when the horizontal range
    stays above ``v·T/π`` (``f′ ≥ ½``), from ``a(t_north)`` and, if the target may pass
    north westwards within the turn, from ``a(t_north) + 2π``. A target nearer than that
    (passing close to or over the radar) is sampled: the beam-to-target angle at 4,096
    times of the turn, each passage of a multiple of 2π refined by bisection."""
    rows = np.arange(n)
    p, v = kinematics(rows, np.full(n, t_north))
    d = p - site
    horizontal = np.hypot(d[:, 0], d[:, 1])
    travel = np.hypot(v[:, 0], v[:, 1]) * period  # horizontal distance flown in the turn
    nearest = horizontal - travel  # a bound on the horizontal range during the turn
    near = nearest <= reach
    close = near & (nearest <= travel / math.pi)
    far = near & ~close
    a0 = wrap_2pi(np.arctan2(d[far, 0], d[far, 1]))
    again = a0 <= travel[far] / nearest[far]  # may pass north westwards: a second root from a0 + 2π
    newton_rows = np.concatenate([rows[far], rows[far][again]])
    a = np.concatenate([a0, a0[again] + TWO_PI])
    t = t_north + period * a / TWO_PI
    for _ in range(_NEWTON_STEPS):
        p, v = kinematics(newton_rows, t)
        d = p - site
        a = a + wrap_pi(np.arctan2(d[:, 0], d[:, 1]) - a)  # unwrapped near the last iterate
        rate = (d[:, 1] * v[:, 0] - d[:, 0] * v[:, 1]) / (d[:, 0] ** 2 + d[:, 1] ** 2)
        step = (t - t_north - period * a / TWO_PI) / (1.0 - period * rate / TWO_PI)
        t = t - step
        if np.all(np.abs(step) < _NEWTON_TOL):
            break
    sampled_rows, sampled_t = _sampled_crossings(kinematics, rows[close], site, t_north, period)
    rows, t = np.concatenate([newton_rows, sampled_rows]), np.concatenate([t, sampled_t])
    inside = (t >= t_north) & (t < t_north + period)
    rows, t = rows[inside], t[inside]
    order = np.lexsort((t, rows))
    return rows[order], t[order]


def _sampled_crossings(kinematics: Kinematics, rows: np.ndarray, site: np.ndarray, t_north: float,
                       period: float, samples: int = 4096) -> tuple[np.ndarray, np.ndarray]:
    """:func:`beam_crossings` of objects near the radar, by sampling and bisection."""
    if not len(rows):
        return rows, np.empty(0)
    grid = t_north + period * np.arange(samples + 1) / samples
    k, g = np.repeat(rows, len(grid)), np.tile(grid, len(rows))
    p, _ = kinematics(k, g)
    d = (p - site).reshape(len(rows), len(grid), 3)
    az = np.unwrap(np.arctan2(d[..., 0], d[..., 1]), axis=1)
    phi = TWO_PI * (grid - t_north) / period - az  # beam minus target, continuous
    turns = np.floor(phi / TWO_PI)
    i, j = np.nonzero(np.diff(turns, axis=1))
    lo, hi, level = grid[j], grid[j + 1], np.maximum(turns[i, j], turns[i, j + 1]) * TWO_PI
    a_lo = az[i, j]
    for _ in range(60):  # bisection on phi(t) - level, phi's sign at lo is below
        mid = 0.5 * (lo + hi)
        p, _ = kinematics(rows[i], mid)
        dm = p - site
        a = a_lo + wrap_pi(np.arctan2(dm[:, 0], dm[:, 1]) - a_lo)
        below = (TWO_PI * (mid - t_north) / period - a - level) * np.sign(phi[i, j + 1] - phi[i, j]) < 0
        lo, hi = np.where(below, mid, lo), np.where(below, hi, mid)
    return rows[i], 0.5 * (lo + hi)


def _sectors(scenario: Scenario, sensor: SensorSpec, run: int) -> Iterator[Batch]:
    """A rotating radar's stream, sector by sector (module docstring)."""
    sensor_id, kind, T, S = sensor.id, sensor.measurement_kind, sensor.period, sensor.sectors
    is_range = ~KINDS[kind].angles  # lengths: a jammer's range outliers, if it has any
    n = len(sensor.components)
    az_index = sensor.components.index("az")
    rng = process_rng(scenario.seed, sensor_id, run)
    site = sensor.site.position(0.0)
    std = sensor.std.copy()
    truths = truth_trajectories(scenario, run)
    targets = [truths[tid] for tid in sensor.targets]
    traffic = population(scenario, run)
    end = scenario.duration
    seq = yielded = 0
    for t_north in iter_times(sensor.start, T, end):
        t_north = float(t_north)
        fleet = _flying(traffic, t_north, t_north + T)
        count = len(targets) + (len(fleet) if fleet is not None else 0)
        ids = fleet.ids if fleet is not None else []

        def name(row: int) -> str:
            return sensor.targets[row] if row < len(targets) else ids[row - len(targets)]

        def kinematics(rows: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            p, v = np.empty((len(rows), 3)), np.empty((len(rows), 3))
            listed = rows < len(targets)
            for k in np.flatnonzero(listed):  # (an iterate may fall before 0, where no truth is)
                x = targets[rows[k]].state(max(float(t[k]), 0.0))
                p[k], v[k] = x[:3], x[3:6]
            if fleet is not None and not listed.all():
                pa, va, _ = fleet.kinematics(t[~listed], rows[~listed] - len(targets))
                p[~listed], v[~listed] = pa, va
            return p, v

        rows, times = beam_crossings(kinematics, count, site, t_north, T, sensor.max_range)
        if fleet is not None:  # alive at the crossing
            k = rows >= len(targets)
            alive = ~k.copy()
            alive[k] = (fleet.t0[rows[k] - len(targets)] <= times[k]) & (times[k] < fleet.t1[rows[k] - len(targets)])
            rows, times = rows[alive], times[alive]
        draws = ScanDraws.rows(rng, len(rows), n)
        positions = kinematics(rows, times)[0] if len(rows) else np.empty((0, 3))
        d = positions - site
        covered = coverage_mask(sensor, d) & (times <= end)
        plots: list[tuple] = []  # (t, the SensorEvent's fields after t and the measurement, z)
        h = np.column_stack([c for c, name in zip(az_el_range_arrays(d), ("az", "el", "range"))
                             if name in sensor.components]) if len(rows) else np.empty((0, n))
        for i in np.flatnonzero(covered):
            t = float(times[i])
            effect = jam_effect(scenario, sensor_id, t, positions[i]) if scenario.jammers else None
            detected = bool(draws.detect[i] < sensor.p_detect)
            outlier = detected and effect is not None and draws.outlier[i] < effect.p_outlier
            z = None
            if detected:
                z = finish_measurement(kind, h[i] + _error(sensor, effect, outlier, draws.gauss[i], draws.law[i],
                                                           is_range))
            plots.append((t, (effect is not None, outlier, detected, name(rows[i])), z))
        if sensor.clutter_rate > 0.0:
            for z in clutter_plots(rng, sensor):
                t = t_north + T * float(z[az_index]) / TWO_PI  # when the beam points where it is
                if t <= end:
                    plots.append((t, (False, False, True, "", True, True), z))
        plots.sort(key=lambda p: p[0])
        i = 0
        for j in range(S):
            t0, t1 = t_north + T * j / S, min(t_north + T * (j + 1) / S, end)
            if t0 > end or (t0 == end and yielded):  # (a turn starting at the end: done)
                break
            yielded += 1
            events = []
            while i < len(plots) and (plots[i][0] < t1 or t1 == end):
                t, fields, z = plots[i]
                m = None
                if z is not None:
                    m = Measurement(t=t, sensor=sensor_id, kind=kind, z=z, std=std, site=site, seq=seq)
                    seq += 1
                events.append(SensorEvent(t, m, *fields))
                i += 1
            yield Batch(t0, t1, events)


def _flying(traffic, t0: float, t1: float):
    """The aircraft alive at some time of ``[t0, t1)``, in birth order."""
    if traffic is None:
        return None
    first = traffic.fleet(t0)
    later = traffic.fleet(math.nextafter(t1, -math.inf))
    born = later.take(later.index > (first.index.max() if len(first) else -1))
    return type(first).concat([first, born])
