"""CAT021 (ADS-B target reports), edition 2.6: what an aircraft says of itself, as a
ground station received it.

Read and written (:class:`AdsbReport`): I021/010 SAC/SIC, /040 target report
descriptor (first octet and first extension), /161 track number, /071 time of
applicability for position, /073 and /074 time of message reception for position
(1/128 s; high precision: full-second indication and 2⁻³⁰ s), /130 and /131 WGS-84
position (180°/2²³; high resolution 180°/2³⁰), /080 target address, /140 geometric
height (6.25 ft), /090 quality indicators (NUCr/NACv, NUCp/NIC, NICbaro, SIL, NACp,
SILS, SDA, GVA, PIC: the raw categories, whose meaning depends on the MOPS version),
/210 MOPS version, /070 Mode 3/A, /145 flight level (1/4 FL), /160 airborne ground
vector (2⁻¹⁴ NM/s, 360°/2¹⁶), /170 target identification. The rest of the UAP is
stepped over.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from .framing import (
    Category, Compound, Explicit, Extended, Fixed, Repetitive, icao_bytes, icao_chars, quantise, sint, time_of_day,
    uint, wrap,
)
from .units import FT, NM, TOD_LSB, TURN

_AGES = ("AOS", "TRD", "M3A", "QI", "TI1", "MAM", "GH", "FL", "SAL", "FSA", "AS", "TAS", "MH", "BVR", "GVR", "GV",
         "TAR", "TI2", "TS", "MET", "ROA", "ARA", "SCC")
CATEGORY = Category(21, "2.6", (
    ("010", Fixed(2)), ("040", Extended()), ("161", Fixed(2)), ("015", Fixed(1)), ("071", Fixed(3)),
    ("130", Fixed(6)), ("131", Fixed(8)),
    ("072", Fixed(3)), ("150", Fixed(2)), ("151", Fixed(2)), ("080", Fixed(3)), ("073", Fixed(3)),
    ("074", Fixed(4)), ("075", Fixed(3)),
    ("076", Fixed(4)), ("140", Fixed(2)), ("090", Extended()), ("210", Fixed(1)), ("070", Fixed(2)),
    ("230", Fixed(2)), ("145", Fixed(2)),
    ("152", Fixed(2)), ("200", Fixed(1)), ("155", Fixed(2)), ("157", Fixed(2)), ("160", Fixed(4)),
    ("165", Fixed(2)), ("077", Fixed(3)),
    ("170", Fixed(6)), ("020", Fixed(1)),
    ("220", Compound((("WS", Fixed(2)), ("WD", Fixed(2)), ("TMP", Fixed(2)), ("TRB", Fixed(1))))),
    ("146", Fixed(2)), ("148", Fixed(2)), ("110", Compound((("TIS", Extended()), ("TID", Repetitive(15))))),
    ("016", Fixed(1)),
    ("008", Fixed(1)), ("271", Extended()), ("132", Fixed(1)), ("250", Repetitive(8)), ("260", Fixed(7)),
    ("400", Fixed(1)), ("295", Compound(tuple((n, Fixed(1)) for n in _AGES))),
    None, None, None, None, None, ("RE", Explicit()), ("SP", Explicit()),
))

LATLON_LSB = 180.0 / 2**23  # degrees
LATLON_HR_LSB = 180.0 / 2**30  # degrees
FRACTION_LSB = 2.0**-30  # s
HEIGHT_LSB = 6.25 * FT
FL_LSB = 0.25
GSP_LSB = NM / 16384.0
ANGLE_LSB = TURN / 65536.0


@dataclass(frozen=True)
class Quality:
    """I021/090, the categories as sent: ``nucr_nacv``, ``nucp_nic``, ``nic_baro``,
    ``sil``, ``nacp``, ``sils``, ``sda``, ``gva``, ``pic``; None where the extension
    holding it was not sent."""

    nucr_nacv: int = 0
    nucp_nic: int = 0
    nic_baro: int | None = None
    sil: int | None = None
    nacp: int | None = None
    sils: int | None = None
    sda: int | None = None
    gva: int | None = None
    pic: int | None = None


@dataclass(frozen=True, slots=True)
class AdsbReport:
    """One CAT021 record (module docstring for items and units). ``atp`` (I021/040):
    0 24-bit ICAO address, 1 duplicate, 2 surface vehicle, 3 anonymous; ``mops``
    (I021/210): 0 DO-260, 1 DO-260A, 2 DO-260B, 3 DO-260C. ``reception_fraction`` and
    ``reception_fsi`` are I021/074 as sent (:meth:`reception_time` combines them)."""

    sac: int
    sic: int
    atp: int | None = None
    gbs: bool = False
    sim: bool = False
    tst: bool = False
    track_number: int | None = None
    tod_position: float | None = None  # I021/071, s
    tod_reception: float | None = None  # I021/073, s
    reception_fsi: int | None = None  # I021/074
    reception_fraction: float | None = None  # I021/074, s
    lat: float | None = None  # degrees (I021/131, else /130)
    lon: float | None = None
    high_resolution: bool = True  # the position came (or goes) as I021/131
    address: int | None = None
    geometric_height: float | None = None  # m
    quality: Quality | None = None
    mops: int | None = None
    mode3a: int | None = None
    flight_level: float | None = None  # FL
    ground_speed: float | None = None  # m/s
    track_angle: float | None = None  # rad
    callsign: str | None = None

    category = 21

    def reception_time(self) -> float | None:
        """Time of message reception for position (s of day): I021/074's fraction on the
        second I021/073 and the full-second indication name; else I021/073."""
        if self.reception_fraction is None or self.tod_reception is None or self.reception_fsi == 3:
            return self.tod_reception
        whole = math.floor(self.tod_reception) + {0: 0, 1: 1, 2: -1}[self.reception_fsi]
        return whole + self.reception_fraction

    def time(self) -> float | None:
        """The position's time of day: its time of applicability, else of reception."""
        return self.tod_position if self.tod_position is not None else self.reception_time()


