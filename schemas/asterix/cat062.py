"""CAT062 (SDPS track messages), edition 1.21: the system tracks a tracker serves.

Written and read (:class:`SystemTrack`): I062/010 SAC/SIC, /015 service
identification, /070 time of track information (1/128 s), /105 WGS-84 position
(180°/2²⁵), /100 Cartesian position (0.5 m, 24-bit two's complement, in the system's
plane), /185 Cartesian velocity (0.25 m/s), /060 Mode 3/A, /245 target identification,
/380 aircraft-derived data (subfield ADR, the 24-bit address; ID read too), /040 track
number, /080 track status (octets 1, 2 and 4), /136 measured flight level (1/4 FL),
/130 geometric altitude (6.25 ft), /220 rate of climb (6.25 ft/min), /500 estimated
accuracies (:class:`Accuracy`). The rest of the UAP is stepped over.

I062/500 holds standard deviations, each saturating at its largest value ("maximum
value means maximum value or above"), and the xy covariance as
``sign(cov) · √|cov|``: :meth:`Accuracy.from_covariance` takes them from a covariance.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .framing import (
    Category, Compound, Explicit, Extended, Fixed, Repetitive, RepetitiveFX, icao_bytes, icao_chars, quantise,
    sint, time_of_day, uint,
)
from .units import FT, FT_PER_MIN, TOD_LSB

_AGES_290 = (("TRK", 1), ("PSR", 1), ("SSR", 1), ("MDS", 1), ("ADS", 2), ("ES", 1), ("VDL", 1), ("UAT", 1),
             ("LOP", 1), ("MLT", 1))
_AGES_295 = ("MFL", "MD1", "MD2", "MDA", "MD4", "MD5", "MHG", "IAS", "TAS", "SAL", "FSS", "TID", "COM", "SAB",
             "ACS", "BVR", "GVR", "RAN", "TAR", "TAN", "GSP", "VUN", "MET", "EMC", "POS", "GAL", "PUN", "MB", "IAR",
             "MAC", "BPS")
_I380 = (("ADR", Fixed(3)), ("ID", Fixed(6)), ("MHG", Fixed(2)), ("IAS", Fixed(2)), ("TAS", Fixed(2)),
         ("SAL", Fixed(2)), ("FSS", Fixed(2)), ("TIS", Extended()), ("TID", Repetitive(15)), ("COM", Fixed(2)),
         ("SAB", Fixed(2)), ("ACS", Fixed(7)), ("BVR", Fixed(2)), ("GVR", Fixed(2)), ("RAN", Fixed(2)),
         ("TAR", Fixed(2)), ("TAN", Fixed(2)), ("GS", Fixed(2)), ("VUN", Fixed(1)), ("MET", Fixed(8)),
         ("EMC", Fixed(1)), ("POS", Fixed(6)), ("GAL", Fixed(2)), ("PUN", Fixed(1)), ("BDSDATA", Repetitive(8)),
         ("IAR", Fixed(2)), ("MAC", Fixed(2)), ("BPS", Fixed(2)))
_I390 = (("TAG", 2), ("CS", 7), ("IFI", 4), ("FCT", 1), ("TAC", 4), ("WTC", 1), ("DEP", 4), ("DST", 4), ("RDS", 3),
         ("CFL", 2), ("CTL", 2), ("TOD", 0), ("AST", 6), ("STS", 1), ("STD", 7), ("STA", 7), ("PEM", 2), ("PEC", 7))
_I500 = (("APC", Fixed(4)), ("COV", Fixed(2)), ("APW", Fixed(4)), ("AGA", Fixed(1)), ("ABA", Fixed(1)),
         ("ATV", Fixed(2)), ("AA", Fixed(2)), ("ARC", Fixed(1)))
I380 = Compound(_I380)
I500 = Compound(_I500)
CATEGORY = Category(62, "1.21", (
    ("010", Fixed(2)), None, ("015", Fixed(1)), ("070", Fixed(3)), ("105", Fixed(8)), ("100", Fixed(6)),
    ("185", Fixed(4)),
    ("210", Fixed(2)), ("060", Fixed(2)), ("245", Fixed(7)), ("380", I380), ("040", Fixed(2)), ("080", Extended()),
    ("290", Compound(tuple((n, Fixed(k)) for n, k in _AGES_290))),
    ("200", Fixed(1)), ("295", Compound(tuple((n, Fixed(1)) for n in _AGES_295))), ("136", Fixed(2)),
    ("130", Fixed(2)), ("135", Fixed(2)), ("220", Fixed(2)),
    ("390", Compound(tuple((n, Repetitive(4) if k == 0 else Fixed(k)) for n, k in _I390))),
    ("270", Extended()), ("300", Fixed(1)),
    ("110", Compound((("SUM", Fixed(1)), ("PMN", Fixed(4)), ("POS", Fixed(6)), ("GA", Fixed(2)), ("EM1", Fixed(2)),
                      ("TOS", Fixed(1)), ("XP", Fixed(1))))),
    ("120", Fixed(2)), ("510", RepetitiveFX(3)), ("500", I500),
    ("340", Compound((("SID", Fixed(2)), ("POS", Fixed(4)), ("HEIGHT", Fixed(2)), ("MDC", Fixed(2)),
                      ("MDA", Fixed(2)), ("TYP", Fixed(1))))),
    None, None, None, None, None, ("RE", Explicit()), ("SP", Explicit()),
))

LATLON_LSB = 180.0 / 2**25  # degrees
XY_LSB = 0.5  # m
V_LSB = 0.25  # m/s
FL_LSB = 0.25
ALT_LSB = 6.25 * FT
ROCD_LSB = 6.25 * FT_PER_MIN
ACC_LSB = 0.25  # m/s² (AA), m/s (ATV)
AGA_LSB = 6.25 * FT


@dataclass(frozen=True)
class TrackStatus:
    """I062/080: ``mon`` monosensor; ``spi``; ``mrh`` geometric altitude more reliable;
    ``src`` source of I062/130 (0 none, 1 GNSS, 2 3D radar, 3 triangulation, 4 height
    from coverage, 5 speed table, 6 default, 7 multilateration); ``cnf`` tentative;
    ``sim``; ``tse`` last message of the track; ``tsb`` first message; ``cst`` coasting."""

    mon: bool = False
    spi: bool = False
    mrh: bool = False
    src: int = 0
    cnf: bool = False
    sim: bool = False
    tse: bool = False
    tsb: bool = False
    cst: bool = False


@dataclass(frozen=True)
class Accuracy:
    """I062/500 (standard deviations; None: not sent). ``apc_x, apc_y`` (m), ``cov_xy``
    (m, ``sign · √|cov|``), ``apw_lat, apw_lon`` (degrees), ``aga`` geometric altitude
    (m), ``atv_x, atv_y`` (m/s), ``aa_x, aa_y`` (m/s²), ``arc`` rate of climb (m/s)."""

    apc_x: float | None = None
    apc_y: float | None = None
    cov_xy: float | None = None
    apw_lat: float | None = None
    apw_lon: float | None = None
    aga: float | None = None
    atv_x: float | None = None
    atv_y: float | None = None
    aa_x: float | None = None
    aa_y: float | None = None
    arc: float | None = None

    @classmethod
    def from_covariance(cls, P: np.ndarray, lat: float | None = None) -> "Accuracy":
        """From the covariance of a state ``[x, y, z, vx, vy, vz, (ax, ay, az)]`` (ENU, m,
        m/s, m/s²; 6 or 9 rows): σ of each component, the xy term, and, given the
        latitude (degrees), σ of latitude and longitude in degrees on the WGS-84
        ellipsoid (radii of curvature M and N at that latitude)."""
        P = np.asarray(P, dtype=float)
        sd = np.sqrt(np.clip(np.diag(P), 0.0, None))
        cov = float(P[0, 1])
        kw = dict(apc_x=sd[0], apc_y=sd[1], cov_xy=math.copysign(math.sqrt(abs(cov)), cov), aga=sd[2],
                  atv_x=sd[3], atv_y=sd[4], arc=sd[5])
        if len(sd) >= 9:
            kw.update(aa_x=sd[6], aa_y=sd[7])
        if lat is not None:
            a, e2 = 6378137.0, 6.69437999014e-3
            s2 = math.sin(math.radians(lat)) ** 2
            n = a / math.sqrt(1 - e2 * s2)
            m = n * (1 - e2) / (1 - e2 * s2)
            kw.update(apw_lat=math.degrees(sd[1] / m), apw_lon=math.degrees(sd[0] / (n * math.cos(math.radians(lat)))))
        return cls(**{k: float(v) for k, v in kw.items()})


@dataclass(frozen=True, slots=True)
class SystemTrack:
    """One CAT062 record (module docstring for items and units)."""

    sac: int
    sic: int
    track_number: int
    tod: float
    service: int | None = None
    lat: float | None = None  # degrees
    lon: float | None = None
    x: float | None = None  # m
    y: float | None = None
    vx: float | None = None  # m/s
    vy: float | None = None
    status: TrackStatus = TrackStatus()
    mode3a: int | None = None
    callsign: str | None = None
    address: int | None = None
    flight_level: float | None = None  # FL, measured
    altitude: float | None = None  # m, geometric
    rocd: float | None = None  # m/s, rate of climb (+) or descent
    accuracy: Accuracy | None = None

    category = 62


def _acc(b: bytes | None, lsb: float) -> float | None:
    return None if b is None else uint(b) * lsb


def decode(items: dict[str, bytes]) -> SystemTrack:
    g = items.get
    if g("010") is None or g("040") is None or g("070") is None or g("080") is None:
        raise ValueError("a CAT062 track needs I062/010, /040, /070 and /080")
    src = g("010")
    kw: dict = {"sac": src[0], "sic": src[1], "track_number": uint(g("040")), "tod": uint(g("070")) * TOD_LSB}
    if (b := g("015")) is not None:
        kw["service"] = b[0]
    if (b := g("105")) is not None:
        kw["lat"], kw["lon"] = sint(uint(b[:4]), 32) * LATLON_LSB, sint(uint(b[4:]), 32) * LATLON_LSB
    if (b := g("100")) is not None:
        kw["x"], kw["y"] = sint(uint(b[:3]), 24) * XY_LSB, sint(uint(b[3:]), 24) * XY_LSB
    if (b := g("185")) is not None:
        kw["vx"], kw["vy"] = sint(uint(b[:2]), 16) * V_LSB, sint(uint(b[2:]), 16) * V_LSB
    s = Extended().split(g("080"))
    o = [p[0] for p in s] + [0] * 4
    kw["status"] = TrackStatus(mon=bool(o[0] & 0x80), spi=bool(o[0] & 0x40), mrh=bool(o[0] & 0x20),
                               src=(o[0] >> 2) & 7, cnf=bool(o[0] & 0x02), sim=bool(o[1] & 0x80),
                               tse=bool(o[1] & 0x40), tsb=bool(o[1] & 0x20), cst=bool(o[3] & 0x80))
    if (b := g("060")) is not None:
        kw["mode3a"] = uint(b) & 0xFFF
    if (b := g("245")) is not None:
        kw["callsign"] = icao_chars(b[1:])
    if (b := g("380")) is not None:
        sub = I380.split(b)
        if "ADR" in sub:
            kw["address"] = uint(sub["ADR"])
        if "ID" in sub and "callsign" not in kw:
            kw["callsign"] = icao_chars(sub["ID"])
    if (b := g("136")) is not None:
        kw["flight_level"] = sint(uint(b), 16) * FL_LSB
    if (b := g("130")) is not None:
        kw["altitude"] = sint(uint(b), 16) * ALT_LSB
    if (b := g("220")) is not None:
        kw["rocd"] = sint(uint(b), 16) * ROCD_LSB
    if (b := g("500")) is not None:
        sub = I500.split(b)
        apc, apw, atv, aa = sub.get("APC"), sub.get("APW"), sub.get("ATV"), sub.get("AA")
        cov = sub.get("COV")
        kw["accuracy"] = Accuracy(
            apc_x=_acc(apc and apc[:2], XY_LSB), apc_y=_acc(apc and apc[2:], XY_LSB),
            cov_xy=None if cov is None else sint(uint(cov), 16) * XY_LSB,
            apw_lat=_acc(apw and apw[:2], LATLON_LSB), apw_lon=_acc(apw and apw[2:], LATLON_LSB),
            aga=_acc(sub.get("AGA"), AGA_LSB), atv_x=_acc(atv and atv[:1], ACC_LSB),
            atv_y=_acc(atv and atv[1:], ACC_LSB), aa_x=_acc(aa and aa[:1], ACC_LSB), aa_y=_acc(aa and aa[1:], ACC_LSB),
            arc=_acc(sub.get("ARC"), ROCD_LSB))
    return SystemTrack(**kw)


def _sd(x: float, lsb: float, bits: int, what: str) -> bytes:
    return quantise(x, lsb, bits, False, what, saturate=True).to_bytes(bits // 8, "big")


def _pair(a: float | None, b: float | None, lsb: float, bits: int, what: str) -> bytes | None:
    if a is None or b is None:
        return None
    return _sd(a, lsb, bits, what) + _sd(b, lsb, bits, what)


def encode(t: SystemTrack) -> bytes:
    s = t.status
    items: dict[str, bytes | None] = {
        "010": bytes((t.sac, t.sic)),
        "070": time_of_day(t.tod),
        "040": quantise(t.track_number, 1, 16, False, "I062/040 track number").to_bytes(2, "big"),
        "080": Extended.join([
            bytes(((s.mon << 7) | (s.spi << 6) | (s.mrh << 5) | (s.src << 2) | (s.cnf << 1),)),
            bytes(((s.sim << 7) | (s.tse << 6) | (s.tsb << 5),)), b"\x00", bytes((s.cst << 7,))]),
    }
    if t.service is not None:
        items["015"] = bytes((t.service,))
    if t.lat is not None:
        items["105"] = (quantise(t.lat, LATLON_LSB, 32, True, "I062/105 lat").to_bytes(4, "big")
                        + quantise(t.lon, LATLON_LSB, 32, True, "I062/105 lon").to_bytes(4, "big"))
    if t.x is not None:
        items["100"] = (quantise(t.x, XY_LSB, 24, True, "I062/100 x").to_bytes(3, "big")
                        + quantise(t.y, XY_LSB, 24, True, "I062/100 y").to_bytes(3, "big"))
    if t.vx is not None:
        items["185"] = (quantise(t.vx, V_LSB, 16, True, "I062/185 vx").to_bytes(2, "big")
                        + quantise(t.vy, V_LSB, 16, True, "I062/185 vy").to_bytes(2, "big"))
    if t.mode3a is not None:
        items["060"] = (t.mode3a & 0xFFF).to_bytes(2, "big")
    if t.callsign is not None:
        items["245"] = b"\x00" + icao_bytes(t.callsign)
    if t.address is not None:
        items["380"] = I380.join({"ADR": quantise(t.address, 1, 24, False, "I062/380 ADR").to_bytes(3, "big")})
    if t.flight_level is not None:
        items["136"] = quantise(t.flight_level, FL_LSB, 16, True, "I062/136 FL").to_bytes(2, "big")
    if t.altitude is not None:
        items["130"] = quantise(t.altitude, ALT_LSB, 16, True, "I062/130 altitude").to_bytes(2, "big")
    if t.rocd is not None:
        items["220"] = quantise(t.rocd, ROCD_LSB, 16, True, "I062/220 rate of climb").to_bytes(2, "big")
    if (a := t.accuracy) is not None:
        sub = {
            "APC": _pair(a.apc_x, a.apc_y, XY_LSB, 16, "I062/500 APC"),
            "COV": None if a.cov_xy is None else
            quantise(a.cov_xy, XY_LSB, 16, True, "I062/500 COV", saturate=True).to_bytes(2, "big"),
            "APW": _pair(a.apw_lat, a.apw_lon, LATLON_LSB, 16, "I062/500 APW"),
            "AGA": None if a.aga is None else _sd(a.aga, AGA_LSB, 8, "I062/500 AGA"),
            "ATV": _pair(a.atv_x, a.atv_y, ACC_LSB, 8, "I062/500 ATV"),
            "AA": _pair(a.aa_x, a.aa_y, ACC_LSB, 8, "I062/500 AA"),
            "ARC": None if a.arc is None else _sd(a.arc, ROCD_LSB, 8, "I062/500 ARC"),
        }
        if any(v is not None for v in sub.values()):
            items["500"] = I500.join(sub)
    return CATEGORY.join(items)
