"""CAT021 ADS-B reports (edition 2.6): the items zfusion reads from byte strings written
from the specification, the high-precision reception time, round trips, and libasterix
both ways."""

from __future__ import annotations

import math
import random

import asterix.generated as lib
import pytest
from asterix.base import Bits, RawDatablock

from schemas import asterix as ax
from schemas.asterix import cat021

NM, FT = 1852.0, 0.3048
LIB = lib.Cat_021_2_6

REPORT = bytes.fromhex(
    "eb 1d 73 09 80"     # FSPEC: 010 040 161 071 131 | 080 073 074 | 140 090 210 145 | 160 | 170
    "19 c9"              # I021/010
    "01 40"              # I021/040 ATP 0, FX; first extension GBS
    "0a bc"              # I021/161 track 0xABC
    "46 50 00"           # I021/071 36000 s × 128
    "10 00 00 00 e0 00 00 00"  # I021/131 lat 45° = 2²⁸ × 180°/2³⁰, lon −90° = −2²⁹
    "3c 65 86"           # I021/080
    "46 50 40"           # I021/073 36000.5 s
    "b0 00 00 00"        # I021/074 FSI 2 (one second before I021/073's), fraction 0.75 s = 3 × 2²⁸
    "06 40"              # I021/140 10000 ft = 1600 × 6.25 ft
    "31 f3 35 a0"        # I021/090 NACv 1 NIC 8 | NICbaro 1 SIL 3 NACp 9 | SILS 1 SDA 2 GVA 2 | PIC 10
    "12"                 # I021/210 version 2 (DO-260B), link 2 (1090 ES)
    "05 79"              # I021/145 FL 350.25 = 1401 quarters
    "08 00 40 00"        # I021/160 0.125 NM/s = 2048 × 2⁻¹⁴, track angle 90°
    "4d 74 b1 cb 38 20"  # I021/170 "SWR123"
)
WANT = ax.AdsbReport(
    sac=25, sic=201, atp=0, gbs=True, track_number=0xABC, tod_position=36000.0, tod_reception=36000.5,
    reception_fsi=2, reception_fraction=0.75, lat=45.0, lon=-90.0, address=0x3C6586, geometric_height=10000 * FT,
    quality=ax.Quality(nucr_nacv=1, nucp_nic=8, nic_baro=1, sil=3, nacp=9, sils=1, sda=2, gva=2, pic=10), mops=2,
    flight_level=350.25, ground_speed=0.125 * NM, track_angle=math.pi / 2, callsign="SWR123")


def _one(data: bytes):
    (r,) = ax.decode(bytes((21, 0, 3 + len(data))) + data)
    return r


def test_every_item_from_the_specification():
    r = _one(REPORT)
    for f in WANT.__dataclass_fields__:
        want = getattr(WANT, f)
        assert getattr(r, f) == (pytest.approx(want, abs=1e-9) if isinstance(want, float) else want), f
    assert cat021.encode(r) == REPORT
    assert r.reception_time() == 35999.75 and r.time() == 36000.0


@pytest.mark.parametrize("fsi, want", [(0, 36000.75), (1, 36001.75), (2, 35999.75), (3, 36000.5)])
def test_full_second_indication(fsi, want):
    r = ax.AdsbReport(sac=1, sic=1, tod_reception=36000.5, reception_fsi=fsi, reception_fraction=0.75)
    assert r.reception_time() == want
    assert ax.AdsbReport(sac=1, sic=1, tod_reception=36000.5).time() == 36000.5


def test_low_resolution_position_and_short_quality():
    # I021/130 (FRN 6): lat 45° = 2²¹ × 180°/2²³; I021/090 without extensions (a DO-260 NUCp)
    data = bytes.fromhex("85 01 20"  # FSPEC: FRN 1 and 6 | none | FRN 17
                         "19c9 200000 c00000 0e")
    r = _one(data)
    assert (r.lat, r.lon, r.high_resolution) == (45.0, -90.0, False)
    assert r.quality == ax.Quality(nucr_nacv=0, nucp_nic=7)
    assert cat021.encode(r) == data


def _random(rng: random.Random) -> ax.AdsbReport:
    return ax.AdsbReport(
        sac=rng.randrange(256), sic=rng.randrange(256), atp=rng.randrange(4), track_number=rng.randrange(4096),
        tod_position=rng.randrange(86400 * 128) / 128, tod_reception=rng.randrange(86400 * 128) / 128,
        lat=rng.randrange(-2**30 // 2, 2**30 // 2) * 180 / 2**30, lon=rng.randrange(-2**31, 2**31) * 180 / 2**30,
        address=rng.randrange(1 << 24), geometric_height=rng.randrange(-240, 24000) * 6.25 * FT,
        quality=ax.Quality(nucr_nacv=rng.randrange(8), nucp_nic=rng.randrange(16), nic_baro=rng.randrange(2),
                           sil=rng.randrange(4), nacp=rng.randrange(12), gva=rng.randrange(4)),
        mops=rng.randrange(4), flight_level=rng.randrange(-60, 6000) / 4, callsign="AFR1234")


def test_round_trip_and_libasterix_both_ways():
    rng = random.Random(21)
    reports = [_random(rng) for _ in range(60)]
    data = ax.encode(reports)
    back = [m for d in data for m in ax.decode(d)]
    for r, b in zip(reports, back, strict=True):
        for f in r.__dataclass_fields__:
            want = getattr(r, f)
            if f == "quality":  # the third extension goes out (GVA), with SILS and SDA as 0
                want = ax.Quality(**{**want.__dict__, "sils": 0, "sda": 0})
            assert getattr(b, f) == (pytest.approx(want, abs=1e-9) if isinstance(want, float) else want), f
    recs = [r for d in data for db in RawDatablock.parse(Bits.from_bytes(d)) for r in LIB.cv_uap.parse(db.get_raw_records())]
    for r, lr in zip(reports, recs, strict=True):
        pos = lr.get_item("131").variation
        assert pos.get_item("LAT").variation.content.as_quantity("°") == pytest.approx(r.lat, abs=1e-12)
        assert pos.get_item("LON").variation.content.as_quantity("°") == pytest.approx(r.lon, abs=1e-12)
        assert lr.get_item("071").variation.content.as_quantity("s") == pytest.approx(r.tod_position)
        assert lr.get_item("140").variation.content.as_quantity("ft") == pytest.approx(r.geometric_height / FT)
        assert lr.get_item("080").variation.content.as_uint() == r.address
        q = lr.get_item("090").variation
        assert (q.get_item("NACP").as_uint(), q.get_item("NUCPNIC").as_uint(), q.get_item("GVA").as_uint()) == \
            (r.quality.nacp, r.quality.nucp_nic, r.quality.gva)
    rec = LIB.cv_record.create({
        "010": (("SAC", 1), ("SIC", 2)), "071": (1234.5, "s"), "080": 0x00ABCD,
        "131": (("LAT", (52.3, "°")), ("LON", (4.76, "°"))), "140": (35000.0, "ft"),
        "090": ((1, 9, None), (0, 2, 10, None), (0, 0, 0, 1, None))})
    (got,) = ax.decode(LIB.create([rec]).unparse().to_bytes())
    assert (got.lat, got.lon) == (pytest.approx(52.3, abs=180 / 2**31), pytest.approx(4.76, abs=180 / 2**31))
    assert (got.tod_position, got.address, got.geometric_height) == (1234.5, 0xABCD, pytest.approx(35000 * FT))
    assert (got.quality.nucp_nic, got.quality.sil, got.quality.nacp, got.quality.gva) == (9, 2, 10, 1)
