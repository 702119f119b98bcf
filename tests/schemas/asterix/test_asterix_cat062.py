"""CAT062 system tracks (edition 1.21) and CAT065 SDPS status (edition 1.6), the
categories zfusion writes: byte strings written from the specifications, I062/500 from
a covariance, round trips of every item, and libasterix reading what we write."""

from __future__ import annotations

import math
import random

import asterix.generated as lib
import numpy as np
import pytest
from asterix.base import Bits, RawDatablock

from schemas import asterix as ax
from schemas.asterix import cat062, cat065
from schemas.asterix.cat062 import Accuracy, TrackStatus

FT = 0.3048
LIB62, LIB65 = lib.Cat_062_1_21, lib.Cat_065_1_6

TRACK = bytes.fromhex(
    "bf 7d 35 04"        # FSPEC: 010 015 070 105 100 185 | 060 245 380 040 080 | 136 130 220 | 500
    "19 64"              # I062/010 SAC 25 SIC 100
    "04"                 # I062/015 service 4
    "07 08 20"           # I062/070 3600.25 s × 128
    "00 80 00 00 ff 00 00 00"  # I062/105 lat 45° = 2²³ × 180°/2²⁵, lon −90° = −2²⁴ (32-bit)
    "00 07 d1 ff f0 60"  # I062/100 x 1000.5 m = 2001 halves, y −2000 m = −4000 (24-bit)
    "03 20 ff d8"        # I062/185 vx 200 m/s = 800 quarters, vy −10 m/s = −40
    "02 9c"              # I062/060 code 1234
    "00 4d 74 b1 cb 38 20"  # I062/245 STI 0, "SWR123"
    "80 4c a2 f1"        # I062/380 subfield ADR only
    "12 34"              # I062/040 track 0x1234
    "89 21 01 80"        # I062/080 MON, SRC 2 (3D radar) | TSB | (nothing) | CST
    "05 78"              # I062/136 FL 350
    "06 40"              # I062/130 10000 ft = 1600 × 6.25 ft
    "ff 60"              # I062/220 −1000 ft/min = −160 × 6.25 ft/min
    "d4 0064 0078 0014 0a 14 0a"  # I062/500 APC 50, 60 m; COV 10 m; AGA 62.5 ft; ATV 5, 2.5 m/s
)
WANT = ax.SystemTrack(
    sac=25, sic=100, track_number=0x1234, tod=3600.25, service=4, lat=45.0, lon=-90.0, x=1000.5, y=-2000.0,
    vx=200.0, vy=-10.0, status=TrackStatus(mon=True, src=2, tsb=True, cst=True), mode3a=0o1234, callsign="SWR123",
    address=0x4CA2F1, flight_level=350.0, altitude=10000 * FT, rocd=-1000 * FT / 60,
    accuracy=Accuracy(apc_x=50.0, apc_y=60.0, cov_xy=10.0, aga=62.5 * FT, atv_x=5.0, atv_y=2.5))

STATUS = bytes.fromhex(
    "fe"                 # FSPEC: 010 000 015 030 020 040 050
    "19 64 01 04 07 08 20 07"  # SAC 25 SIC 100, SDPS status, service 4, 3600.25 s, batch 7
    "58"                 # I065/040 NOGO 1 (degraded), TSV, PSS 2
    "03"                 # I065/050 main radar out of service
)


def _approx(want):
    return pytest.approx(want, abs=1e-9) if isinstance(want, float) else want


def test_track_from_the_specification():
    (t,) = ax.decode(bytes((62, 0, 3 + len(TRACK))) + TRACK)
    for f in WANT.__dataclass_fields__:
        if f != "accuracy":
            assert getattr(t, f) == _approx(getattr(WANT, f)), f
    for f in Accuracy.__dataclass_fields__:
        assert getattr(t.accuracy, f) == _approx(getattr(WANT.accuracy, f)), f
    assert cat062.encode(t) == TRACK


def test_status_from_the_specification():
    (m,) = ax.decode(bytes((65, 0, 3 + len(STATUS))) + STATUS)
    assert m == ax.SdpsStatus(sac=25, sic=100, message_type=1, service=4, tod=3600.25, batch=7, nogo=1, tsv=True,
                              pss=2, report=3)
    assert cat065.encode(m) == STATUS


def test_accuracies_from_a_covariance():
    P = np.diag([30.0**2, 40.0**2, 100.0**2, 5.0**2, 6.0**2, 2.0**2])
    P[0, 1] = P[1, 0] = -300.0  # sign(cov) · √|cov| = −17.32 m
    a = Accuracy.from_covariance(P, lat=0.0)
    assert (a.apc_x, a.apc_y, a.aga, a.atv_x, a.atv_y, a.arc) == (30.0, 40.0, 100.0, 5.0, 6.0, 2.0)
    assert a.cov_xy == pytest.approx(-math.sqrt(300.0))
    # at the equator a degree of latitude is M·π/180 with M = a(1 − e²); of longitude a·π/180
    assert a.apw_lat == pytest.approx(math.degrees(40.0 / (6378137.0 * (1 - 6.69437999014e-3))), rel=1e-12)
    assert a.apw_lon == pytest.approx(math.degrees(30.0 / 6378137.0), rel=1e-12)
    # saturation: "maximum value means maximum value or above"
    huge = ax.SystemTrack(sac=1, sic=1, track_number=1, tod=0.0, accuracy=Accuracy(apc_x=1e7, apc_y=1.0, aga=1e5))
    back = ax.decode(ax.encode([huge])[0])[0].accuracy
    assert (back.apc_x, back.apc_y, back.aga) == (65535 * 0.5, 1.0, 255 * 6.25 * FT)


