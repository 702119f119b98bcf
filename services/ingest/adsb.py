r"""ADS-B receivers, sans I/O: ``aircraft.json`` and SBS-1 text in, position reports out.

Everything that decides what a receiver's output means lives here; HTTP, sockets and
clocks are the process's. Two outputs of readsb, dump1090-fa and tar1090 (which serves
readsb's file) are read (``docs/ingest.md``):

* ``aircraft.json``: ``now`` (UTC s; ms in readsb's ``jv2`` API form) and one object per
  aircraft; a position's **time of validity** is ``now − seen_pos``. ``alt_baro`` is
  pressure altitude (ft, 1013.25 hPa) or ``"ground"``; ``alt_geom`` is above the WGS-84
  ellipsoid (ft) and is preferred. ``hex`` is the 24-bit address, ``~`` first when it is
  not an ICAO address. The source is ``type``, overridden by ``"lat"`` in the ``mlat``
  or ``tisb`` field lists (dump1090-fa omits ``type`` for ``adsb_icao``).
* the BaseStation feed (port 30003): ``MSG,3`` airborne and ``MSG,2`` surface positions,
  ``MSG,4`` velocities, ``MSG,1`` callsigns; the time of validity is the "generated" date
  and time (fields 7–8: when the receiver got the message; 9–10 are when it wrote the
  line), in UTC for readsb and in the receiver's **local time** for dump1090-fa.

Accuracy. NACp bounds the 95 % horizontal error (EPU). For a circular Gaussian of σ per
axis ``P(r ≤ R) = 1 − exp(−R²/2σ²)``, so ``R₉₅ = σ·√(−2 ln 0.05) = 2.4477 σ``::

    σ_h = √((EPU / 2.4477)² + (5.1 m)²/12)        (+ the airborne CPR cell, uniform)

MLAT and TIS-B positions have their own σ (:data:`MLAT_STD_M`, :data:`TISB_STD_M`: the
aircraft's NACp describes its own navigator, not them); no NACp: :data:`DEFAULT_NACP`;
NACp 0 (unknown) is skipped. Vertically: geometric altitude from GVA (or NACp's VEPU),
``σ = bound/1.96``; pressure altitude differs from geometric by the weather (QNH,
temperature) and the geoid, a slowly varying bias stated as :data:`BARO_STD_M`.

:class:`AdsbReceiver` publishes each position once: a repeat (same address and position,
time within :data:`REPEAT_TOL_S`, the files' rounding) or an older position is skipped.
"""

from __future__ import annotations

import calendar
import json
import math
import re
from dataclasses import dataclass, field
from datetime import datetime, timezone
from zoneinfo import ZoneInfo, ZoneInfoNotFoundError

import numpy as np

from fusion.types import Identity

from .gateway import DECODE_ERRORS, Reading, Rejected, undecodable
from .krakensdr import ParseError, Skipped

FT = 0.3048  # m
KT = 1852.0 / 3600.0  # m/s
FPM = FT / 60.0  # m/s
NM = 1852.0  # m

K95_2D = math.sqrt(-2.0 * math.log(0.05))  # 2.4477: the 95 % radius of a circular Gaussian / σ
K95_1D = 1.959963984540054  # the 97.5 % quantile of N(0, 1): a two-sided 95 % bound / σ
# DO-260B NACp: the 95 % bound on the horizontal position error (EPU), metres.
NACP_EPU_M = {11: 3.0, 10: 10.0, 9: 30.0, 8: 0.05 * NM, 7: 0.1 * NM, 6: 0.3 * NM, 5: 0.5 * NM,
              4: 1.0 * NM, 3: 2.0 * NM, 2: 4.0 * NM, 1: 10.0 * NM}
