"""Site and scenario files: find, parse, validate, convert to SI (the format is in README.md).

A site file holds ``[origin]``, ``[defaults]``, ``[tracker]``, ``[sensors.<id>]`` and,
optionally, ``recovery_s`` (the live publishers' recovery window); a scenario file adds
``seed``, ``duration_s``, ``[targets]`` and ``[jammers]``, and its sensors' ``targets``
and ``latency_s``. :func:`load_site` takes either (a file with any scenario key is
read as a scenario); :func:`load_scenario` takes only scenarios.

Every problem raises :class:`ScenarioError` naming the file, the line and the field,
e.g. ``patent-3d.toml:14: sensors.radar2d.std_range_m: must be > 0 (got -20)``.
"""

from __future__ import annotations

import math
import os
import re
import tomllib
from importlib import resources
from pathlib import Path

import numpy as np

from fusion.geodetic import LocalFrame, geodetic_to_enu
from fusion.lazy import lazy
from fusion.measurement.kinds import KINDS
from fusion.regions import Region, box_polygon, polygon_area

from ._toml import ANGLE, LENGTH, RATE, TIME, Reader, TomlSource
from .geometry import coverage_span
from .noise import OUTLIER_LAWS
from .spec import (
    DF_KINDS,
    JAM_MODES,
    MAX_RECOVERY_S,
    RECOVERY_S,
    SENSOR_KINDS,
    TOPOLOGIES,
    TRUTH_PROCESS,
    JammerSpec,
    Scenario,
    ScenarioError,
    SensorSpec,
    Site,
    SiteSpec,
    TargetSpec,
    TrafficSpec,
)
from .segments import (
    ConstantAcceleration,
    ConstantVelocity,
    CoordinatedTurn,
    Orbit,
    Static,
    Waypoints,
)

# A recorded trajectory file's reader (and its scipy splines) loads only for a scenario that has one.
recorded = lazy("sensors_sim.recorded")

_ID = re.compile(r"^[A-Za-z0-9_-]+$")  # ids become Zenoh key chunks: no '/', '*', ...
_MIN_SEPARATION = 1.0  # m: a sensor closer than this to a target or jammer is "at" it
_GRID_TOL = 1e-9
_SCENARIO_KEYS = ("seed", "duration_s", "truth_dt_s", "targets", "jammers", "traffic", "truth")  # what makes a file a scenario
MOBILE = "messages"  # ``site = "messages"``: a mobile station's position comes with each measurement


# --- finding files ----------------------------------------------------------------------


def _builtin_dir():
    return resources.files("sensors_sim").joinpath("scenarios")


def list_scenarios() -> list[tuple[str, str]]:
    """The built-in scenarios: (name, one-line description), sorted by name."""
    out = []
    for entry in sorted(_builtin_dir().iterdir(), key=lambda e: e.name.removesuffix(".toml")):
        if entry.name.endswith(".toml"):
            try:
                description = tomllib.loads(entry.read_text(encoding="utf-8")).get("description", "")
            except tomllib.TOMLDecodeError:
                description = "(unreadable: run load_scenario for details)"
            out.append((entry.name[: -len(".toml")], str(description)))
    return out


def load_scenario(name_or_path: str | os.PathLike) -> Scenario:
    """Load a built-in scenario by name (``patent-3d``) or a TOML file by path."""
    root, name, display = _parse(name_or_path)
    return _scenario(root, name, display)


def load_site(name_or_path: str | os.PathLike) -> SiteSpec:
    """Load a site file, or a scenario (built-in name or path) as the site it contains:
    a file with any of the scenario-only keys (seed, duration_s, targets, ...) is
    loaded, and validated, as a whole scenario."""
    root, name, display = _parse(name_or_path, "site file")
    if any(root.has(k) for k in _SCENARIO_KEYS):
        return _scenario(root, name, display)
    return _site_file(root, name, display)


