"""CAT034 service messages (edition 1.29): north markers and sector crossings from
byte strings written from the specification, round trips, and libasterix both ways."""

from __future__ import annotations

import math
import random

import asterix.generated as lib
import pytest
from asterix.base import Bits, RawDatablock

from schemas import asterix as ax
from schemas.asterix import cat034

LIB = lib.Cat_034_1_29

SECTOR = bytes.fromhex(
    "f9 10"          # FSPEC: 010, 000, 030, 020, 041; 120 (FRN 11)
    "19 01"          # I034/010
    "02"             # I034/000 sector crossing
    "54 60 40"       # I034/030 43200.5 s × 128 = 0x546040
    "40"             # I034/020 sector 90° = 64 × 360°/2⁸
    "02 00"          # I034/041 4.0 s × 128 = 0x0200
    "00 78 20 00 00 c0 00 00"  # I034/120 height 120 m, lat 45° = 2²¹, lon −90° = −2²² (24-bit)
)
NORTH = bytes.fromhex(
    "e4"             # FSPEC: 010, 000, 030, 050
    "19 01 01 54 60 40"
    "88 00 40"       # I034/050 compound: COM and SSR (5th subfield) present
)


def _one(data: bytes):
    (r,) = ax.decode(bytes((34, 0, 3 + len(data))) + data)
    return r


def test_sector_crossing_from_the_specification():
    m = _one(SECTOR)
    assert m == ax.ServiceMessage(sac=25, sic=1, message_type=ax.SECTOR_CROSSING, tod=43200.5, sector=math.pi / 2,
                                  rotation_period=4.0, position=(45.0, -90.0, 120.0))
    assert cat034.encode(m) == SECTOR


def test_north_marker_steps_over_the_status_item():
    m = _one(NORTH)
    assert (m.message_type, m.tod, m.sector) == (ax.NORTH_MARKER, 43200.5, None)


def test_round_trip_and_libasterix_both_ways():
    rng = random.Random(34)
    msgs = [ax.ServiceMessage(sac=rng.randrange(256), sic=rng.randrange(256), message_type=rng.choice((1, 2)),
                              tod=rng.randrange(86400 * 128) / 128, sector=rng.randrange(256) * 2 * math.pi / 256,
                              rotation_period=rng.randrange(1, 2000) / 128) for _ in range(40)]
    data = ax.encode(msgs)
    assert [m for d in data for m in ax.decode(d)] == msgs
    recs = [r for d in data for db in RawDatablock.parse(Bits.from_bytes(d)) for r in LIB.cv_uap.parse(db.get_raw_records())]
    for m, r in zip(msgs, recs, strict=True):
        assert r.get_item("000").as_uint() == m.message_type
        assert r.get_item("030").variation.content.as_quantity("s") == pytest.approx(m.tod)
        assert r.get_item("020").variation.content.as_quantity("°") == pytest.approx(math.degrees(m.sector))
        assert r.get_item("041").variation.content.as_quantity("s") == pytest.approx(m.rotation_period)
    rec = LIB.cv_record.create({"010": (("SAC", 7), ("SIC", 8)), "000": 2, "030": (100.25, "s"), "020": (180.0, "°"),
                                "041": (4.5, "s")})
    assert ax.decode(LIB.create([rec]).unparse().to_bytes()) == [
        ax.ServiceMessage(sac=7, sic=8, message_type=2, tod=100.25, sector=math.pi, rotation_period=4.5)]