NACP_VEPU_M = {11: 4.0, 10: 15.0, 9: 45.0}  # DO-260A NACp's vertical bound (95 %), metres
GVA_M = {1: 150.0, 2: 45.0}  # DO-260B GVA: 95 % bound on the geometric altitude error, metres
# DO-260B NACv: 95 % bounds on the horizontal and vertical velocity errors, m/s.
NACV_M_S = {1: (10.0, 50 * FT), 2: (3.0, 15 * FT), 3: (1.0, 5 * FT), 4: (0.3, 1.5 * FT)}
CPR_CELL_M = 5.1  # airborne CPR: 6°/2¹⁷ of latitude; uniform error, σ = cell/√12
ALT_STEP_M = 25 * FT  # altitude reported in 25 ft steps; uniform error, σ = step/√12
DEFAULT_NACP = 7  # no NACp: one class below the ADS-B Out mandates' minimum (8)
MLAT_STD_M = 150.0  # multilateration, per horizontal axis (geometry-dependent, outliers expected)
TISB_STD_M = 200.0  # TIS-B (secondary-radar tracks rebroadcast), per horizontal axis
BARO_STD_M = 150.0  # pressure altitude as a stand-in for the geometric one
REPEAT_TOL_S = 0.25  # dump1090-fa rounds now and seen_pos to 0.1 s each
VELOCITY_MAX_AGE_S = 5.0  # SBS: a velocity (MSG,4) older than this is not attached to a position
MAX_BODY = 16 << 20  # bytes; ~700 per aircraft
MAX_ADDRESSES = 10_000  # per receiver: the last position, callsign and velocity of each
SOURCES = ("adsb", "mlat", "tisb", "adsc", "other")
ALT_REFS = ("geometric", "barometric", "ground", "none")

_JSON_SOURCE = {"adsb_icao": "adsb", "adsb_icao_nt": "adsb", "adsr_icao": "adsb", "adsb_other": "adsb",
                "adsr_other": "adsb", "tisb_icao": "tisb", "tisb_other": "tisb", "tisb_trackfile": "tisb",
                "mlat": "mlat", "adsc": "adsc"}  # mode_s, other, unknown and new ones: "other"
_HEX = re.compile(r"~?[0-9a-fA-F]{6}")
_CALLSIGN = re.compile(r"[A-Z0-9 ]{1,8}")
_SBS_DATE = re.compile(r"([0-9]{4})/([0-9]{1,2})/([0-9]{1,2})")
_SBS_TIME = re.compile(r"([0-9]{1,2}):([0-9]{2}):([0-9]{2})(?:\.([0-9]{1,9}))?")
_COUNT = re.compile(r"0*[1-9][0-9]{0,3}")
_MS_THRESHOLD = 1e11  # a ``now`` above this is milliseconds (readsb's jv2 form)
_EPOCH = (1e9, 1e10)  # plausible UTC seconds: 2001 .. 2286
_ALT_FT = (-2000.0, 130_000.0)
_SEEN_MAX_S = 86_400.0
_AUTO_STEP_S = 900.0  # time zones are whole quarter hours
_SBS_NOT_MSG = {"SEL", "ID", "AIR", "STA", "CLK"}


@dataclass(frozen=True)
class PositionReport:
    """One aircraft position at its time of validity, in SI units.

    Attributes:
        t: time of validity, UTC POSIX seconds.
        address: the 24-bit address, six lower-case hex digits; ``~`` first for a
            non-ICAO one (TIS-B track, anonymous): an identity, not a proof of one.
        lat_deg, lon_deg: WGS-84 position, degrees.
        alt_m: altitude (m) as ``alt_ref`` says, or None (``ground``, ``none``).
        alt_ref: ``geometric`` (above the WGS-84 ellipsoid), ``barometric`` (pressure
            altitude), ``ground`` (on the surface, height unknown) or ``none``.
        source: ``adsb``, ``mlat``, ``tisb``, ``adsc`` or ``other`` (:data:`SOURCES`).
        std_h_m: standard deviation per horizontal axis (m).
        std_v_m: standard deviation of ``alt_m`` (m), or None without one.
        callsign: the flight identification, or None.
        velocity_m_s: (east, north) ground velocity at the aircraft (m/s), or None.
        vrate_m_s: vertical rate (m/s, up), or None.
        std_vel_m_s: (horizontal per axis, vertical) velocity std from NACv, or None.
        nac_p: the NACp the accuracy came from, or None.
        fmt: ``json`` or ``sbs``.
    """

    t: float
    address: str
    lat_deg: float
    lon_deg: float
    alt_m: float | None
    alt_ref: str
    source: str
    std_h_m: float
    std_v_m: float | None
    callsign: str | None = None
    velocity_m_s: tuple[float, float] | None = None
    vrate_m_s: float | None = None
    std_vel_m_s: tuple[float, float] | None = None
    nac_p: int | None = None
    fmt: str = "json"


# ------------------------------------------------------------------ accuracy