def _parse(name_or_path, what: str = "scenario file") -> tuple[Reader, str, str]:
    text, name, display = _read(name_or_path, what)
    source = TomlSource(text, display)
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        m = re.search(r"line (\d+)", str(e))
        raise ScenarioError(f"{display}:{m.group(1) if m else 1}: invalid TOML: {e}") from None
    return Reader(data, (), source), name, display


def _read(name_or_path, what: str = "scenario file") -> tuple[str, str, str]:
    """(text, scenario name, name used in messages); ``what`` the file is, in them."""
    s = os.fspath(name_or_path)
    looks_like_path = s.endswith(".toml") or os.sep in s or (os.altsep and os.altsep in s) or os.path.exists(s)
    if looks_like_path:
        p = Path(s)
        try:
            return p.read_text(encoding="utf-8"), p.stem, s
        except OSError as e:
            raise ScenarioError(f"{s}: cannot read {what}: {e.strerror}") from None
    entry = _builtin_dir().joinpath(f"{s}.toml")
    if not entry.is_file():
        names = ", ".join(n for n, _ in list_scenarios())
        raise ScenarioError(f"unknown scenario {s!r}: not a file, and not a built-in ({names})")
    return entry.read_text(encoding="utf-8"), s, f"{s}.toml"


# --- the file, table by table -----------------------------------------------------------


def _header(root: Reader, scenario: bool) -> dict:
    """``description``, ``recovery_s``, ``[origin]``, ``[defaults]`` and ``[tracker]``:
    what a site and a scenario share besides their sensors (:class:`SiteSpec` keyword
    arguments)."""
    description = root.string("description") if scenario else root.string("description", "")
    recovery = root.quantity("recovery", TIME, default=RECOVERY_S, gt=0, le=MAX_RECOVERY_S)
    origin_r = root.table("origin")
    origin = (
        origin_r.number("lat_deg", ge=-90, le=90),
        origin_r.number("lon_deg", ge=-180, le=180),
        origin_r.number("alt_m"),
    )
    origin_r.finish()
    defaults_r = root.table("defaults")
    # the method name is checked by the CLI against fusion.methods (sensors_sim does
    # not depend on the estimation methods)
    defaults = {"topology": defaults_r.string("topology", choices=TOPOLOGIES),
                "method": defaults_r.string("method")}
    defaults_r.finish()
    tracker = root.raw("tracker", {})
    if not isinstance(tracker, dict):
        raise root.error("must be a table", "tracker")
    return {"description": description, "origin": origin, "tracker": tracker, "defaults": defaults,
            "recovery": recovery}


def _site_file(root: Reader, name: str, display: str) -> SiteSpec:
    header = _header(root, scenario=False)
    sensors = {sid: _sensor(r, header["origin"], None)[0] for sid, r in root.tables("sensors")}
    regions = _regions(root, sensors)
    root.finish()
    _check_ids(root.source, {}, sensors, {})
    return SiteSpec(name=name, **header, sensors=sensors, source=display, regions=regions)


