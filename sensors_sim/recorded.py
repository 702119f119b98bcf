r"""Recorded air traffic as truth: ADS-B state vectors in, per-aircraft ENU trajectories out.

Records come from ``traffic``'s JSON collections (:func:`read_traffic_json`: timestamp ms,
icao24, latitude, longitude, altitude ft, groundspeed kt, track °, vertical_rate ft/min,
onground) or from our JSON lines (:func:`read_jsonl`, SI units; ``docs/ingest.md``).
Positions go to the origin's ENU frame (pymap3d, WGS-84); velocities (track from true
north, vertical rate) are rotated from the aircraft's local ENU axes into the origin's.

Smoothing. A recorded position is tagged to the second but is the last one heard before
the tag, so successive positions advance by 0–2× the speed while the velocities are
smooth. Each axis is a nearly-constant-velocity process (white acceleration of PSD q)
seen in position (σ_p) and velocity (σ_v); the trajectory is its smoothed mean, the RTS
smoother's result, computed as one banded least-squares solve over the states
``x_k = (p_k, v_k)`` at the record times::

    min  Σ_k (z_k − p_k)²/σ_p² + (u_k − v_k)²/σ_v² + Σ_k r_kᵀ Q(h_k)⁻¹ r_k,   r_k = x_{k+1} − F(h_k) x_k
    F(h) = [1 h; 0 1],   Q(h)⁻¹ = (1/q) [12/h³  −6/h²; −6/h²  4/h]

(block-tridiagonal normal equations). A record whose normalised residual exceeds
:data:`OUTLIER_SIGMA` (the recording's altitude and position glitches) is dropped and the
solve repeated. Between records the mean of that process given both neighbouring states
is the cubic Hermite interpolant of ``(p_k, v_k), (p_{k+1}, v_{k+1})``: position C¹ and
cubic, velocity quadratic, acceleration piecewise linear.

Repeats. A state vector repeats the last position heard (and its altitude, sent in the
same message) until a new one arrives: only new positions are measurements, velocities
are taken from every record.

Segments. A gap of more than ``max_gap_s`` between new positions, or the aircraft on the
ground (kept only with ``keep_ground``), ends a segment. An aircraft exists only within
its segments, from its first new position to its last: nothing is extrapolated.
"""

from __future__ import annotations

import gzip
import importlib.metadata
import json
import math
import zlib
from collections import Counter
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path

import numpy as np
import pymap3d
from scipy.interpolate import CubicHermiteSpline
from scipy.linalg import LinAlgError, solveh_banded

from fusion.geodetic import LocalFrame

FT = 0.3048  # m
KT = 1852.0 / 3600.0  # m/s
FPM = FT / 60.0  # m/s
OUTLIER_SIGMA = 6.0  # a record this many σ from the smoothed path is a glitch
MAX_PASSES = 8  # outlier passes per segment
TRAFFIC_SAMPLE = "traffic/data/samples/collections/{name}.json.gz"  # in traffic's wheel
JSONL_FIELDS = {"t", "id", "callsign", "lat_deg", "lon_deg", "alt_m", "gs_m_s", "track_deg", "vrate_m_s", "on_ground"}
_COLUMNS = ("t", "lat", "lon", "alt", "gs", "track", "vrate")


