"""CAT034 (monoradar service messages), edition 1.29: a rotating radar's scan timing.

A radar sends a north marker each time its antenna passes north and, with sectorised
output, a sector crossing each time it passes a sector boundary: everything of the
sectors behind the beam has been sent. Read and written (:class:`ServiceMessage`):
I034/000 message type, /010 SAC/SIC, /030 time of day, /020 sector number (the azimuth
of the boundary crossed, 360°/2⁸), /041 antenna rotation period (1/128 s), /120 the
3D position of the data source (WGS-84, 180°/2²³, height in m). The status and
processing-mode items (/050, /060, /070, /090, /100, /110) are stepped over.
"""

from __future__ import annotations

from dataclasses import dataclass

from .framing import Category, Compound, Explicit, Fixed, Repetitive, quantise, sint, time_of_day, uint, wrap
from .units import TOD_LSB, TURN

_STATUS = (("COM", Fixed(1)), None, None, ("PSR", Fixed(1)), ("SSR", Fixed(1)))
CATEGORY = Category(34, "1.29", (
    ("010", Fixed(2)), ("000", Fixed(1)), ("030", Fixed(3)), ("020", Fixed(1)), ("041", Fixed(2)),
    ("050", Compound(_STATUS + (("MDS", Fixed(2)),))), ("060", Compound(_STATUS + (("MDS", Fixed(1)),))),
    ("070", Repetitive(2)), ("100", Fixed(8)), ("110", Fixed(1)), ("120", Fixed(8)), ("090", Fixed(2)),
    ("RE", Explicit()), ("SP", Explicit()),
))

NORTH_MARKER = 1
SECTOR_CROSSING = 2
SECTOR_LSB = TURN / 256.0
LATLON_LSB = 180.0 / 2**23  # degrees


@dataclass(frozen=True, slots=True)
class ServiceMessage:
    """One CAT034 record. ``message_type``: 1 north marker, 2 sector crossing, 3
    geographical filtering, 4 jamming strobe, 5 solar storm, 6 SSR jamming, 7 Mode S
    jamming. ``sector``: azimuth of the boundary crossed (rad); ``rotation_period`` (s);
    ``position``: (lat °, lon °, height m) of the radar."""

    sac: int
    sic: int
    message_type: int
    tod: float | None = None
    sector: float | None = None
    rotation_period: float | None = None
    position: tuple[float, float, float] | None = None

    category = 34


def decode(items: dict[str, bytes]) -> ServiceMessage:
    g = items.get
    src, typ = g("010"), g("000")
    if src is None or typ is None:
        raise ValueError("a CAT034 message needs I034/010 (data source) and I034/000 (message type)")
    kw: dict = {"sac": src[0], "sic": src[1], "message_type": typ[0]}
    if (b := g("030")) is not None:
        kw["tod"] = uint(b) * TOD_LSB
    if (b := g("020")) is not None:
        kw["sector"] = b[0] * SECTOR_LSB
    if (b := g("041")) is not None:
        kw["rotation_period"] = uint(b) * TOD_LSB
    if (b := g("120")) is not None:
        kw["position"] = (sint(uint(b[2:5]), 24) * LATLON_LSB, sint(uint(b[5:8]), 24) * LATLON_LSB,
                          float(sint(uint(b[0:2]), 16)))
    return ServiceMessage(**kw)


def encode(m: ServiceMessage) -> bytes:
    items: dict[str, bytes] = {"010": bytes((m.sac, m.sic)), "000": bytes((m.message_type,))}
    if m.tod is not None:
        items["030"] = time_of_day(m.tod)
    if m.sector is not None:
        items["020"] = bytes((wrap(m.sector, SECTOR_LSB, 8),))
    if m.rotation_period is not None:
        items["041"] = quantise(m.rotation_period, TOD_LSB, 16, False, "I034/041 period").to_bytes(2, "big")
    if m.position is not None:
        lat, lon, h = m.position
        items["120"] = (quantise(h, 1.0, 16, True, "I034/120 height").to_bytes(2, "big")
                        + quantise(lat, LATLON_LSB, 24, True, "I034/120 lat").to_bytes(3, "big")
                        + quantise(lon, LATLON_LSB, 24, True, "I034/120 lon").to_bytes(3, "big"))
    return CATEGORY.join(items)