def _scenario(root: Reader, name: str, display: str) -> Scenario:
    seed = root.integer("seed", ge=0)
    duration = root.quantity("duration", TIME, gt=0)
    truth_dt = root.quantity("truth_dt", TIME, default=None, gt=0)
    endless = root.raw("endless", default=False)
    if not isinstance(endless, bool):
        raise root.error("must be true or false", "endless")
    header = _header(root, scenario=True)
    origin = header["origin"]
    traffic_r = root.table("traffic", required=False)
    traffic = _traffic(traffic_r) if traffic_r is not None else None
    truth_r = root.table("truth", required=False)
    if truth_r is not None:
        if traffic is not None:
            raise truth_r.error("a scenario takes its aircraft from [traffic] or from [truth], not both", "file")
        traffic = _recorded(truth_r, origin, display, duration)
    targets = {tid: _target(r, origin) for tid, r in root.tables("targets", required=traffic is None)}
    jammers = {jid: _jammer(r, origin) for jid, r in root.tables("jammers", required=False)}
    sensors, sensor_pos_keys = {}, {}
    for sid, r in root.tables("sensors"):
        sensors[sid], sensor_pos_keys[sid] = _sensor(r, origin, targets)
    regions = _regions(root, sensors)
    root.finish()

    src = root.source
    _check_ids(src, targets, sensors, jammers)
    for sid, s in sensors.items():
        _check_targets(src, s, targets, jammers)
        if s.start > duration * (1 + _GRID_TOL):
            raise src.error(("sensors", sid, "start_s"), f"first scan after the end (duration {duration:g} s)")
        if sensor_pos_keys[sid] is not None:  # (a position report's sensor has no site to be apart)
            _check_apart(src, ("sensors", sid, sensor_pos_keys[sid]), s.site,
                         {**{t: ts.x0[:3] for t, ts in targets.items()},
                          **{j: js.site.points for j, js in jammers.items()}})
    noisy = [tid for tid, t in targets.items() if t.jerk_psd > 0]
    if noisy and endless:  # its truth is a grid of states over the duration: it has an end
        raise src.error(("targets", noisy[0], "jerk_psd"), "an endless scenario needs closed-form truth "
                        "(no process noise)")
    if noisy and truth_dt is None:
        raise src.error(("targets", noisy[0], "jerk_psd"), "process noise needs truth_dt_s (the truth grid step)")
    if noisy:
        for sid, s in sensors.items():
            if s.sectors:  # a beam crossing is at any time: the truth between nodes is carried forward
                continue
            for key, value in (("start_s", s.start), ("period_s", s.period)):
                if not _on_grid(value, truth_dt):
                    raise src.error(("sensors", sid, key), f"scans must fall on the truth grid: must be a "
                                    f"multiple of truth_dt_s = {truth_dt:g}")
    return Scenario(
        name=name, **header, sensors=sensors, seed=seed, duration=duration, targets=targets, jammers=jammers,
        truth_dt=truth_dt if noisy else None, source=display, traffic=traffic, endless=endless, regions=regions,
    )


def _on_grid(value: float, step: float) -> bool:
    k = round(value / step)
    return abs(value - k * step) <= _GRID_TOL * max(step, abs(value))


# --- positions --------------------------------------------------------------------------


def _geodetic_to_enu(lat: float, lon: float, alt: float, origin: tuple[float, float, float]) -> np.ndarray:
    return np.array(geodetic_to_enu(lat, lon, alt, *origin, deg=True), dtype=float)


def _point(r: Reader, origin) -> tuple[np.ndarray, str]:
    """A fixed ENU position from ``pos_m`` / ``pos_km`` or ``lat_deg, lon_deg, alt_m``."""
    r.allow("lat_deg", "lon_deg", "alt_m")
    geodetic = [k for k in ("lat_deg", "lon_deg", "alt_m") if r.has(k)]
    enu_key = r.unit_key("pos", LENGTH, required=not geodetic)
    if enu_key and geodetic:
        raise r.error(f"give either {enu_key} or lat_deg/lon_deg/alt_m, not both", geodetic[0])
    if enu_key:
        return r.vector(enu_key, (2, 3), LENGTH[enu_key[4:]]), enu_key
    lat, lon = r.number("lat_deg", ge=-90, le=90), r.number("lon_deg", ge=-180, le=180)
    return _geodetic_to_enu(lat, lon, r.number("alt_m"), origin), "lat_deg"


def _site(r: Reader, origin, require_path: bool = False) -> tuple[Site, str]:
    """A fixed point, or a path: ``path_m`` / ``path_km`` with ``path_t_s``."""
    r.allow("path_t_s")
    path, key = r.unit_vector("path", LENGTH, (2, 3), required=require_path, min_rows=2)
    if path is None:
        if r.has("path_t_s"):
            raise r.error("path_t_s needs path_m or path_km", "path_t_s")
        point, key = _point(r, origin)
        return Site(point[None, :]), key
    if any(r.has(k) for k in ("pos_m", "pos_km", "lat_deg", "lon_deg", "alt_m")):
        raise r.error("give either a position or a path, not both", key)
    times = r.vector("path_t_s", (len(path),))  # one time per point
    if times[0] < 0 or np.any(np.diff(times) <= 0):
        raise r.error("must be >= 0 and strictly increasing", "path_t_s")
    return Site(path, times), key


