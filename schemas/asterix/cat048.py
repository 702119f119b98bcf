"""CAT048 (monoradar target reports), edition 1.32: a radar's plots, and the items a
tracker reads from them.

Read and written (:class:`TargetReport`): I048/010 SAC/SIC, /140 time of day, /020 the
target report descriptor (first octet and first extension), /040 measured position in
polar co-ordinates, /070 Mode 3/A, /090 flight level, /110 the height a 3D radar
measured, /161 track number, /170 track status (first octet and first extension),
/200 track velocity in polar co-ordinates, /220 aircraft address, /240 aircraft
identification. Every other item of the UAP is stepped over by its layout.

Scales (from the specification): time 1/128 s; ρ 1/256 NM, θ 360°/2¹⁶; flight level
1/4 FL (14-bit two's complement); 3D height 25 ft (14-bit two's complement); ground
speed 2⁻¹⁴ NM/s, heading 360°/2¹⁶. θ is clockwise from north at the radar, as zfusion
counts azimuth. An absent item is None (or False for a flag).
"""

from __future__ import annotations

from dataclasses import dataclass

from .framing import (
    Category, Compound, Explicit, Extended, Fixed, Repetitive, RepetitiveFX, icao_bytes, icao_chars, quantise,
    sint, time_of_day, uint, wrap,
)
from .units import FT, NM, TOD_LSB, TURN

CATEGORY = Category(48, "1.32", (
    ("010", Fixed(2)), ("140", Fixed(3)), ("020", Extended()), ("040", Fixed(4)), ("070", Fixed(2)),
    ("090", Fixed(2)), ("130", Compound(tuple((n, Fixed(1)) for n in ("SRL", "SRR", "SAM", "PRL", "PAM", "RPD",
                                                                       "APD")))),
    ("220", Fixed(3)), ("240", Fixed(6)), ("250", Repetitive(8)), ("161", Fixed(2)), ("042", Fixed(4)),
    ("200", Fixed(4)), ("170", Extended()),
    ("210", Fixed(4)), ("030", RepetitiveFX(1)), ("080", Fixed(2)), ("100", Fixed(4)), ("110", Fixed(2)),
    ("120", Compound((("CAL", Fixed(2)), ("RDS", Repetitive(6))))), ("230", Fixed(2)),
    ("260", Fixed(7)), ("055", Fixed(1)), ("050", Fixed(2)), ("065", Fixed(1)), ("060", Fixed(2)),
    ("SP", Explicit()), ("RE", Explicit()),
))

RHO_LSB = NM / 256.0
THETA_LSB = TURN / 65536.0
FL_LSB = 0.25
HEIGHT_LSB = 25.0 * FT
GSP_LSB = NM / 16384.0


@dataclass(frozen=True)
class TrackStatus:
    """I048/170: ``cnf`` tentative track; ``rad`` 0 combined, 1 PSR, 2 SSR/Mode S, 3
    invalid; ``dou`` low confidence in plot-to-track association; ``mah`` horizontal
    manoeuvre; ``cdm`` 0 maintaining, 1 climbing, 2 descending, 3 unknown; ``tre`` end of
    track; ``gho`` ghost."""

    cnf: bool = False
    rad: int = 0
    dou: bool = False
    mah: bool = False
    cdm: int = 0
    tre: bool = False
    gho: bool = False


@dataclass(frozen=True, slots=True)
class TargetReport:
    """One CAT048 record (module docstring for items and units).

    ``typ`` (I048/020): 0 no detection, 1 PSR, 2 SSR, 3 SSR + PSR, 4 Mode S all-call,
    5 Mode S roll-call, 6 all-call + PSR, 7 roll-call + PSR. ``mode3a`` is the code as
    an integer whose octal digits are the code (``0o7700``).
    """

    sac: int
    sic: int
    tod: float | None = None
    typ: int | None = None
    sim: bool = False
    rdp: bool = False
    spi: bool = False
    rab: bool = False
    tst: bool = False
    rho: float | None = None  # m
    theta: float | None = None  # rad
    mode3a: int | None = None
    mode3a_validated: bool = True
    mode3a_garbled: bool = False
    flight_level: float | None = None  # FL
    fl_validated: bool = True
    fl_garbled: bool = False
    height_3d: float | None = None  # m
    track_number: int | None = None
    track_status: TrackStatus | None = None
    ground_speed: float | None = None  # m/s
    heading: float | None = None  # rad
    address: int | None = None  # the 24-bit Mode S address
    callsign: str | None = None

    category = 48


