"""CAT048 target reports: every item zfusion reads, from byte strings written from the
specification (edition 1.32), the items it steps over, and a cross-check both ways
with libasterix (MIT; its codec is generated from the machine-readable specifications,
so it shares no code with ours)."""

from __future__ import annotations

import math
import random

import asterix.generated as lib
import pytest
from asterix.base import Bits, RawDatablock

from schemas import asterix as ax
from schemas.asterix import cat048
from schemas.asterix.cat048 import TrackStatus

NM, FT = 1852.0, 0.3048
LIB = lib.Cat_048_1_32

# One record of every item zfusion reads, octet by octet:
PLOT = bytes.fromhex(
    "fd d7 08"         # FSPEC: FRN 1-6; 8, 9, 11, 13, 14; 19
    "19 c9"            # I048/010 SAC 25, SIC 201
    "41 6f 5d"         # I048/140 33502.7265625 s × 128 = 0x416F5D
    "a4"               # I048/020 TYP 5 (Mode S roll-call), SPI, no extension
    "66 c0 20 00"      # I048/040 ρ 102.75 NM × 256 = 0x66C0, θ 45° = 0x2000
    "0f c0"            # I048/070 validated, not garbled, code 7700
    "05 28"            # I048/090 FL 330 × 4 = 0x528
    "4c a2 f1"         # I048/220 address 4CA2F1
    "4d 74 b1 cb 38 20"  # I048/240 "SWR123  ": S=19 W=23 R=18 1=49 2=50 3=51 sp=32 sp=32
    "01 23"            # I048/161 track 291
    "04 00 c0 00"      # I048/200 0.0625 NM/s = 0x0400, heading 270° = 0xC000
    "4c"               # I048/170 RAD 2, MAH, CDM 2 (descending)
    "3f fc"            # I048/110 3D height −100 ft = −4 × 25 ft, 14-bit two's complement
)
WANT = ax.TargetReport(
    sac=25, sic=201, tod=33502.7265625, typ=5, spi=True, rho=102.75 * NM, theta=math.pi / 4, mode3a=0o7700,
    flight_level=330.0, address=0x4CA2F1, callsign="SWR123", track_number=291, ground_speed=0.0625 * NM,
    heading=1.5 * math.pi, track_status=TrackStatus(rad=2, mah=True, cdm=2), height_3d=-100 * FT)


def _one(data: bytes) -> ax.TargetReport:
    (r,) = ax.decode(bytes((48, 0, 3 + len(data))) + data)
    return r


def test_every_item_from_the_specification():
    got = _one(PLOT)
    for f in WANT.__dataclass_fields__:
        want = getattr(WANT, f)
        assert getattr(got, f) == (pytest.approx(want, abs=1e-9) if isinstance(want, float) else want), f
    assert cat048.encode(got) == PLOT  # and back, octet for octet


@pytest.mark.parametrize("item, octets, field, value", [
    ("020", "b1 80", "tst", True),                          # SIM (0x10) and, in the first extension, TST
    ("020", "b1 80", "sim", True),
    ("070", "cf c0", "mode3a_validated", False),            # V = 1: not validated; G = 1: garbled
    ("070", "cf c0", "mode3a_garbled", True),
    ("090", "3f f6", "flight_level", -2.5),                  # −10 quarter-FL
    ("090", "85 28", "fl_validated", False),
    ("161", "0f ff", "track_number", 4095),
    ("170", "c1 c0", "track_status", TrackStatus(cnf=True, rad=2, tre=True, gho=True)),
    ("040", "ff ff ff ff", "theta", 65535 * 2 * math.pi / 65536),
])
def test_single_items(item, octets, field, value):
    frn = cat048.CATEGORY.frn[item]
    fspec = ax.framing.write_fspec(sorted([0, frn]))
    got = getattr(_one(fspec + b"\x19\x01" + bytes.fromhex(octets)), field)
    assert got == (pytest.approx(value) if isinstance(value, float) else value)


# Items zfusion does not read, stepped over by their layouts; written by hand and equal to
# what libasterix encodes for the same values.
STEPPED = bytes.fromhex(
    "83 21 41 04"       # FSPEC: 010, 130; 250; 030; SP (FRN 27)
    "01 02"             # I048/010
    "a0 17 ba"          # I048/130 compound: SRL 23 × 360°/2¹³, SAM −70 dBm
    "01 0112233445566740"  # I048/250 one BDS register
    "03 04"             # I048/030 repetitive with FX: codes 1 and 2
    "03 aa bb"          # SP, explicit length 3
)


def test_compound_repetitive_and_explicit_items_are_stepped_over():
    rec = LIB.cv_record.create({"010": (("SAC", 1), ("SIC", 2)), "130": {"SRL": (1.0, "°"), "SAM": (-70, "dBm")},
                                "250": [(0x1122334455667, 4, 0)], "030": [1, 2], "SP": b"\xaa\xbb"})
    assert LIB.create([rec]).unparse().to_bytes()[3:] == STEPPED
    plot = _one(STEPPED + b"")
    assert (plot.sac, plot.sic, plot.tod) == (1, 2, None)
    # two records in one block: the second is found after the first's stepped-over items
    second = cat048.encode(ax.TargetReport(sac=9, sic=9, tod=1.0))
    recs = ax.decode(bytes((48, 0, 3 + len(STEPPED) + len(second))) + STEPPED + second)
    assert [(r.sac, r.tod) for r in recs] == [(1, None), (9, 1.0)]