def _check_apart(src: TomlSource, path: tuple, site: Site, others: dict[str, np.ndarray]) -> None:
    for oid, pts in others.items():
        d = np.linalg.norm(site.points[:, None, :] - np.atleast_2d(pts)[None, :, :], axis=-1)
        if np.min(d) < _MIN_SEPARATION:
            raise src.error(path, f"at the same place as {oid!r} (closer than {_MIN_SEPARATION:g} m)")


# --- targets ----------------------------------------------------------------------------


def _target(r: Reader, origin) -> TargetSpec:
    p0, _ = _point(r, origin)
    v0 = r.vector("vel_mps", (2, 3), default=np.zeros(3))
    a0 = r.vector("acc_mps2", (2, 3), default=np.zeros(3))
    jerk_psd = r.number("jerk_psd", 0.0, ge=0)
    seg_readers = r.array_of_tables("segments")
    segments = tuple(_segment(s, origin, last=(i == len(seg_readers) - 1))
                     for i, s in enumerate(seg_readers)) if seg_readers else (ConstantAcceleration(),)
    r.finish()
    return TargetSpec(r.path[-1], np.concatenate([p0, v0, a0]), segments, jerk_psd)


def _pair(r: Reader, key: str, factor: float = 1.0, lo: float = 0.0) -> tuple[float, float]:
    """``[lowest, highest]``, ``lo <= lowest <= highest`` (then scaled by ``factor``)."""
    a, b = r.vector(key, (2,))
    if not lo <= a <= b:
        raise r.error(f"must be [lowest, highest] with {lo:g} <= lowest <= highest", key)
    return a * factor, b * factor


def _traffic(r: Reader) -> TrafficSpec:
    """The ``[traffic]`` table: aircraft crossing a box at random (:mod:`sensors_sim.traffic`)."""
    rate = r.number("rate_per_min", gt=0) / 60.0
    max_alive = r.integer("max_alive", ge=1)
    key = r.unit_key("box", LENGTH)
    x0, x1, y0, y1 = r.vector(key, (4,), LENGTH[key[4:]])
    if not (x0 < x1 and y0 < y1):
        raise r.error("must be [x_min, x_max, y_min, y_max] with x_min < x_max and y_min < y_max", key)
    speed = _pair(r, "speed_mps")
    if speed[0] <= 0:
        raise r.error("must be [lowest, highest] with 0 < lowest <= highest", "speed_mps")
    alt = _pair(r, "alt_m")
    waypoints = r.integer("waypoints", 0, ge=0)
    offset = r.quantity("waypoint_offset", LENGTH, default=0.0, ge=0)
    key = r.unit_key("turn_rate", RATE, required=False)
    turn_rate = TrafficSpec.turn_rate if key is None else _pair(r, key, RATE[key[len("turn_rate_"):]])
    if turn_rate[0] <= 0:
        raise r.error("must be [lowest, highest] with 0 < lowest <= highest", key)
    level_changes = r.integer("level_changes", 0, ge=0)
    climb_rate = _pair(r, "climb_rate_mps") if r.has("climb_rate_mps") else TrafficSpec.climb_rate
    if climb_rate[0] <= 0:
        raise r.error("must be [lowest, highest] with 0 < lowest <= highest", "climb_rate_mps")
    r.finish()
    return TrafficSpec(rate, max_alive, (float(x0), float(x1), float(y0), float(y1)),
                       (float(speed[0]), float(speed[1])), (float(alt[0]), float(alt[1])),
                       waypoints, float(offset), (float(turn_rate[0]), float(turn_rate[1])), level_changes,
                       (float(climb_rate[0]), float(climb_rate[1])))


TRAFFIC_SAMPLE = "traffic:"  # ``file = "traffic:quickstart"``: a collection of the traffic package