def _random(rng: random.Random, k: int) -> ax.SystemTrack:
    return ax.SystemTrack(
        sac=1, sic=2, track_number=k, tod=rng.randrange(86400 * 128) / 128, service=rng.randrange(256),
        lat=rng.randrange(-2**24, 2**24) * 180 / 2**25, lon=rng.randrange(-2**25, 2**25) * 180 / 2**25,
        x=rng.randrange(-2**23, 2**23) / 2, y=rng.randrange(-2**23, 2**23) / 2, vx=rng.randrange(-2**15, 2**15) / 4,
        vy=rng.randrange(-2**15, 2**15) / 4, status=TrackStatus(mon=rng.random() < .5, src=rng.randrange(8),
                                                                cnf=rng.random() < .5, tse=rng.random() < .5),
        mode3a=rng.randrange(4096), callsign=rng.choice([None, "BAW12", "KLM1234"]),
        address=rng.choice([None, rng.randrange(1 << 24)]), flight_level=rng.randrange(-60, 6000) / 4,
        altitude=rng.randrange(-240, 24000) * 6.25 * FT, rocd=rng.randrange(-2**15, 2**15) * 6.25 * FT / 60,
        accuracy=Accuracy(apc_x=rng.randrange(65536) / 2, apc_y=rng.randrange(65536) / 2,
                          cov_xy=rng.randrange(-2**15, 2**15) / 2, apw_lat=rng.randrange(65536) * 180 / 2**25,
                          apw_lon=rng.randrange(65536) * 180 / 2**25, aga=rng.randrange(256) * 6.25 * FT,
                          atv_x=rng.randrange(256) / 4, atv_y=rng.randrange(256) / 4))


def test_round_trip_of_every_item_written():
    rng = random.Random(62)
    tracks = [_random(rng, k) for k in range(100)]
    back = [t for d in ax.encode(tracks, max_octets=1400) for t in ax.decode(d)]
    assert len(back) == len(tracks)
    for t, b in zip(tracks, back):
        for f in t.__dataclass_fields__:
            if f != "accuracy":
                assert getattr(b, f) == _approx(getattr(t, f)), f
        for f in Accuracy.__dataclass_fields__:
            assert getattr(b.accuracy, f) == _approx(getattr(t.accuracy, f)), f


def test_libasterix_reads_what_we_write():
    rng = random.Random(63)
    tracks = [_random(rng, k) for k in range(40)]
    status = ax.SdpsStatus(sac=1, sic=2, message_type=1, service=3, tod=5.5, nogo=0, pss=1)
    recs = []
    for d in ax.encode(tracks + [status]):
        for db in RawDatablock.parse(Bits.from_bytes(d)):
            cls = LIB62 if db.get_category() == 62 else LIB65
            recs.extend(cls.cv_uap.parse(db.get_raw_records()))
    assert len(recs) == len(tracks) + 1
    for t, r in zip(tracks, recs):
        v = lambda item, sub, unit: r.get_item(item).variation.get_item(sub).variation.content.as_quantity(unit)  # noqa: E731
        assert r.get_item("040").variation.content.as_uint() == t.track_number
        assert r.get_item("070").variation.content.as_quantity("s") == pytest.approx(t.tod)
        assert (v("105", "LAT", "°"), v("105", "LON", "°")) == (pytest.approx(t.lat), pytest.approx(t.lon))
        assert (v("100", "X", "m"), v("100", "Y", "m")) == (t.x, t.y)
        assert (v("185", "VX", "m/s"), v("185", "VY", "m/s")) == (t.vx, t.vy)
        assert r.get_item("080").variation.get_item("SRC").as_uint() == t.status.src
        assert r.get_item("130").variation.content.as_quantity("ft") == pytest.approx(t.altitude / FT)
        acc = r.get_item("500").variation
        apc = acc.get_item("APC").variation
        assert apc.get_item("X").variation.content.as_quantity("m") == t.accuracy.apc_x
        assert acc.get_item("COV").variation.content.as_quantity("m") == t.accuracy.cov_xy
        if t.address is not None:
            assert r.get_item("380").variation.get_item("ADR").variation.content.as_uint() == t.address
        if t.callsign is not None:
            assert r.get_item("245").variation.get_item("CHR").variation.content.as_string().rstrip() == t.callsign
    last = recs[-1]
    assert last.get_item("000").as_uint() == 1 and last.get_item("030").variation.content.as_quantity("s") == 5.5
    assert last.get_item("040").variation.get_item("PSS").as_uint() == 1