def nacp_std_m(nac_p: int) -> float:
    """σ per horizontal axis (m) of NACp 1–11: EPU/2.4477 with the CPR cell's σ added
    in quadrature. ValueError for 0 (unknown) and reserved values."""
    if nac_p not in NACP_EPU_M:
        raise ValueError(f"NACp {nac_p}: no accuracy bound (1..11 have one)")
    return math.hypot(NACP_EPU_M[nac_p] / K95_2D, CPR_CELL_M / math.sqrt(12.0))


def horizontal_std(source: str, nac_p: int | None, own_nacp: bool = True) -> float | None:
    """σ per horizontal axis (m) of a position from ``source``; None: unknown (NACp 0).

    ``own_nacp``: the NACp describes this position's source (TIS-B: only when the TIS-B
    message carried it; MLAT: never)."""
    if source == "mlat":
        return MLAT_STD_M
    if source == "tisb" and (nac_p is None or not own_nacp):
        return TISB_STD_M
    if nac_p is None:
        return nacp_std_m(DEFAULT_NACP)
    return nacp_std_m(nac_p) if nac_p in NACP_EPU_M else None


def vertical_std(alt_ref: str, gva: int | None = None, nac_p: int | None = None) -> float | None:
    """σ (m) of an altitude: geometric from GVA, else NACp's VEPU, else GVA 1's bound,
    as a 95 % bound /1.96 with the 25 ft step added; barometric :data:`BARO_STD_M`."""
    if alt_ref == "barometric":
        return BARO_STD_M
    if alt_ref != "geometric":
        return None
    bound = GVA_M.get(gva) or NACP_VEPU_M.get(nac_p) or GVA_M[1]
    return math.hypot(bound / K95_1D, ALT_STEP_M / math.sqrt(12.0))


def velocity_std(nac_v: int | None) -> tuple[float, float] | None:
    """(σ per horizontal axis, σ vertical) in m/s from NACv 1–4; None otherwise."""
    if nac_v not in NACV_M_S:
        return None
    h, v = NACV_M_S[nac_v]
    return h / K95_2D, v / K95_1D


def ground_velocity(gs_kt: float | None, track_deg: float | None) -> tuple[float, float] | None:
    """(east, north) m/s of a ground speed (kt) along a true track (degrees)."""
    if gs_kt is None or track_deg is None:
        return None
    a = math.radians(track_deg)
    return gs_kt * KT * math.sin(a), gs_kt * KT * math.cos(a)


def callsign(value) -> str | None:
    """A flight identification as sent (``A–Z 0–9``, ≤ 8, padded with spaces), or None."""
    if not isinstance(value, str):
        return None
    text = value.strip().upper()
    return text if _CALLSIGN.fullmatch(text) else None


# ------------------------------------------------------------------ aircraft.json


def _num(d: dict, key: str, lo: float = -math.inf, hi: float = math.inf) -> float | None:
    """A finite number within [lo, hi] from a JSON field; None when absent or null."""
    x = d.get(key)
    if x is None:
        return None
    if isinstance(x, bool) or not isinstance(x, (int, float)):
        raise ParseError("value", f"{key}: a {type(x).__name__}, not a number")
    try:
        x = float(x)
    except OverflowError:
        raise ParseError("range", f"{key}: an integer beyond any float") from None
    return _within(x, key, lo, hi)


def _within(x: float, what: str, lo: float, hi: float) -> float:
    """``x`` if finite and in [lo, hi], else the refusal by cause."""
    if not math.isfinite(x):
        raise ParseError("non-finite", f"{what}: {x}")
    if not lo <= x <= hi:
        raise ParseError("range", f"{what}: {x:g} outside [{lo:g}, {hi:g}]")
    return x


def _int(d: dict, key: str, hi: int) -> int | None:
    x = _num(d, key, 0, hi)
    if x is not None and x != int(x):
        raise ParseError("value", f"{key}: {x:g} is not an integer")
    return None if x is None else int(x)


def _fields(d: dict, key: str) -> frozenset:
    """The ``mlat`` / ``tisb`` list: the names of fields derived from that source."""
    x = d.get(key)
    if x is None:
        return frozenset()
    if not isinstance(x, list) or not all(isinstance(s, str) for s in x):
        raise ParseError("value", f"{key}: expected a list of field names")
    return frozenset(x)


def epoch_seconds(value: float, key: str) -> float:
    """UTC seconds from seconds or milliseconds; ParseError outside 2001–2286."""
    t = value / 1000.0 if value >= _MS_THRESHOLD else value
    if not _EPOCH[0] <= t <= _EPOCH[1]:
        raise ParseError("time", f"{key}: {value:g} is not a UTC epoch time")
    return t


