"""Loaded site and scenario files: immutable records in SI units (metres, seconds, radians).

A :class:`SiteSpec` is what a deployment knows without truth: its origin, its sensors
(kind, where they are, stated std, nominal period), the ``[tracker]`` table and the
``[defaults]``. A :class:`Scenario` is a site plus targets, jammers, a seed and a
duration, so a scenario is accepted wherever a site is asked for.
:func:`sensors_sim.loader.load_site` and :func:`~sensors_sim.loader.load_scenario`
build these from TOML files; everything else in ``sensors_sim`` (truth, sensors,
jammers) is a pure function of them. Positions are local ENU metres around
``origin``; azimuths are compass (clockwise from north) in [0, 2π).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from fusion.measurement.kinds import KINDS
from fusion.topology import TOPOLOGIES

from .segments import Segment

RECOVERY_S = 30.0  # s: a site's recovery window when its file gives no ``recovery_s``
MAX_RECOVERY_S = 3600.0  # s: the longest (every live publisher holds its window in memory)


@dataclass(frozen=True)
class SensorKind:
    """A kind of sensor a scenario or site file declares (``kind = "radar2d"``).

    Attributes:
        name: the ``kind`` key's value.
        measures: the measurement kind it reports (:data:`fusion.measurement.kinds.KINDS`).
        active: it sees its own echo (two-way path loss, :mod:`sensors_sim.jammer`);
            the others are passive.
        airborne: a scenario gives it a flight path (``path_m``/``path_km``), not a point.
        std_keys: per component, the keys of its stated std, the first one given read
            (each in the component's units: ``_deg``/``_rad`` or ``_m``/``_km``); empty:
            each component's wire std field (``std_az``, ``std_range``, ...).
    """

    name: str
    measures: str
    active: bool = False
    airborne: bool = False
    std_keys: tuple[tuple[str, ...], ...] = ()

    def std_keys_of(self) -> tuple[tuple[str, ...], ...]:
        """The std keys per component (the class docstring's ``std_keys``, filled in)."""
        return self.std_keys or tuple((c.std_field,) for c in KINDS[self.measures].components)


#: every sensor kind, by name
SENSOR_KINDS: dict[str, SensorKind] = {k.name: k for k in (
    SensorKind("df", "bearing"),
    SensorKind("airborne_df", "bearing", airborne=True),
    SensorKind("radar2d", "range_az", active=True),
    SensorKind("angle", "azel"),
    SensorKind("radar3d", "az_el_range", active=True),
    # a cooperative surveillance receiver: each aircraft's own position report
    SensorKind("adsb", "position", std_keys=(("std_pos",), ("std_pos",), ("std_alt", "std_pos"))),
)}
# Sensors that may report bearings on a jammer (it is an emitter): the DF family's.
DF_KINDS = frozenset(k.name for k in SENSOR_KINDS.values() if KINDS[k.measures].family == "df")
JAM_MODES = ("barrage", "spot")
TRUTH_PROCESS = "truth"


class ScenarioError(ValueError):
    """A scenario file that cannot be used; the message reads ``file:line: field: why``."""


@dataclass(frozen=True, eq=False)
class Site:
    """Where a sensor or jammer is: a fixed point, or a timed path flown straight
    (piecewise linear) between its points and held at its ends.

    Attributes:
        points: (n, 3) ENU positions; n = 1 for a fixed site.
        times: (n,) strictly increasing times of the points, or None for a fixed site.
    """

    points: np.ndarray
    times: np.ndarray | None = None

    @property
    def fixed(self) -> bool:
        return self.times is None

    def position(self, t: float) -> np.ndarray:
        if self.times is None:
            return self.points[0].copy()
        return np.array([np.interp(t, self.times, self.points[:, i]) for i in range(3)])


@dataclass(frozen=True, eq=False)
class TargetSpec:
    """A target: initial state ``x0 = [p, v, a]`` (9,), motion segments, and the PSD
    ``jerk_psd`` (m²/s⁵) of the white-noise jerk added on top (0: deterministic)."""

    id: str
    x0: np.ndarray
    segments: tuple[Segment, ...]
    jerk_psd: float = 0.0


@dataclass(frozen=True, eq=False)
class TrafficSpec:
    """An endless stream of aircraft crossing a box (``[traffic]``; :mod:`sensors_sim.traffic`).

    Attributes:
        rate: births per second (Poisson).
        max_alive: at most this many aircraft at once: a birth while that many fly is dropped.
        box: ``(x_min, x_max, y_min, y_max)`` ENU metres, the area crossed edge to edge.
        speed: ``(lowest, highest)`` ground speed (m/s), uniform.
        alt: ``(lowest, highest)`` altitude (m, ENU up), uniform.
        waypoints: points each crossing flies by (fly-by turns); 0: a straight line.
        waypoint_offset: the largest distance of a waypoint across the line (m).
        turn_rate: ``(lowest, highest)`` rate of the turns (rad/s), uniform.
        level_changes: climbs or descents to a new level per crossing; 0: level flight.
        climb_rate: ``(lowest, highest)`` vertical rate of a level change (m/s), uniform.
    """

    rate: float
    max_alive: int
    box: tuple[float, float, float, float]
    speed: tuple[float, float]
    alt: tuple[float, float]
    waypoints: int = 0
    waypoint_offset: float = 0.0
    turn_rate: tuple[float, float] = (float(np.radians(1.0)), float(np.radians(3.0)))
    level_changes: int = 0
    climb_rate: tuple[float, float] = (5.0, 15.0)


@dataclass(frozen=True, eq=False)
class SensorSpec:
    """One sensor process.

    Attributes:
        kind: one of :data:`SENSOR_KINDS`.
        site: its position (fixed, or a flight path for an airborne DF); None in a site
            file for a mobile station whose position comes with each measurement.
        period, start: scans at ``start + k·period`` up to the scenario's duration (in
            a site file: the nominal period, which sizes the consumers' buffers).
        std: stated noise standard deviations, in the order of the measurement kind's
            components (rad, m).
        p_detect: probability of detecting a target in coverage, per scan.
        fov_az: (first azimuth, width) of the azimuth sector, clockwise (rad).
        fov_el: (lowest, highest) elevation seen (rad).
        max_range: instrumented range (m), ``inf`` for none.
        band: frequency band, which a spot jammer must find; None: no band given.
        signal_power: power received from a target 1 km away, in the jammer's units
            (only ratios matter; see :mod:`sensors_sim.jammer`).
        targets: ids of what it observes: targets, and for DF kinds also jammers.
        clutter_rate: mean number of false alarms per scan (Poisson), spread uniformly
            over the sensor's coverage in measurement space (see
            :mod:`sensors_sim.emulators`); 0: none.
        latency: the emulated link delay (s): each measurement is published this long
            after its time of validity; 0: at once.
        sac_sic: its ASTERIX data source identifier (SAC, SIC), for a radar whose
            plots come as ASTERIX (``zfusion ingest asterix``); None: none.
        sectors: a rotating radar's sectors per turn (its plots are published sector by
            sector, each at the time the beam crossed it; ``period`` is the rotation
            period, ``start`` a time the beam points north); 0: a snapshot sensor, every
            plot of a scan at the scan's time.
    """

    id: str
    kind: str
    site: Site | None
    period: float
    start: float
    std: np.ndarray
    p_detect: float = 1.0
    fov_az: tuple[float, float] = (0.0, 2.0 * np.pi)
    fov_el: tuple[float, float] = (-np.pi / 2.0, np.pi / 2.0)
    max_range: float = np.inf
    band: str | None = None
    signal_power: float = 1.0
    targets: tuple[str, ...] = ()
    clutter_rate: float = 0.0
    latency: float = 0.0
    sac_sic: tuple[int, int] | None = None
    sectors: int = 0

    @property
    def measurement_kind(self) -> str:
        return SENSOR_KINDS[self.kind].measures

    @property
    def components(self) -> tuple[str, ...]:
        """The names of its measurement kind's components."""
        return KINDS[self.measurement_kind].names

    @property
    def active(self) -> bool:
        return SENSOR_KINDS[self.kind].active


@dataclass(frozen=True, eq=False)
class JammerSpec:
    """One jammer process (see :mod:`sensors_sim.jammer` for its effect).

    Attributes:
        mode: ``barrage`` (every sensor in reach) or ``spot`` (sensors on ``band``,
            once found: ``search_delay`` after each switch-on).
        band: the victim band of a spot jammer; None for barrage.
        power: its power received 1 km away (same units as ``SensorSpec.signal_power``).
        reach: distance beyond which it affects nothing (m).
        schedule: on-intervals ``(t_on, t_off)``, sorted and disjoint; on in [t_on, t_off).
        outlier_law, outlier_std: law and std of angular outliers (rad).
        outlier_std_range: std of range outliers (m), or None: ranges get no outliers.
        p_outlier: a fixed outlier probability (the IMM thesis's p), or None to derive
            it from the jamming-to-signal ratio.
        period: period of its published jamming state (s).
    """

    id: str
    site: Site
    mode: str
    band: str | None
    power: float
    reach: float
    schedule: tuple[tuple[float, float], ...]
    search_delay: float
    outlier_law: str
    outlier_std: float
    outlier_std_range: float | None
    p_outlier: float | None
    period: float


@dataclass(frozen=True, eq=False, kw_only=True)
class SiteSpec:
    """A loaded site: what a deployment knows without truth. ``eq=False``: compared by
    identity, like :class:`Scenario`.

    Attributes:
        name: built-in name or file stem.
        description: one line (may be empty in a site file).
        origin: (lat °, lon °, alt m), WGS-84, of the local ENU frame.
        sensors: id -> spec, in file order (a site file's have no ``targets``).
        tracker: the ``[tracker]`` table, untouched (the estimation methods validate it).
        defaults: ``{"topology": ..., "method": ...}``, what the processes use when the
            command line does not say.
        source: the file it came from (for messages).
        regions: name -> :class:`fusion.regions.Region`, in file order (``[regions]``:
            what each regional fuser holds; empty: one fuser holds everything).
        recovery: the recovery window (s, ``recovery_s``; default :data:`RECOVERY_S`):
            in a live session each publisher keeps about this long of its stream, twice
            over, for a consumer cut off from it to get back (docs/live.md).
    """

    name: str
    description: str
    origin: tuple[float, float, float]
    sensors: dict[str, SensorSpec]
    tracker: dict
    defaults: dict
    source: str = ""
    regions: dict = field(default_factory=dict)
    recovery: float = RECOVERY_S

    def sensor(self, sensor_id: str) -> SensorSpec:
        try:
            return self.sensors[sensor_id]
        except KeyError:
            raise KeyError(f"{self.name!r} has no sensor {sensor_id!r}; "
                           f"sensors: {', '.join(self.sensors)}") from None

    def kind_of(self, sensor_id: str) -> str:
        """The sensor kind (``df``, ``airborne_df``, ``radar2d``, ``angle``, ``radar3d``)."""
        return self.sensor(sensor_id).kind


@dataclass(frozen=True, eq=False, kw_only=True)
class Scenario(SiteSpec):
    """A loaded scenario: a site plus what only a simulation knows. ``eq=False``:
    compared and hashed by identity (the truth cache keys on it); two loads of one file
    are two scenarios.

    Attributes (beyond :class:`SiteSpec`'s):
        seed: scenario seed (``--seed`` replaces it: ``dataclasses.replace``).
        duration: last scenario time (s); scans run up to and including it.
        targets, jammers: id -> spec, in file order.
        truth_dt: step of the truth's process-noise grid (s), or None if no target has
            process noise.
        traffic: aircraft entering and leaving at random, seen by every sensor, or None.
        endless: it can go on past its duration (closed-form truth, no process-noise
            grid): a live emulation without ``--for`` plays it until stopped.
    """

    seed: int
    duration: float
    targets: dict[str, TargetSpec]
    jammers: dict[str, JammerSpec]
    truth_dt: float | None = None
    traffic: TrafficSpec | None = None
    endless: bool = False

    def process_ids(self) -> list[str]:
        """Ids of every source process: sensors, jammers, then ``truth``."""
        return [*self.sensors, *self.jammers, TRUTH_PROCESS]

    def jammer(self, jammer_id: str) -> JammerSpec:
        try:
            return self.jammers[jammer_id]
        except KeyError:
            raise KeyError(f"scenario {self.name!r} has no jammer {jammer_id!r}; "
                           f"jammers: {', '.join(self.jammers) or 'none'}") from None

    def target(self, target_id: str) -> TargetSpec:
        try:
            return self.targets[target_id]
        except KeyError:
            raise KeyError(f"scenario {self.name!r} has no target {target_id!r}; "
                           f"targets: {', '.join(self.targets)}") from None