def _recorded(r: Reader, origin, display: str, duration: float) -> recorded.RecordedTraffic:
    """The ``[truth]`` table: recorded aircraft as the targets (:mod:`sensors_sim.recorded`).
    ``file``: a path (relative to the scenario file) or ``traffic:<name>``, a collection
    of the ``traffic`` package; ``format``: ``traffic`` or ``jsonl`` (default: from the
    name); the window ``[start_s, start_s + duration_s]`` after the first record (default
    the scenario's duration); ``max_gap_s``, ``keep_ground`` (segmentation);
    ``without_adsb``: the share of the aircraft that send no ADS-B."""
    name = r.string("file")
    if name.startswith(TRAFFIC_SAMPLE):
        try:
            path = recorded.traffic_sample(name[len(TRAFFIC_SAMPLE):])
        except FileNotFoundError as e:
            raise r.error(str(e), "file") from None
    else:
        path = Path(name) if os.path.isabs(name) else Path(display).parent / name
        if not path.is_file():
            raise r.error(f"no such file: {path}", "file")
    jsonl = path.name.endswith((".jsonl", ".jsonl.gz"))
    form = r.string("format", "jsonl" if jsonl else "traffic", choices=("traffic", "jsonl"))
    start = r.quantity("start", TIME, default=0.0, ge=0)
    length = r.quantity("duration", TIME, default=duration, gt=0)
    options = recorded.SmoothingOptions(
        max_gap_s=r.quantity("max_gap", TIME, default=recorded.SmoothingOptions.max_gap_s, gt=0),
        keep_ground=r.raw("keep_ground", False))
    if not isinstance(options.keep_ground, bool):
        raise r.error("must be true or false", "keep_ground")
    without = r.number("without_adsb", 0.0, ge=0, le=1)
    r.finish()
    try:
        records = recorded.read_records(path, form)
    except (OSError, ValueError) as e:
        raise r.error(f"cannot read {path}: {e}", "file") from None
    if not len(records):
        raise r.error(f"{path}: no record could be read ({dict(records.rejected)})", "file")
    t_zero = float(records.t.min()) + start
    recording = recorded.Recording(records, LocalFrame(*origin, deg=True), options, window=(t_zero, t_zero + length))
    if not recording.segments:
        span = float(records.t.max() - records.t.min())
        raise r.error(f"no aircraft in the window [{start:g}, {start + length:g}] s of the recording "
                      f"({span:g} s long)", "start_s")
    return recorded.RecordedTraffic(recording, t_zero, name, without)


_SEGMENT_TYPES = ("static", "cv", "ca", "turn", "waypoints", "orbit")


def _segment(r: Reader, origin, last: bool):
    kind = r.string("type", choices=_SEGMENT_TYPES)
    if kind == "waypoints":
        points, _ = r.unit_vector("points", LENGTH, (2, 3), min_rows=1)
        seg = Waypoints(points, r.number("speed_mps", gt=0))
    elif kind == "orbit":
        a, b = r.vector("axes_m", (2,))
        if not a >= b > 0:
            raise r.error("semi-axes [along, across] must satisfy along >= across > 0", "axes_m")
        seg = Orbit(float(a), float(b), r.quantity("lap", TIME, gt=0), r.quantity("heading", ANGLE),
                    r.string("turn", "left", choices=("left", "right")) == "left",
                    r.quantity("duration", TIME, default=None, gt=0))
    else:
        duration = r.quantity("duration", TIME, default=None, gt=0)
        if duration is None and not last:
            raise r.error("missing (only the last segment may omit it)", "duration_s")
        if kind == "static":
            seg = Static(duration)
        elif kind == "cv":
            seg = ConstantVelocity(duration, r.vector("vel_mps", (2, 3), default=None))
        elif kind == "ca":
            seg = ConstantAcceleration(duration, r.vector("acc_mps2", (2, 3), default=None))
        else:
            seg = CoordinatedTurn(r.quantity("turn_rate", RATE, ne=0), duration)
    r.finish()
    return seg


# --- sensors ----------------------------------------------------------------------------