def _address(value) -> str:
    if not isinstance(value, str) or not _HEX.fullmatch(value):
        raise ParseError("address", f"hex: {str(value)[:20]!r} is not a 24-bit address")
    return value.lower()


def _aircraft(a: dict, now: float | None) -> PositionReport | Skipped:
    """One aircraft object -> its position report (ParseError when malformed)."""
    address = _address(a.get("hex"))
    own = _num(a, "now", 0.0)  # readsb --json-port: one aircraft per line, its own time
    if own is not None:
        now = epoch_seconds(own, "now")
    lat, lon = _num(a, "lat", -90.0, 90.0), _num(a, "lon", -180.0, 180.0)
    if lat is None or lon is None:
        return Skipped("no-position")
    if now is None:
        raise ParseError("time", f"{address}: no 'now' in the document or the aircraft")
    seen_pos = _num(a, "seen_pos", 0.0, _SEEN_MAX_S)
    if seen_pos is None:
        raise ParseError("missing", f"{address}: a position without seen_pos")
    kind = a.get("type", "adsb_icao")
    if not isinstance(kind, str):
        raise ParseError("value", f"{address}: type is a {type(kind).__name__}")
    mlat, tisb = _fields(a, "mlat"), _fields(a, "tisb")
    source = "mlat" if "lat" in mlat else "tisb" if "lat" in tisb else _JSON_SOURCE.get(kind, "other")
    nac_p = _int(a, "nac_p", 15)
    std_h = horizontal_std(source, nac_p, own_nacp=source != "tisb" or "nac_p" in tisb)
    if std_h is None:
        return Skipped("accuracy-unknown")
    baro = a.get("alt_baro")
    ground = baro == "ground"
    if ground:
        baro = None
    elif baro is not None:
        baro = _num(a, "alt_baro", *_ALT_FT)
    geom = _num(a, "alt_geom", *_ALT_FT)
    if geom is not None:
        alt_m, alt_ref = geom * FT, "geometric"
    elif ground:
        alt_m, alt_ref = None, "ground"
    elif baro is not None:
        alt_m, alt_ref = baro * FT, "barometric"
    else:
        alt_m, alt_ref = None, "none"
    gs, track = _num(a, "gs", 0.0, 5000.0), _num(a, "track", -360.0, 360.0)
    baro_rate, geom_rate = _num(a, "baro_rate", -60_000, 60_000), _num(a, "geom_rate", -60_000, 60_000)
    rate = (geom_rate if geom_rate is not None else baro_rate) if alt_ref == "geometric" else \
        (baro_rate if baro_rate is not None else geom_rate)
    gva = _int(a, "gva", 3)
    return PositionReport(
        t=now - seen_pos, address=address, lat_deg=lat, lon_deg=lon, alt_m=alt_m, alt_ref=alt_ref, source=source,
        std_h_m=std_h, std_v_m=vertical_std(alt_ref, gva, nac_p if source not in ("mlat", "tisb") else None),
        callsign=callsign(a.get("flight")), velocity_m_s=ground_velocity(gs, track),
        vrate_m_s=None if rate is None else rate * FPM, std_vel_m_s=velocity_std(_int(a, "nac_v", 15)),
        nac_p=nac_p, fmt="json")


def parse_aircraft_json(data: bytes | str) -> list[PositionReport | Rejected | Skipped]:
    """An ``aircraft.json`` document (or readsb's one-aircraft ``--json-port`` line, or
    its ``jv2`` API answer) -> one event per aircraft. Never raises."""
    if len(data) > MAX_BODY:
        return [Rejected("too-large", f"{len(data)} bytes > {MAX_BODY}")]
    try:
        doc = json.loads(data)
    except DECODE_ERRORS as e:
        return [undecodable(e, "json")]
    if not isinstance(doc, dict):
        return [Rejected("document", f"expected an object, got a {type(doc).__name__}")]
    if "hex" in doc and "aircraft" not in doc:
        items, now = [doc], None
    else:
        items = doc.get("aircraft", doc.get("ac"))
        if not isinstance(items, list):
            return [Rejected("document", "no 'aircraft' list")]
        try:
            x = _num(doc, "now", 0.0)
            now = None if x is None else epoch_seconds(x, "now")
        except ParseError as e:
            return [Rejected(e.cause, f"aircraft.json: {e}")]
    out: list[PositionReport | Rejected | Skipped] = []
    for i, a in enumerate(items):
        if not isinstance(a, dict):
            out.append(Rejected("aircraft", f"aircraft {i}: a {type(a).__name__}, not an object"))
            continue
        try:
            out.append(_aircraft(a, now))
        except ParseError as e:
            out.append(Rejected(e.cause, f"aircraft {i}: {e}"))
    return out