def _random_report(rng: random.Random) -> ax.TargetReport:
    return ax.TargetReport(
        sac=rng.randrange(256), sic=rng.randrange(256), tod=rng.randrange(86400 * 128) / 128, typ=rng.randrange(8),
        sim=rng.random() < 0.5, spi=rng.random() < 0.5, rho=rng.randrange(65536) * NM / 256,
        theta=rng.randrange(65536) * 2 * math.pi / 65536, mode3a=rng.randrange(4096),
        mode3a_garbled=rng.random() < 0.5, flight_level=rng.randrange(-1000, 8000) / 4,
        height_3d=rng.randrange(-8192, 8192) * 25 * FT, track_number=rng.randrange(4096),
        track_status=TrackStatus(cnf=rng.random() < 0.5, rad=rng.randrange(4), cdm=rng.randrange(4)),
        ground_speed=rng.randrange(65536) * NM / 16384, heading=rng.randrange(65536) * 2 * math.pi / 65536,
        address=rng.randrange(1 << 24), callsign=rng.choice(["KLM1234", "A", "N12345", "DLH4AB"]))


def test_round_trip_of_every_item():
    rng = random.Random(48)
    for _ in range(200):
        r = _random_report(rng)
        back = ax.decode(ax.encode([r])[0])[0]
        for f in r.__dataclass_fields__:
            want = getattr(r, f)
            assert getattr(back, f) == (pytest.approx(want, abs=1e-9) if isinstance(want, float) else want), f


def _lib_records(data: bytes):
    out = []
    for db in RawDatablock.parse(Bits.from_bytes(data)):
        out.extend(LIB.cv_uap.parse(db.get_raw_records()))
    return out


def test_libasterix_reads_what_we_write():
    rng = random.Random(7)
    reports = [_random_report(rng) for _ in range(50)]
    recs = [r for d in ax.encode(reports) for r in _lib_records(d)]
    assert len(recs) == len(reports)
    for r, lr in zip(reports, recs):
        q = lambda item, sub, unit: lr.get_item(item).variation.get_item(sub).variation.content.as_quantity(unit)  # noqa: E731
        assert lr.get_item("010").variation.get_item("SIC").as_uint() == r.sic
        assert lr.get_item("140").variation.content.as_quantity("s") == pytest.approx(r.tod)
        assert q("040", "RHO", "NM") == pytest.approx(r.rho / NM)
        assert q("040", "THETA", "°") == pytest.approx(math.degrees(r.theta))
        assert q("090", "FL", "FL") == pytest.approx(r.flight_level)
        assert lr.get_item("110").variation.get_item("3DH").variation.content.as_quantity("ft") == \
            pytest.approx(r.height_3d / FT)
        assert int(lr.get_item("070").variation.get_item("MODE3A").variation.content.as_string(), 8) == r.mode3a
        assert lr.get_item("220").variation.content.as_uint() == r.address
        assert lr.get_item("240").variation.content.as_string().rstrip() == r.callsign
        assert lr.get_item("161").variation.get_item("TRN").as_uint() == r.track_number
        assert q("200", "GSP", "NM/s") == pytest.approx(r.ground_speed / NM)
        assert lr.get_item("020").variation.get_item("TYP").as_uint() == r.typ


def test_we_read_what_libasterix_writes():
    rng = random.Random(8)
    for _ in range(30):
        rho, theta, fl = rng.uniform(0, 255), rng.uniform(0, 359.9), rng.randrange(-60, 4000) / 4
        tod, code = rng.uniform(0, 86399), rng.randrange(4096)
        rec = LIB.cv_record.create({
            "010": (("SAC", 3), ("SIC", 4)), "140": (tod, "s"),
            "040": (("RHO", (rho, "NM")), ("THETA", (theta, "°"))),
            "070": (0, 1, 0, 0, ("MODE3A", f"{code:04o}")), "090": (0, 0, ("FL", (fl, "FL"))),
            "220": 0xABCDEF, "240": "EZY12AB ",
        })
        (got,) = ax.decode(LIB.create([rec]).unparse().to_bytes())
        assert got.tod == pytest.approx(tod, abs=1 / 256)
        assert got.rho == pytest.approx(rho * NM, abs=NM / 512)
        assert math.degrees(got.theta) == pytest.approx(theta, abs=360 / 2**17)
        assert got.flight_level == fl and got.mode3a == code and got.mode3a_garbled
        assert (got.address, got.callsign) == (0xABCDEF, "EZY12AB")


def test_values_the_items_cannot_hold_are_refused():
    for bad in (dict(rho=256 * NM), dict(flight_level=3000.0), dict(callsign="lower-case"), dict(track_number=4096)):
        with pytest.raises(ValueError):
            cat048.encode(ax.TargetReport(sac=1, sic=1, theta=0.0, **bad))