def _latlon(b: bytes, n: int, lsb: float) -> tuple[float, float]:
    return sint(uint(b[:n]), 8 * n) * lsb, sint(uint(b[n:]), 8 * n) * lsb


def decode(items: dict[str, bytes]) -> AdsbReport:
    g = items.get
    src = g("010")
    if src is None:
        raise ValueError("no I021/010 (data source): the report cannot be attributed")
    kw: dict = {"sac": src[0], "sic": src[1]}
    if (b := g("040")) is not None:
        kw["atp"] = b[0] >> 5
        if len(b) > 1:
            kw.update(gbs=bool(b[1] & 0x40), sim=bool(b[1] & 0x20), tst=bool(b[1] & 0x10))
    if (b := g("161")) is not None:
        kw["track_number"] = ((b[0] & 0x0F) << 8) | b[1]
    if (b := g("071")) is not None:
        kw["tod_position"] = uint(b) * TOD_LSB
    if (b := g("073")) is not None:
        kw["tod_reception"] = uint(b) * TOD_LSB
    if (b := g("074")) is not None:
        kw.update(reception_fsi=b[0] >> 6, reception_fraction=(uint(b) & 0x3FFFFFFF) * FRACTION_LSB)
    if (b := g("131")) is not None:
        kw["lat"], kw["lon"] = _latlon(b, 4, LATLON_HR_LSB)
    elif (b := g("130")) is not None:
        kw["lat"], kw["lon"] = _latlon(b, 3, LATLON_LSB)
        kw["high_resolution"] = False
    if (b := g("080")) is not None:
        kw["address"] = uint(b)
    if (b := g("140")) is not None:
        kw["geometric_height"] = sint(uint(b), 16) * HEIGHT_LSB
    if (b := g("090")) is not None:
        q = {"nucr_nacv": b[0] >> 5, "nucp_nic": (b[0] >> 1) & 0x0F}
        if len(b) > 1:
            q.update(nic_baro=b[1] >> 7, sil=(b[1] >> 5) & 3, nacp=(b[1] >> 1) & 0x0F)
        if len(b) > 2:
            q.update(sils=(b[2] >> 5) & 1, sda=(b[2] >> 3) & 3, gva=(b[2] >> 1) & 3)
        if len(b) > 3:
            q["pic"] = b[3] >> 4
        kw["quality"] = Quality(**q)
    if (b := g("210")) is not None:
        kw["mops"] = (b[0] >> 3) & 7
    if (b := g("070")) is not None:
        kw["mode3a"] = ((b[0] & 0x0F) << 8) | b[1]
    if (b := g("145")) is not None:
        kw["flight_level"] = sint(uint(b), 16) * FL_LSB
    if (b := g("160")) is not None:
        kw["ground_speed"] = (((b[0] & 0x7F) << 8) | b[1]) * GSP_LSB
        kw["track_angle"] = uint(b[2:4]) * ANGLE_LSB
    if (b := g("170")) is not None:
        kw["callsign"] = icao_chars(b)
    return AdsbReport(**kw)