# ------------------------------------------------------------------ SBS-1 BaseStation


@dataclass(frozen=True)
class SbsPosition:
    """``MSG,2`` (surface) or ``MSG,3`` (airborne): a position at ``t`` (UTC s)."""

    t: float
    address: str
    lat_deg: float
    lon_deg: float
    alt_m: float | None
    alt_ref: str
    on_ground: bool
    mlat: bool
    callsign: str | None
    velocity_m_s: tuple[float, float] | None


@dataclass(frozen=True)
class SbsVelocity:
    """``MSG,4``: ground velocity (east, north m/s) and vertical rate at ``t``."""

    t: float
    address: str
    velocity_m_s: tuple[float, float] | None
    vrate_m_s: float | None


@dataclass(frozen=True)
class SbsIdentification:
    """``MSG,1``: the callsign of an address."""

    t: float
    address: str
    callsign: str


def _text_num(text: str, what: str, lo: float, hi: float) -> float | None:
    """A finite number in [lo, hi] from an SBS field; None when empty."""
    text = text.strip()
    if not text:
        return None
    try:
        x = float(text)
    except ValueError:
        raise ParseError("value", f"{what}: {text[:20]!r} is not a number") from None
    return _within(x, what, lo, hi)


def _naive_seconds(date: str, clock: str) -> float | None:
    """``YYYY/MM/DD`` and ``HH:MM:SS.fff`` read as UTC -> POSIX seconds; None if empty."""
    date, clock = date.strip(), clock.strip()
    if not date and not clock:
        return None
    d, c = _SBS_DATE.fullmatch(date), _SBS_TIME.fullmatch(clock)
    if d is None or c is None:
        raise ParseError("time", f"date/time {date[:12]!r} {clock[:16]!r}")
    y, mo, day = (int(x) for x in d.groups())
    h, mi, s = (int(x) for x in c.groups()[:3])
    if not (1970 <= y <= 2200 and 1 <= mo <= 12 and 1 <= day <= calendar.monthrange(y, mo)[1]
            and h < 24 and mi < 60 and s < 61):
        raise ParseError("time", f"date/time {date} {clock} out of range")
    frac = float("0." + c.group(4)) if c.group(4) else 0.0
    return calendar.timegm((y, mo, day, h, mi, s)) + frac


@dataclass(frozen=True)
class SbsClock:
    """How the SBS date and time become UTC: ``auto`` (the receiver's offset from this
    clock, in whole quarter hours, from the "logged" time of each line), ``UTC``, or an
    IANA zone name (``Europe/Paris``: dump1090-fa writes local time)."""

    zone: str = "auto"

    def __post_init__(self):
        if self.zone not in ("auto", "UTC"):
            try:
                ZoneInfo(self.zone)
            except (ZoneInfoNotFoundError, ValueError, OSError):
                raise ValueError(f"time zone {self.zone!r}: auto, UTC or an IANA name (Europe/Paris)") from None

    def offset(self, local: float, logged: float, now: float) -> float:
        """Seconds to subtract from a date/time read as UTC (``local``) for the real UTC."""
        if self.zone == "UTC":
            return 0.0
        if self.zone == "auto":
            gap = logged - now
            if not abs(gap) <= 14 * 3600 + _AUTO_STEP_S / 2:  # also NaN
                raise ParseError("time", f"the receiver's clock is {gap:+.3g} s from this one: not a time zone")
            return round(gap / _AUTO_STEP_S) * _AUTO_STEP_S
        wall = datetime.fromtimestamp(local, timezone.utc).replace(tzinfo=None)
        return wall.replace(tzinfo=ZoneInfo(self.zone)).utcoffset().total_seconds()


MAX_SBS_LINE = 1024  # characters; a line is ~130


def _sbs_alt(text: str) -> tuple[float | None, str]:
    """Field 12: feet, ``H`` after it when geometric (``--use-gnss``)."""
    text = text.strip()
    geometric = text.endswith("H")
    x = _text_num(text[:-1] if geometric else text, "altitude", *_ALT_FT)
    if x is None:
        return None, "none"
    return x * FT, "geometric" if geometric else "barometric"