_UNITS = {"rad": ANGLE, "m": LENGTH}  # a component's unit -> the units its scenario keys may take


def _std(r: Reader, sensor_kind) -> np.ndarray:
    """The stated std per component: each from the first of its keys given (the last one
    required), in the component's units (:class:`sensors_sim.spec.SensorKind`)."""
    out = []
    for c, keys in zip(KINDS[sensor_kind.measures].components, sensor_kind.std_keys_of()):
        units = _UNITS[c.unit]
        value = None
        for key in keys[:-1]:
            value = r.quantity(key, units, default=None, gt=0)
            if value is not None:
                break
        out.append(value if value is not None else r.quantity(keys[-1], units, gt=0))
    return np.array(out)


_POSITION_KEYS = ("pos_m", "pos_km", "lat_deg", "lon_deg", "alt_m", "path_m", "path_km")


def _sensor(r: Reader, origin, targets: dict | None) -> tuple[SensorSpec, str | None]:
    """One ``[sensors.<id>]`` table; ``targets`` is None in a site file, whose sensors
    may be mobile (``site = "messages"``) and have no ``targets`` nor ``latency_s``. A
    sensor whose reports are positions (a kind that is not sited) needs no position: it
    stands at the origin unless one is given (and its position key is then None)."""
    kind = r.string("kind", choices=tuple(SENSOR_KINDS))
    sensor_kind = SENSOR_KINDS[kind]
    if not KINDS[sensor_kind.measures].sited and not any(r.has(k) for k in (*_POSITION_KEYS, "site")):
        site, pos_key = Site(np.zeros((1, 3))), None
    elif targets is None and r.raw("site", None) is not None:
        if r.data["site"] != MOBILE:
            raise r.error(f"must be {MOBILE!r} (a mobile station: its position comes with each measurement); "
                          "give a fixed position as pos_m, pos_km or lat_deg/lon_deg/alt_m", "site")
        if any(r.has(k) for k in _POSITION_KEYS):
            raise r.error(f"a mobile station (site = {MOBILE!r}) has no fixed position: remove it", "site")
        site, pos_key = None, "site"
    else:
        if targets is not None and r.has("site"):
            raise r.error("a scenario's sensors need a position or a path (the emulator measures from it); "
                          f"site = {MOBILE!r} is for site files", "site")
        site, pos_key = _site(r, origin, require_path=(sensor_kind.airborne and targets is not None))
    rotating = r.unit_key("rotation_period", TIME, required=False)
    if rotating and r.has("period_s"):
        raise r.error("give period_s (a snapshot sensor) or rotation_period_s (a rotating radar), not both",
                      "period_s")
    period = r.quantity("rotation_period" if rotating else "period", TIME, gt=0)
    sectors = r.integer("sectors", 32 if rotating else 0, ge=1)
    if sectors and not rotating:
        raise r.error("sectors are a rotating radar's: give rotation_period_s", "sectors")
    start = r.quantity("start", TIME, default=0.0, ge=0)
    std = _std(r, sensor_kind)
    p_detect = r.number("p_detect", 1.0, gt=0, le=1)
    fov_az = (0.0, 2 * math.pi)
    key = r.unit_key("fov_az", ANGLE, required=False)
    if key:
        first, last = r.vector(key, (2,), ANGLE[key[7:]])
        width = (last - first) % (2 * math.pi)
        fov_az = (first % (2 * math.pi), width if width > 0 else 2 * math.pi)  # [0, 360]: all round
    fov_el = (-math.pi / 2, math.pi / 2)
    key = r.unit_key("fov_el", ANGLE, required=False)
    if key:
        lo, hi = r.vector(key, (2,), ANGLE[key[7:]])
        if not (-math.pi / 2 - 1e-12 <= lo < hi <= math.pi / 2 + 1e-12):
            raise r.error("must be [lowest, highest] with -90° <= lowest < highest <= 90°", key)
        fov_el = (lo, hi)
    max_range = r.quantity("max_range", LENGTH, default=math.inf, gt=0)
    band = r.string("band", None)
    signal_power = r.number("signal_power_w", 1.0, gt=0)
    clutter_rate = r.number("clutter_rate", 0.0, ge=0)
    latency = r.quantity("latency", TIME, default=0.0, ge=0) if targets is not None else 0.0
    sac_sic = r.raw("sac_sic", None)
    if sac_sic is not None and (not isinstance(sac_sic, list) or len(sac_sic) != 2 or not all(
            isinstance(x, int) and not isinstance(x, bool) and 0 <= x <= 255 for x in sac_sic)):
        raise r.error("must be [SAC, SIC], two integers 0-255 (the ASTERIX data source identifier)", "sac_sic")
    refs = r.raw("targets", None) if targets is not None else None
    if refs is not None and (not isinstance(refs, list) or not refs or not all(isinstance(x, str) for x in refs)
                             or len(set(refs)) != len(refs)):
        raise r.error("must be a non-empty list of distinct ids", "targets")
    spec = SensorSpec(
        id=r.path[-1], kind=kind, site=site, period=period, start=start, std=std, p_detect=p_detect,
        fov_az=fov_az, fov_el=fov_el, max_range=max_range, band=band, signal_power=signal_power,
        targets=tuple(refs) if refs is not None else tuple(targets or ()), clutter_rate=clutter_rate,
        latency=latency, sac_sic=None if sac_sic is None else tuple(sac_sic), sectors=sectors,
    )
    unbounded = [c for c in spec.components if math.isinf(coverage_span(spec, c)[1])]
    if clutter_rate > 0 and unbounded:  # false alarms are spread uniformly over the coverage
        why = ("give max_range_m or max_range_km" if unbounded == ["range"]
               else f"a {kind} sensor's {', '.join(unbounded)} have no coverage bounds")
        raise r.error(f"clutter needs a finite coverage: {why}", "clutter_rate")
    r.finish()
    if rotating and not spec.active:
        raise r.error(f"only a radar's antenna rotates (radar2d, radar3d), not a {kind}'s", rotating)
    if rotating and not (site is not None and site.fixed):
        raise r.error("a rotating radar stands still: give it a fixed position", rotating)
    return spec, pos_key