def decode(items: dict[str, bytes]) -> TargetReport:
    """The items of one record (:meth:`Category.split`) -> a :class:`TargetReport`."""
    g = items.get
    src = g("010")
    if src is None:
        raise ValueError("no I048/010 (data source): the record cannot be attributed")
    kw: dict = {"sac": src[0], "sic": src[1]}
    if (b := g("140")) is not None:
        kw["tod"] = uint(b) * TOD_LSB
    if (b := g("020")) is not None:
        o = b[0]
        kw.update(typ=o >> 5, sim=bool(o & 0x10), rdp=bool(o & 0x08), spi=bool(o & 0x04), rab=bool(o & 0x02))
        if len(b) > 1:
            kw["tst"] = bool(b[1] & 0x80)
    if (b := g("040")) is not None:
        kw["rho"] = ((b[0] << 8) | b[1]) * RHO_LSB
        kw["theta"] = ((b[2] << 8) | b[3]) * THETA_LSB
    if (b := g("070")) is not None:
        kw.update(mode3a=((b[0] & 0x0F) << 8) | b[1], mode3a_validated=not b[0] & 0x80,
                  mode3a_garbled=bool(b[0] & 0x40))
    if (b := g("090")) is not None:
        kw.update(flight_level=sint((b[0] << 8) | b[1], 14) * FL_LSB, fl_validated=not b[0] & 0x80,
                  fl_garbled=bool(b[0] & 0x40))
    if (b := g("110")) is not None:
        kw["height_3d"] = sint((b[0] << 8) | b[1], 14) * HEIGHT_LSB
    if (b := g("161")) is not None:
        kw["track_number"] = ((b[0] & 0x0F) << 8) | b[1]
    if (b := g("170")) is not None:
        o = b[0]
        e = b[1] if len(b) > 1 else 0
        kw["track_status"] = TrackStatus(cnf=bool(o & 0x80), rad=(o >> 5) & 3, dou=bool(o & 0x10),
                                         mah=bool(o & 0x08), cdm=(o >> 1) & 3, tre=bool(e & 0x80),
                                         gho=bool(e & 0x40))
    if (b := g("200")) is not None:
        kw["ground_speed"] = ((b[0] << 8) | b[1]) * GSP_LSB
        kw["heading"] = ((b[2] << 8) | b[3]) * THETA_LSB
    if (b := g("220")) is not None:
        kw["address"] = uint(b)
    if (b := g("240")) is not None:
        kw["callsign"] = icao_chars(b)
    return TargetReport(**kw)


def encode(r: TargetReport) -> bytes:
    """A :class:`TargetReport` -> one record's octets (ValueError for a value the items
    cannot hold)."""
    items: dict[str, bytes | None] = {"010": bytes((r.sac, r.sic))}
    if r.tod is not None:
        items["140"] = time_of_day(r.tod)
    if r.typ is not None:
        first = (r.typ << 5) | (r.sim << 4) | (r.rdp << 3) | (r.spi << 2) | (r.rab << 1)
        items["020"] = Extended.join([bytes((first,)), bytes((r.tst << 7,))])
    if r.rho is not None:
        rho = quantise(r.rho, RHO_LSB, 16, False, "I048/040 rho")
        items["040"] = ((rho << 16) | wrap(r.theta, THETA_LSB, 16)).to_bytes(4, "big")
    if r.mode3a is not None:
        flags = ((not r.mode3a_validated) << 15) | (r.mode3a_garbled << 14)
        items["070"] = (flags | (r.mode3a & 0xFFF)).to_bytes(2, "big")
    if r.flight_level is not None:
        flags = ((not r.fl_validated) << 15) | (r.fl_garbled << 14)
        items["090"] = (flags | quantise(r.flight_level, FL_LSB, 14, True, "I048/090 FL")).to_bytes(2, "big")
    if r.height_3d is not None:
        items["110"] = quantise(r.height_3d, HEIGHT_LSB, 14, True, "I048/110 height").to_bytes(2, "big")
    if r.track_number is not None:
        items["161"] = quantise(r.track_number, 1, 12, False, "I048/161 track number").to_bytes(2, "big")
    if (s := r.track_status) is not None:
        first = (s.cnf << 7) | (s.rad << 5) | (s.dou << 4) | (s.mah << 3) | (s.cdm << 1)
        items["170"] = Extended.join([bytes((first,)), bytes(((s.tre << 7) | (s.gho << 6),))])
    if r.ground_speed is not None:
        gsp = quantise(r.ground_speed, GSP_LSB, 16, False, "I048/200 ground speed")
        items["200"] = ((gsp << 16) | wrap(r.heading, THETA_LSB, 16)).to_bytes(4, "big")
    if r.address is not None:
        items["220"] = quantise(r.address, 1, 24, False, "I048/220 address").to_bytes(3, "big")
    if r.callsign is not None:
        items["240"] = icao_bytes(r.callsign)
    return CATEGORY.join(items)