def _sbs_velocity(f: list[str]) -> tuple[float, float] | None:
    return ground_velocity(_text_num(f[12], "ground speed", 0.0, 5000.0), _text_num(f[13], "track", -360.0, 360.0))


def parse_sbs_line(line: str, now: float, clock: SbsClock = SbsClock()) \
        -> SbsPosition | SbsVelocity | SbsIdentification | Rejected | Skipped:
    """One BaseStation line (``MSG,…``, 22 comma-separated fields) -> its message.
    ``now`` (UTC s) is this clock, for :class:`SbsClock` ``auto``. Never raises."""
    line = line.strip()
    if len(line) > MAX_SBS_LINE:
        return Rejected("line-too-long", f"{len(line)} characters > {MAX_SBS_LINE}")
    f = line.split(",")
    if f[0] in _SBS_NOT_MSG:
        return Skipped("not-msg")
    if f[0] != "MSG":
        return Rejected("message-type", f"{line[:20]!r} is not an SBS MSG line")
    try:
        if len(f) < 10:
            raise ParseError("fields", f"{len(f)} fields, a MSG line has 22")
        kind = f[1].strip()
        if len(kind) != 1 or kind not in "12345678":
            raise ParseError("message-type", f"MSG,{kind[:8]!r}: transmission types are 1..8")
        kind = int(kind)
        address = _address(f[4].strip())
        generated = _naive_seconds(f[6], f[7])
        logged = _naive_seconds(f[8], f[9])
        if generated is None and logged is None:
            raise ParseError("time", "no date and time")
        local = generated if generated is not None else logged
        t = local - clock.offset(local, logged if logged is not None else local, now)
        if kind == 1:
            cs = callsign(f[10]) if len(f) > 10 else None
            if cs is None:
                raise ParseError("value", f"callsign {f[10][:20] if len(f) > 10 else ''!r}")
            return SbsIdentification(t, address, cs)
        if kind == 4:
            if len(f) < 17:
                raise ParseError("fields", f"{len(f)} fields, MSG,4 needs 17")
            vrate = f[16].strip().removesuffix("H")
            rate = _text_num(vrate, "vertical rate", -60_000, 60_000)
            return SbsVelocity(t, address, _sbs_velocity(f), None if rate is None else rate * FPM)
        if kind not in (2, 3):
            return Skipped("no-position")
        if len(f) < 16:
            raise ParseError("fields", f"{len(f)} fields, MSG,{kind} needs 16")
        lat, lon = _text_num(f[14], "latitude", -90.0, 90.0), _text_num(f[15], "longitude", -180.0, 180.0)
        if lat is None or lon is None:
            return Skipped("no-position")
        if lat == 0.0 and lon == 0.0:
            raise ParseError("position", "0, 0: no position")
        alt_m, alt_ref = _sbs_alt(f[11])
        on_ground = kind == 2 or (len(f) > 21 and f[21].strip() == "-1")
        if on_ground and alt_ref != "geometric":
            alt_m, alt_ref = None, "ground"
        mlat = len(f) > 18 and _COUNT.fullmatch(f[18].strip()) is not None  # mlat-server: receivers used
        return SbsPosition(t, address, lat, lon, alt_m, alt_ref, on_ground, mlat, callsign(f[10]),
                           _sbs_velocity(f))
    except ParseError as e:
        return Rejected(e.cause, f"SBS {f[0]},{f[1][:4] if len(f) > 1 else ''}: {e}")


# ------------------------------------------------------------------ the receiver


def _remember(d: dict, key: str, value) -> None:
    """``d[key] = value`` as the newest entry, forgetting the oldest beyond MAX_ADDRESSES."""
    d.pop(key, None)
    d[key] = value
    if len(d) > MAX_ADDRESSES:
        del d[next(iter(d))]


def position_reading(r: PositionReport, sensor: str) -> Reading | Skipped:
    """A position report as a ``position`` reading of the receiver (or ground station)
    ``sensor``: its WGS-84 position and its own noise (σ per horizontal axis, σ of the
    altitude). One without an altitude (on the ground, or none reported) is no 3D
    position: skipped ``no-altitude``. The reading carries the aircraft's identity (its
    address and callsign), which the tracker keeps on the track."""
    if r.alt_m is None or r.std_v_m is None:
        return Skipped("no-altitude")
    return Reading(sensor=sensor, t=r.t, kind="position", z=None,
                   std=np.array([r.std_h_m, r.std_h_m, r.std_v_m]), geodetic=(r.lat_deg, r.lon_deg, r.alt_m),
                   identity=Identity(r.address, r.callsign))