def _check_targets(src, sensor: SensorSpec, targets: dict, jammers: dict) -> None:
    path = ("sensors", sensor.id, "targets")
    for ref in sensor.targets:
        if ref in jammers:
            if sensor.kind not in DF_KINDS:
                raise src.error(path, f"{ref!r} is a jammer: only DF sensors ({', '.join(sorted(DF_KINDS))}) "
                                "report bearings on jammers")
        elif ref not in targets:
            raise src.error(path, f"unknown target {ref!r} (targets: {', '.join(targets)}; "
                            f"jammers: {', '.join(jammers) or 'none'})")


def _check_ids(src, targets, sensors, jammers) -> None:
    seen: dict[str, str] = {}
    for table, ids in (("targets", targets), ("jammers", jammers), ("sensors", sensors)):
        for i in ids:
            if not _ID.match(i):
                raise src.error((table, i), "ids may use only letters, digits, '_' and '-'")
            if i == TRUTH_PROCESS:
                raise src.error((table, i), f"{TRUTH_PROCESS!r} is the truth process's id")
            if i in seen:
                raise src.error((table, i), f"id already used in [{seen[i]}]: ids must be unique")
            seen[i] = table


# --- regions ----------------------------------------------------------------------------


def _regions(root: Reader, sensors: dict) -> dict[str, Region]:
    """``[regions.<name>]``: ``polygon_m``/``polygon_km`` (``[[e, n], ...]`` in the
    origin's ENU frame) or ``box_m``/``box_km`` (``[e_min, n_min, e_max, n_max]``), a
    ``margin_m``/``margin_km`` (default 0) and ``sensors``, the ids of the sensors that
    feed it (a sensor may feed several regions)."""
    out: dict[str, Region] = {}
    for name, r in root.tables("regions", required=False):
        if not _ID.match(name):
            raise r.error("region names may use only letters, digits, '_' and '-' (they are key chunks)")
        polygon, key = r.unit_vector("polygon", LENGTH, (2,), required=False, min_rows=3)
        box_key = r.unit_key("box", LENGTH, required=polygon is None)
        if polygon is not None and box_key is not None:
            raise r.error(f"give either {key} or {box_key}, not both", box_key)
        if box_key is not None:
            key = box_key
            e0, n0, e1, n1 = r.vector(box_key, (4,), LENGTH[box_key[4:]])
            if not (e0 < e1 and n0 < n1):
                raise r.error("must be [e_min, n_min, e_max, n_max] with e_min < e_max and n_min < n_max", box_key)
            polygon = box_polygon(e0, n0, e1, n1)
        elif abs(polygon_area(polygon)) <= 0.0:
            raise r.error("degenerate polygon: its points enclose no area", key)
        margin = r.quantity("margin", LENGTH, default=0.0, ge=0)
        refs = r.raw("sensors")
        if not isinstance(refs, list) or not refs or not all(isinstance(x, str) for x in refs) \
                or len(set(refs)) != len(refs):
            raise r.error("must be a non-empty list of distinct sensor ids (a region needs sensors)", "sensors")
        unknown = [x for x in refs if x not in sensors]
        if unknown:
            raise r.error(f"unknown sensor {unknown[0]!r} (sensors: {', '.join(sensors)})", "sensors")
        r.finish()
        out[name] = Region(name, polygon, margin, tuple(refs))
    return out