def encode(r: AdsbReport) -> bytes:
    items: dict[str, bytes] = {"010": bytes((r.sac, r.sic))}
    if r.atp is not None:
        items["040"] = Extended.join([bytes((r.atp << 5,)), bytes(((r.gbs << 6) | (r.sim << 5) | (r.tst << 4),))])
    if r.track_number is not None:
        items["161"] = quantise(r.track_number, 1, 12, False, "I021/161 track number").to_bytes(2, "big")
    if r.tod_position is not None:
        items["071"] = time_of_day(r.tod_position)
    if r.tod_reception is not None:
        items["073"] = time_of_day(r.tod_reception)
    if r.reception_fraction is not None:
        frac = quantise(r.reception_fraction, FRACTION_LSB, 30, False, "I021/074 fraction", saturate=True)
        items["074"] = ((r.reception_fsi << 30) | frac).to_bytes(4, "big")
    if r.lat is not None:
        n, lsb, item = (4, LATLON_HR_LSB, "131") if r.high_resolution else (3, LATLON_LSB, "130")
        items[item] = (quantise(r.lat, lsb, 8 * n, True, f"I021/{item} lat").to_bytes(n, "big")
                       + quantise(r.lon, lsb, 8 * n, True, f"I021/{item} lon").to_bytes(n, "big"))
    if r.address is not None:
        items["080"] = quantise(r.address, 1, 24, False, "I021/080 address").to_bytes(3, "big")
    if r.geometric_height is not None:
        items["140"] = quantise(r.geometric_height, HEIGHT_LSB, 16, True, "I021/140 height").to_bytes(2, "big")
    if (q := r.quality) is not None:
        parts = [bytes(((q.nucr_nacv << 5) | (q.nucp_nic << 1),))]
        if q.nacp is not None or q.sil is not None or q.nic_baro is not None or q.gva is not None or q.pic is not None:
            parts.append(bytes((((q.nic_baro or 0) << 7) | ((q.sil or 0) << 5) | ((q.nacp or 0) << 1),)))
        if q.gva is not None or q.sda is not None or q.sils is not None or q.pic is not None:
            parts.append(bytes((((q.sils or 0) << 5) | ((q.sda or 0) << 3) | ((q.gva or 0) << 1),)))
        if q.pic is not None:
            parts.append(bytes((q.pic << 4,)))
        items["090"] = _join_all(parts)
    if r.mops is not None:
        items["210"] = bytes((r.mops << 3 | 2,))  # link technology: 1090 ES
    if r.mode3a is not None:
        items["070"] = (r.mode3a & 0xFFF).to_bytes(2, "big")
    if r.flight_level is not None:
        items["145"] = quantise(r.flight_level, FL_LSB, 16, True, "I021/145 FL").to_bytes(2, "big")
    if r.ground_speed is not None:
        gs = quantise(r.ground_speed, GSP_LSB, 15, False, "I021/160 ground speed")
        items["160"] = ((gs << 16) | wrap(r.track_angle, ANGLE_LSB, 16)).to_bytes(4, "big")
    if r.callsign is not None:
        items["170"] = icao_bytes(r.callsign)
    return CATEGORY.join(items)


def _join_all(parts: list[bytes]) -> bytes:
    """Extended parts kept as given (a quality extension of zeros still says "sent")."""
    return b"".join(bytes((p[0] | (k < len(parts) - 1),)) for k, p in enumerate(parts))