@dataclass(frozen=True)
class SmoothingOptions:
    """The smoother's model (module docstring), horizontal (per axis) and vertical.

    Attributes:
        std_pos_h, std_pos_v: σ_p of the recorded positions (m).
        std_vel_h, std_vel_v: σ_v of the recorded velocities (m/s).
        q_h, q_v: white-acceleration PSD q (m²/s³).
        max_gap_s: a longer gap between records ends a segment.
        keep_ground: keep on-ground records (as their own segments).
        min_records: a segment with fewer new positions is dropped (``short``).
    """

    std_pos_h: float = 60.0
    std_pos_v: float = 15.0
    std_vel_h: float = 1.5
    std_vel_v: float = 1.0
    q_h: float = 0.5
    q_v: float = 0.2
    max_gap_s: float = 10.0
    keep_ground: bool = False
    min_records: int = 3

    def __post_init__(self):
        for name in ("std_pos_h", "std_pos_v", "std_vel_h", "std_vel_v", "q_h", "q_v", "max_gap_s"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
        if self.min_records < 2:
            raise ValueError(f"min_records must be >= 2, got {self.min_records}")


@dataclass
class Records:
    """Recorded state vectors, one row each, sorted by aircraft then time; NaN where a
    record has no value. ``rejected`` counts the records that could not be read."""

    id: np.ndarray  # str
    callsign: np.ndarray  # str ('' when unknown)
    t: np.ndarray  # UTC s
    lat: np.ndarray  # °
    lon: np.ndarray  # °
    alt: np.ndarray  # m
    gs: np.ndarray  # m/s
    track: np.ndarray  # ° from true north
    vrate: np.ndarray  # m/s up
    ground: np.ndarray  # bool
    rejected: Counter = field(default_factory=Counter)

    def __len__(self) -> int:
        return len(self.t)


class RecordError(ValueError):
    def __init__(self, cause: str, detail: str):
        super().__init__(detail)
        self.cause = cause


# (key, unit factor, limits in the file's unit) per column, for each input form
_TRAFFIC = {"t": ("timestamp", 1e-3, (1e12, 1e13)), "lat": ("latitude", 1.0, (-90, 90)),
            "lon": ("longitude", 1.0, (-180, 180)), "alt": ("altitude", FT, (-2000, 130_000)),
            "gs": ("groundspeed", KT, (0, 5000)), "track": ("track", 1.0, (-360, 360)),
            "vrate": ("vertical_rate", FPM, (-60_000, 60_000))}
_JSONL = {"t": ("t", 1.0, (1e9, 1e10)), "lat": ("lat_deg", 1.0, (-90, 90)), "lon": ("lon_deg", 1.0, (-180, 180)),
          "alt": ("alt_m", 1.0, (-1000, 40_000)), "gs": ("gs_m_s", 1.0, (0, 3000)),
          "track": ("track_deg", 1.0, (-360, 360)), "vrate": ("vrate_m_s", 1.0, (-300, 300))}
_KEYS = {"traffic": (_TRAFFIC, "icao24", "callsign", "onground"), "jsonl": (_JSONL, "id", "callsign", "on_ground")}
_REQUIRED = ("t", "lat", "lon")


def records_from_dicts(items, form: str = "traffic") -> Records:
    """Records from parsed objects in ``form`` ``traffic`` or ``jsonl``. A malformed one
    is skipped and counted in ``rejected`` by its first fault, checked in this order: not
    an object (``record``), a field ``jsonl`` does not have (``unknown-field``), then per
    number (time, position, altitude, speed, track, rate) ``missing`` (time and position
    only), ``value`` (not a number) or ``range`` (not finite or outside its limits), then
    the on-ground flag (``value``), the id (``missing``) and the callsign (``value``).
    Column by column, for speed."""
    units, id_key, cs_key, ground_key = _KEYS[form]
    items = list(items)
    rows = [d if type(d) is dict else {} for d in items]
    n = len(rows)
    cause = np.full(n, "", dtype=object)

    def fail(bad: np.ndarray, why: str) -> None:
        cause[bad & (cause == "")] = why

    fail(np.fromiter((type(d) is not dict for d in items), bool, n), "record")
    if form == "jsonl":
        fail(np.fromiter((not d.keys() <= JSONL_FIELDS for d in rows), bool, n), "unknown-field")
    cols = {}
    for c, (key, k, (lo, hi)) in units.items():
        raw = [d.get(key) for d in rows]
        number = np.fromiter((type(x) in (int, float) for x in raw), bool, n)  # a bool's type is bool
        missing = np.fromiter((x is None for x in raw), bool, n)
        if c in _REQUIRED:
            fail(missing, "missing")
        fail(~number & ~missing, "value")
        x = np.array([v if ok and -1e300 < v < 1e300 else math.nan for v, ok in zip(raw, number)], dtype=float)
        with np.errstate(invalid="ignore"):
            fail(number & ~((x >= lo) & (x <= hi)), "range")
        cols[c] = x * k
    ground = [d.get(ground_key, False) for d in rows]
    fail(np.fromiter((type(g) is not bool for g in ground), bool, n), "value")
    ids = [x.strip().lower() if type(x) is str else None for x in (d.get(id_key) for d in rows)]
    fail(np.fromiter((x is None or not 0 < len(x) <= 32 for x in ids), bool, n), "missing")
    names = [d.get(cs_key) for d in rows]
    fail(np.fromiter((x is not None and (type(x) is not str or len(x) > 32) for x in names), bool, n), "value")
    ok = cause == ""
    keep = np.flatnonzero(ok)
    t, ident = cols["t"][keep], np.array([ids[i] for i in keep], dtype=str)
    order = np.lexsort((t, ident))
    return Records(id=ident[order], callsign=np.array([(names[i] or "").strip() for i in keep], dtype=str)[order],
                   ground=np.array([ground[i] for i in keep], dtype=bool)[order],
                   rejected=Counter(cause[~ok].tolist()), **{c: x[keep][order] for c, x in cols.items()})


def read_traffic_json(path: str | Path) -> Records:
    """A ``traffic`` collection (a JSON list of records, gzip-compressed or not)."""
    raw = Path(path).read_bytes()
    if raw[:2] == b"\x1f\x8b":
        raw = gzip.decompress(raw)
    try:
        items = json.loads(raw)
    except (ValueError, RecursionError) as e:
        raise ValueError(f"{path}: not JSON ({type(e).__name__})") from None
    if not isinstance(items, list):
        raise ValueError(f"{path}: expected a JSON list of records")
    return records_from_dicts(items, "traffic")


def read_jsonl(path: str | Path) -> Records:
    """Our JSON lines: one record per line (``JSONL_FIELDS``; t, id, lat_deg and lon_deg
    required). A line that is not JSON is counted as ``json``."""
    items, bad = [], 0
    opener = gzip.open if Path(path).suffix == ".gz" else open
    with opener(path, "rt", encoding="utf-8", errors="replace") as f:
        for line in f:
            if not line.strip():
                continue
            try:
                items.append(json.loads(line))
            except (ValueError, RecursionError):
                bad += 1
    out = records_from_dicts(items, "jsonl")
    if bad:
        out.rejected["json"] += bad
    return out


@lru_cache(maxsize=4)
def _read_cached(path: str, form: str, stamp: tuple[int, int]) -> Records:
    return read_traffic_json(path) if form == "traffic" else read_jsonl(path)


def read_records(path: str | Path, form: str) -> Records:
    """:func:`read_traffic_json` (``form`` ``traffic``) or :func:`read_jsonl` (``jsonl``),
    cached while the file is unchanged (a scenario loaded twice reads it once). The
    records are shared: not to be modified."""
    st = Path(path).stat()
    return _read_cached(str(path), form, (st.st_mtime_ns, st.st_size))


def traffic_sample(name: str = "quickstart") -> Path:
    """The path of a collection shipped in ``traffic``'s wheel, found from its installed
    metadata without importing it. FileNotFoundError says how to install it."""
    try:
        dist = importlib.metadata.distribution("traffic")
    except importlib.metadata.PackageNotFoundError:
        raise FileNotFoundError("the 'traffic' package is not installed: pip install --no-deps traffic==2.13") from None
    path = Path(dist.locate_file(TRAFFIC_SAMPLE.format(name=name)))
    if not path.is_file():
        raise FileNotFoundError(f"{path}: not in traffic {dist.version}")
    return path


# ------------------------------------------------------------------ smoothing


def smooth_axis(t: np.ndarray, z: np.ndarray, wz: np.ndarray, u: np.ndarray, wu: np.ndarray,
                q: float) -> tuple[np.ndarray, np.ndarray]:
    """The smoothed positions and velocities (n, m) of m axes sharing times and weights.

    Args:
        t: (n,) increasing times.
        z, u: (n, m) measured positions and velocities (any value where the weight is 0).
        wz, wu: (n,) weights 1/σ² of each record's position and velocity (0: none).
        q: white-acceleration PSD.

    Minimises the module docstring's cost by its normal equations ``A x = b``, A banded
    (upper bandwidth 3). LinAlgError when the records do not fix a path (fewer than two
    positions, or one and no velocity).
    """
    n = len(t)
    h = np.diff(t)
    ab = np.zeros((4, 2 * n))  # upper banded form: ab[3 + i − j, j] = A[i, j]
    diag, off1, off2, off3 = ab[3], ab[2], ab[1], ab[0]
    diag[0::2] += wz
    diag[1::2] += wu
    w11, w12, w22 = 12.0 / (q * h ** 3), 6.0 / (q * h ** 2), 4.0 / (q * h)
    # block (k, k) += Fᵀ W F = (1/q)[12/h³ 6/h²; 6/h² 4/h]
    diag[0:-2:2] += w11
    off1[1:-1:2] += w12  # A[2k, 2k+1] lives at column 2k+1
    diag[1:-2:2] += w22
    # block (k+1, k+1) += W = (1/q)[12/h³ −6/h²; −6/h² 4/h]
    diag[2::2] += w11
    off1[3::2] -= w12
    diag[3::2] += w22
    # block (k, k+1) = −Fᵀ W = −(1/q)[12/h³ −6/h²; 6/h² −2/h]
    off2[2::2] -= w11  # A[2k, 2k+2]
    off3[3::2] += w12  # A[2k, 2k+3]
    off1[2::2] -= w12  # A[2k+1, 2k+2]
    off2[3::2] += 0.5 * w22  # A[2k+1, 2k+3] = +2/(q h)
    b = np.zeros((2 * n, z.shape[1]))
    b[0::2] = wz[:, None] * np.where(wz[:, None] > 0, z, 0.0)
    b[1::2] = wu[:, None] * np.where(wu[:, None] > 0, u, 0.0)
    x = solveh_banded(ab, b)
    return x[0::2], x[1::2]


def _robust(t, z, wz, u, wu, q, sz, su) -> tuple[np.ndarray, np.ndarray, int]:
    """:func:`smooth_axis`, dropping the worst records beyond OUTLIER_SIGMA each pass."""
    wz, wu = wz.copy(), wu.copy()
    dropped = 0
    for _ in range(MAX_PASSES):
        p, v = smooth_axis(t, z, wz, u, wu, q)
        rz = np.where(wz > 0, np.linalg.norm(np.where(wz[:, None] > 0, z - p, 0.0), axis=1) / sz, 0.0)
        ru = np.where(wu > 0, np.linalg.norm(np.where(wu[:, None] > 0, u - v, 0.0), axis=1) / su, 0.0)
        worst = max(rz.max(initial=0.0), ru.max(initial=0.0))
        if worst <= OUTLIER_SIGMA:
            break
        cut = max(OUTLIER_SIGMA, 0.5 * worst)  # the worst first: a glitch drags its neighbours
        bad_z, bad_u = rz > cut, ru > cut
        dropped += int(bad_z.sum() + bad_u.sum())
        wz[bad_z], wu[bad_u] = 0.0, 0.0
    return p, v, dropped


# ------------------------------------------------------------------ trajectories


@dataclass(frozen=True, eq=False)
class Segment:
    """One aircraft's continuous stretch of records: smoothed ENU states at the record
    times ``t`` (UTC s), Hermite in between; exists on ``[t[0], t[-1]]``.

    Attributes:
        id: the aircraft (its 24-bit address, lower-case hex).
        callsign: the last non-empty callsign of the stretch, or ''.
        t: (n,) times; p, v: (n, 3) ENU positions (m) and velocities (m/s).
        on_ground: a surface stretch (only with ``keep_ground``).
        outliers: records (positions or velocities) dropped as glitches.
    """

    id: str
    callsign: str
    t: np.ndarray
    p: np.ndarray
    v: np.ndarray
    on_ground: bool = False
    outliers: int = 0

    def __post_init__(self):
        object.__setattr__(self, "_spline", CubicHermiteSpline(self.t, self.p, self.v, axis=0, extrapolate=False))

    @property
    def start(self) -> float:
        return float(self.t[0])

    @property
    def end(self) -> float:
        return float(self.t[-1])

    def position(self, t) -> np.ndarray:
        """ENU position(s) (m), NaN outside the segment."""
        return self._spline(t)

    def velocity(self, t) -> np.ndarray:
        return self._spline(t, 1)

    def acceleration(self, t) -> np.ndarray:
        """The Hermite's second derivative (m/s²): linear between records."""
        return self._spline(t, 2)

    def state(self, t: float) -> np.ndarray:
        """``[p, v, a]`` (9,) at ``t``, as the emulators take a truth state."""
        return np.concatenate([self.position(t), self.velocity(t), self.acceleration(t)])


def _to_origin(frame: LocalFrame, lat, lon, e, n, u) -> np.ndarray:
    """Vectors given in the local ENU axes at (lat, lon) -> the frame's ENU axes."""
    x, y, z = pymap3d.enu2uvw(e, n, u, lat, lon, deg=True)
    return np.stack(pymap3d.uvw2enu(x, y, z, frame.lat0, frame.lon0, deg=True), axis=-1)


def _fresh(r: Records, a: int, b: int) -> np.ndarray:
    """Which of rows [a, b) carry a new position: a state vector repeats the last position
    it heard (and the altitude, sent in the same message) until another arrives."""
    return np.r_[True, (r.lat[a + 1:b] != r.lat[a:b - 1]) | (r.lon[a + 1:b] != r.lon[a:b - 1])]


def _runs(r: Records, i0: int, i1: int, options: SmoothingOptions, counts: Counter) -> list[tuple[int, int]]:
    """The [a, b) row ranges of one aircraft's segments: runs of one ground state, cut
    where two new positions are more than ``max_gap_s`` apart, each from its first new
    position to its last (repeats after the last one, e.g. a receiver that lost the
    aircraft on its landing, are not the aircraft standing still)."""
    out = []
    ground = r.ground[i0:i1]
    flips = np.flatnonzero(ground[1:] != ground[:-1]) + 1
    for a, b in zip([0, *flips.tolist()], [*flips.tolist(), i1 - i0]):
        if ground[a] and not options.keep_ground:
            counts["dropped.ground"] += 1
            continue
        rows = i0 + a + np.flatnonzero(_fresh(r, i0 + a, i0 + b))
        cut = np.flatnonzero(np.diff(r.t[rows]) > options.max_gap_s) + 1
        for run in np.split(rows, cut):
            out.append((int(run[0]), int(run[-1]) + 1))
    return out


def _segment(r: Records, a: int, b: int, frame: LocalFrame, o: SmoothingOptions) -> Segment:
    t = r.t[a:b]
    lat, lon, alt = r.lat[a:b], r.lon[a:b], r.alt[a:b]
    fresh = _fresh(r, a, b)
    has_alt = np.isfinite(alt) & fresh
    if not has_alt.any():
        raise RecordError("no-altitude", "no altitude in the segment")
    # a record without altitude: its horizontal position at the neighbouring altitude (its U is unused)
    alt_filled = np.interp(t, t[has_alt], alt[has_alt])
    pos = frame.to_enu(lat, lon, alt_filled)
    track = np.radians(r.track[a:b])
    ve, vn = r.gs[a:b] * np.sin(track), r.gs[a:b] * np.cos(track)
    has_vh, has_vu = np.isfinite(ve), np.isfinite(r.vrate[a:b])
    vel = _to_origin(frame, lat, lon, np.nan_to_num(ve), np.nan_to_num(vn), np.nan_to_num(r.vrate[a:b]))
    # the horizontal and vertical solves share neither weights nor model
    wzh = np.where(fresh, 1.0 / o.std_pos_h ** 2, 0.0)
    wuh = np.where(has_vh, 1.0 / o.std_vel_h ** 2, 0.0)
    wzv = np.where(has_alt, 1.0 / o.std_pos_v ** 2, 0.0)
    wuv = np.where(has_vu, 1.0 / o.std_vel_v ** 2, 0.0)
    try:
        ph, vh, dh = _robust(t, pos[:, :2], wzh, vel[:, :2], wuh, o.q_h, o.std_pos_h, o.std_vel_h)
        pu, vu, du = _robust(t, pos[:, 2:], wzv, vel[:, 2:], wuv, o.q_v, o.std_pos_v, o.std_vel_v)
    except (LinAlgError, ValueError) as e:
        raise RecordError("singular", f"the records do not fix a path ({e})") from None
    names = r.callsign[a:b][r.callsign[a:b] != ""]
    return Segment(id=str(r.id[a]), callsign=str(names[-1]) if len(names) else "", t=t.copy(),
                   p=np.column_stack([ph, pu]), v=np.column_stack([vh, vu]), on_ground=bool(r.ground[a]),
                   outliers=dh + du)


class Recording:
    """Per-aircraft trajectories of a recording in a site's ENU frame.

    Args:
        records: the recorded state vectors (:func:`read_traffic_json`, :func:`read_jsonl`).
        frame: the site's ENU frame (degrees).
        options: the smoothing model and segmentation.
        window: (start, end) UTC seconds: only records within it.

    Attributes:
        segments: every segment, ordered by aircraft then time.
        counts: records read and used, segments, outliers, and every cause a record or a
            segment was dropped for (``rejected.<cause>``, ``dropped.<cause>``).
    """

    def __init__(self, records: Records, frame: LocalFrame, options: SmoothingOptions = SmoothingOptions(),
                 window: tuple[float, float] | None = None):
        if not frame.deg:
            raise ValueError("the frame's origin must be in degrees (LocalFrame(..., deg=True))")
        self.frame, self.options = frame, options
        self.counts: Counter = Counter({f"rejected.{c}": k for c, k in records.rejected.items()})
        self.counts["records"] = len(records)
        keep = np.ones(len(records), bool)
        if window is not None:
            keep &= (records.t >= window[0]) & (records.t <= window[1])
        same = np.zeros(len(records), bool)  # a second record of the same aircraft at the same time
        same[1:] = (records.id[1:] == records.id[:-1]) & (records.t[1:] == records.t[:-1])
        self.counts["dropped.duplicate"] += int((same & keep).sum())
        keep &= ~same
        r = Records(**{k: getattr(records, k)[keep] for k in ("id", "callsign", "t", "lat", "lon", "alt", "gs",
                                                              "track", "vrate", "ground")})
        self.segments: list[Segment] = []
        starts = np.flatnonzero(np.r_[True, r.id[1:] != r.id[:-1]]) if len(r) else np.empty(0, int)
        for i0, i1 in zip(starts, np.r_[starts[1:], len(r)]):
            for a, b in _runs(r, int(i0), int(i1), options, self.counts):
                if _fresh(r, a, b).sum() < options.min_records:
                    self.counts["dropped.short"] += 1
                    continue
                try:
                    seg = _segment(r, a, b, frame, options)
                except RecordError as e:
                    self.counts[f"dropped.{e.cause}"] += 1
                    continue
                self.segments.append(seg)
                self.counts["used"] += b - a
                self.counts["outliers"] += seg.outliers
        self.counts["segments"] = len(self.segments)
        self._starts = np.array([s.start for s in self.segments])
        self._ends = np.array([s.end for s in self.segments])

    @property
    def start(self) -> float:
        """The first time any aircraft exists (UTC s)."""
        return float(self._starts.min()) if self.segments else math.nan

    @property
    def end(self) -> float:
        return float(self._ends.max()) if self.segments else math.nan

    def aircraft(self) -> list[str]:
        """The aircraft ids, in first-appearance order."""
        return list(dict.fromkeys(s.id for s in sorted(self.segments, key=lambda s: s.start)))

    def alive(self, t: float) -> list[Segment]:
        """The segments that exist at ``t`` (UTC s), by aircraft id."""
        return [self.segments[i] for i in np.flatnonzero((self._starts <= t) & (t <= self._ends))]

    def of(self, aircraft: str) -> list[Segment]:
        """One aircraft's segments in time order."""
        return [s for s in self.segments if s.id == aircraft]


# ------------------------------------------------------------------ a scenario's traffic


class RecordedTraffic:
    """A recording's aircraft as a scenario's traffic (``[truth] file = ...``): every
    segment a target that exists on ``[t0, t1)`` in scenario time (UTC − ``t_zero``),
    named by its aircraft's address (an aircraft seen again after a gap is the same
    target), numbered in order of appearance (its birth order, as ``[traffic]``'s).

    It is its own cursor (:meth:`fleet`, as :class:`sensors_sim.traffic.Traffic`'s), and
    evaluates every segment's Hermite at once: the knots of all segments are one array,
    a segment's found by one ``searchsorted`` on ``segment·span + t``. Before its first
    knot and after its last a segment is extrapolated along its end velocity (a rotating
    radar's root finder may ask there); nothing outside ``[t0, t1)`` is alive.

    Attributes:
        source: the file as the scenario names it.
        t_zero: the UTC time (s) of scenario time 0.
        ids, callsigns, t0, t1: per segment, in birth order.
        max_alive: the most segments alive at once; box: ``(e_min, e_max, n_min, n_max)``
            of every knot (m), as a ``[traffic]`` table's.
        without_adsb: the share of the aircraft that send no ADS-B (the ``adsb``
            emulator draws which, from the seed: :meth:`equipped`).
        counts: the recording's (:class:`Recording`).
    """

    def __init__(self, recording: Recording, t_zero: float, source: str = "", without_adsb: float = 0.0):
        segs = sorted(recording.segments, key=lambda s: (s.start, s.id))
        if not segs:
            raise ValueError("no aircraft")
        self.source, self.t_zero, self.without_adsb = source, float(t_zero), float(without_adsb)
        self.counts = recording.counts
        self.ids = np.array([s.id for s in segs])
        self.callsigns = np.array([s.callsign for s in segs])
        self.t0 = np.array([s.start for s in segs]) - self.t_zero
        self.t1 = np.array([s.end for s in segs]) - self.t_zero
        self._t = np.concatenate([s.t for s in segs]) - self.t_zero
        self._p = np.concatenate([s.p for s in segs])
        self._v = np.concatenate([s.v for s in segs])
        sizes = np.array([len(s.t) for s in segs])
        self._first = np.r_[0, np.cumsum(sizes)[:-1]]
        self._last = self._first + sizes - 1
        self._span = 2.0 * (float(self._t.max()) - min(float(self._t.min()), 0.0)) + 1.0
        self._key = np.repeat(np.arange(len(segs)), sizes) * self._span + self._t
        events = np.r_[np.ones(len(segs)), -np.ones(len(segs))][np.argsort(np.r_[self.t0, self.t1], kind="stable")]
        self.max_alive = int(np.cumsum(events).max())
        self.box = (float(self._p[:, 0].min()), float(self._p[:, 0].max()),
                    float(self._p[:, 1].min()), float(self._p[:, 1].max()))

    def __len__(self) -> int:
        return len(self.ids)

    def fleet(self, t: float) -> "RecordedFleet":
        """The segments alive at ``t`` (``t0 <= t < t1``), in birth order."""
        return RecordedFleet(self, np.flatnonzero((self.t0 <= t) & (t < self.t1)))

    def equipped(self, seed: int) -> frozenset[str]:
        """The aircraft that send ADS-B: all but ``round(without_adsb·n)`` of the ``n``
        addresses, those left out drawn from ``seed`` alone (the same in every run)."""
        names = np.unique(self.ids)
        out = round(self.without_adsb * len(names))
        rng = np.random.Generator(np.random.PCG64(np.random.SeedSequence([int(seed), zlib.crc32(b"adsb")])))
        return frozenset(names[rng.permutation(len(names))[out:]].tolist())

    def kinematics(self, seg: np.ndarray, t) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Position, velocity, acceleration (k, 3) of segments ``seg`` (k,) at ``t`` (one
        time, or one per row): the cubic Hermite between the neighbouring knots."""
        seg = np.asarray(seg, dtype=int)
        t = np.broadcast_to(np.asarray(t, dtype=float), seg.shape)
        a, b = self._first[seg], self._last[seg]
        tc = np.clip(t, self._t[a], self._t[b])
        k = np.clip(np.searchsorted(self._key, seg * self._span + tc, side="right") - 1, a, b - 1)
        h = (self._t[k + 1] - self._t[k])[:, None]
        s = (tc - self._t[k])[:, None]
        s = s / h
        p0, p1, v0, v1 = self._p[k], self._p[k + 1], self._v[k], self._v[k + 1]
        s2, s3 = s * s, s * s * s
        p = (2 * s3 - 3 * s2 + 1) * p0 + (s3 - 2 * s2 + s) * h * v0 + (3 * s2 - 2 * s3) * p1 + (s3 - s2) * h * v1
        v = (6 * s2 - 6 * s) / h * (p0 - p1) + (3 * s2 - 4 * s + 1) * v0 + (3 * s2 - 2 * s) * v1
        acc = (12 * s - 6) / h ** 2 * (p0 - p1) + (6 * s - 4) / h * v0 + (6 * s - 2) / h * v1
        outside = (t != tc)[:, None]
        p = p + np.where(outside, v * (t - tc)[:, None], 0.0)
        return p, v, np.where(outside, 0.0, acc)


class RecordedFleet:
    """Some segments of a :class:`RecordedTraffic`, with the interface of
    :class:`sensors_sim.traffic.Fleet` the emulators and the scoring use."""

    __slots__ = ("traffic", "index")

    def __init__(self, traffic: RecordedTraffic, index: np.ndarray):
        self.traffic, self.index = traffic, np.asarray(index, dtype=int)

    def __len__(self) -> int:
        return len(self.index)

    @property
    def ids(self) -> list[str]:
        return self.traffic.ids[self.index].tolist()

    @property
    def t0(self) -> np.ndarray:
        return self.traffic.t0[self.index]

    @property
    def t1(self) -> np.ndarray:
        return self.traffic.t1[self.index]

    def take(self, rows) -> "RecordedFleet":
        return RecordedFleet(self.traffic, self.index[rows])

    @staticmethod
    def concat(parts: list["RecordedFleet"]) -> "RecordedFleet":
        return RecordedFleet(parts[0].traffic, np.concatenate([p.index for p in parts]))

    def kinematics(self, t, rows=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """As :meth:`sensors_sim.traffic.Fleet.kinematics`."""
        rows = np.arange(len(self.index)) if rows is None else np.asarray(rows, dtype=int)
        return self.traffic.kinematics(self.index[rows], t)

    def positions(self, t) -> np.ndarray:
        return self.kinematics(t)[0]

    def states(self, t) -> np.ndarray:
        return np.concatenate(self.kinematics(t), axis=1)


__all__ = ["FT", "FPM", "KT", "RecordedFleet", "RecordedTraffic", "Records", "Recording", "Segment",
           "SmoothingOptions", "read_jsonl", "read_records", "read_traffic_json", "records_from_dicts", "smooth_axis",
           "traffic_sample"]