# --- jammers ----------------------------------------------------------------------------


def _jammer(r: Reader, origin) -> JammerSpec:
    site, _ = _site(r, origin)
    mode = r.string("mode", choices=JAM_MODES)
    band = r.string("band", None)
    if mode == "spot" and band is None:
        raise r.error("missing (a spot jammer jams one band)", "band")
    if mode == "barrage" and band is not None:
        raise r.error("a barrage jammer jams every band: remove 'band'", "band")
    search_delay = r.quantity("search_delay", TIME, default=0.0, ge=0)
    if mode == "barrage" and r.has("search_delay_s"):
        raise r.error("only a spot jammer searches", "search_delay_s")
    schedule = _schedule(r)
    p_outlier = r.number("p_outlier", None, ge=0, le=1)
    spec = JammerSpec(
        id=r.path[-1], site=site, mode=mode, band=band,
        power=r.number("power_w", 1.0, gt=0),
        reach=r.quantity("range", LENGTH, default=math.inf, gt=0, allow_inf=True),
        schedule=schedule, search_delay=search_delay,
        outlier_law=r.string("outlier_law", "laplacian", choices=OUTLIER_LAWS),
        outlier_std=r.quantity("outlier_std", ANGLE, gt=0),
        outlier_std_range=r.quantity("outlier_std_range", LENGTH, default=None, gt=0),
        p_outlier=p_outlier,
        period=r.quantity("period", TIME, default=1.0, gt=0),
    )
    r.finish()
    return spec


def _schedule(r: Reader) -> tuple[tuple[float, float], ...]:
    """``schedule_s = [[on, off], ...]``: sorted, disjoint, on < off (off may be inf)."""
    raw = r.raw("schedule_s", None)
    if raw is None:
        return ((0.0, math.inf),)
    ok = isinstance(raw, list) and raw and all(
        isinstance(iv, list) and len(iv) == 2 and all(isinstance(x, (int, float)) and not isinstance(x, bool)
                                                      and not math.isnan(x) for x in iv) for iv in raw)
    if not ok:
        raise r.error("must be a non-empty list of [on, off] pairs of numbers (s)", "schedule_s")
    out, prev_off = [], -math.inf
    for on, off in raw:
        if not (0 <= on < off) or on < prev_off or math.isinf(on):
            raise r.error("intervals need 0 <= on < off, sorted and not overlapping", "schedule_s")
        out.append((float(on), float(off)))
        prev_off = off
    return tuple(out)