@dataclass
class AdsbReceiver:
    """One receiver's output -> each new position once, in time order.

    Args:
        clock: how SBS dates become UTC (:class:`SbsClock`).
        sources: the sources to publish (others: skipped ``source``).
        sbs_mlat: the SBS feed carries multilateration results (mlat-client's
            BaseStation output, readsb's MLAT SBS port); otherwise a line is MLAT when
            field 19 holds mlat-server's receiver count.

    State, per address (at most :data:`MAX_ADDRESSES`, the least recent forgotten): the
    last position published; from SBS, the last callsign and velocity.
    """

    clock: SbsClock = field(default_factory=SbsClock)
    sources: frozenset = frozenset(SOURCES)
    sbs_mlat: bool = False
    _last: dict = field(default_factory=dict)
    _callsign: dict = field(default_factory=dict)
    _velocity: dict = field(default_factory=dict)

    def __post_init__(self):
        unknown = set(self.sources) - set(SOURCES)
        if unknown:
            raise ValueError(f"sources {sorted(unknown)}: known are {', '.join(SOURCES)}")

    def receive_json(self, data: bytes | str) -> list[PositionReport | Rejected | Skipped]:
        """An ``aircraft.json`` body: the rejections and skips, then the new positions
        sorted by time."""
        events = parse_aircraft_json(data)
        reports = sorted((e for e in events if isinstance(e, PositionReport)), key=lambda r: (r.t, r.address))
        return [e for e in events if not isinstance(e, PositionReport)] + [self._admit(r) for r in reports]

    def receive_sbs(self, data: bytes | str, now: float) -> list[PositionReport | Rejected | Skipped]:
        """Complete SBS lines (``\\n`` or ``\\r\\n``; blank lines ignored) read at ``now``."""
        text = data.decode("utf-8", "replace") if isinstance(data, (bytes, bytearray)) else data
        out = []
        for line in text.splitlines():
            if not line.strip():
                continue
            m = parse_sbs_line(line, now, self.clock)
            if isinstance(m, SbsIdentification):
                _remember(self._callsign, m.address, m.callsign)
                out.append(Skipped("identification"))
            elif isinstance(m, SbsVelocity):
                _remember(self._velocity, m.address, m)
                out.append(Skipped("velocity"))
            elif isinstance(m, SbsPosition):
                out.append(self._admit(self._sbs_report(m)))
            else:
                out.append(m)
        return out

    def _sbs_report(self, m: SbsPosition) -> PositionReport:
        source = "mlat" if m.mlat or self.sbs_mlat else "adsb"
        cs = m.callsign or self._callsign.get(m.address)
        velocity, vrate = m.velocity_m_s, None
        v = self._velocity.get(m.address)
        if v is not None and abs(v.t - m.t) <= VELOCITY_MAX_AGE_S:
            velocity = velocity or v.velocity_m_s
            vrate = v.vrate_m_s
        return PositionReport(
            t=m.t, address=m.address, lat_deg=m.lat_deg, lon_deg=m.lon_deg, alt_m=m.alt_m, alt_ref=m.alt_ref,
            source=source, std_h_m=horizontal_std(source, None), std_v_m=vertical_std(m.alt_ref), callsign=cs,
            velocity_m_s=velocity, vrate_m_s=vrate, fmt="sbs")

    def _admit(self, r: PositionReport) -> PositionReport | Skipped:
        if r.source not in self.sources:
            return Skipped("source")
        last = self._last.get(r.address)
        if last is not None:
            t, lat, lon = last
            if lat == r.lat_deg and lon == r.lon_deg and abs(r.t - t) <= REPEAT_TOL_S:
                return Skipped("repeat")
            if r.t <= t:
                return Skipped("older")
        _remember(self._last, r.address, (r.t, r.lat_deg, r.lon_deg))
        return r


__all__ = ["AdsbReceiver", "PositionReport", "position_reading", "SbsClock", "SbsIdentification", "SbsPosition", "SbsVelocity",
           "horizontal_std", "nacp_std_m", "parse_aircraft_json", "parse_sbs_line", "vertical_std", "velocity_std"]
