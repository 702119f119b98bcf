"""ASTERIX framing: FSPEC, the six item layouts, data blocks, and what broken bytes become.

Byte strings are written from the layouts' definitions in the category specifications
(EUROCONTROL ASTERIX Part 1 and the category documents), not produced by the code."""

from __future__ import annotations

import random

import pytest

from schemas import asterix as ax
from schemas.asterix import cat048
from schemas.asterix.framing import (
    AsterixError, Category, Compound, Explicit, Extended, Fixed, Repetitive, RepetitiveFX, block, blocks,
    icao_bytes, icao_chars, quantise, read_fspec, sint, write_fspec,
)


@pytest.mark.parametrize("present, octets", [
    ([0], "80"),                      # FRN 1
    ([0, 1, 2, 3, 4, 5, 6], "fe"),    # FRN 1-7: one octet, FX clear
    ([7], "0180"),                    # FRN 8: a second octet, FX set in the first
    ([0, 10], "8110"),                # FRN 1 and 11 (second octet, fourth bit)
    ([27], "01010102"),               # FRN 28: four octets
])
def test_fspec_both_ways(present, octets):
    assert write_fspec(present).hex() == octets
    got, pos = read_fspec(bytes.fromhex(octets) + b"\xAA", 0, len(octets) // 2 + 1)
    assert (got, pos) == (present, len(octets) // 2)


def test_fspec_running_off_the_end_is_truncated():
    with pytest.raises(AsterixError) as e:
        read_fspec(b"\x81\x01", 0, 2)
    assert e.value.cause == "truncated"


def test_extended_stops_at_the_first_clear_fx():
    x = Extended()
    data = bytes.fromhex("a1 81 40 ff")  # three parts: FX 1, 1, 0
    assert x.end(data, 0, 4) == 3
    assert x.split(data[:3]) == [b"\xa1", b"\x81", b"\x40"]
    assert Extended().end(b"\xa0", 0, 1) == 1
    with pytest.raises(AsterixError) as e:
        x.end(bytes.fromhex("a1 81"), 0, 2)
    assert e.value.cause == "truncated"
    with pytest.raises(AsterixError) as e:
        Extended(parts=2).end(bytes.fromhex("01 01 00"), 0, 3)
    assert e.value.cause == "malformed"


def test_extended_join_sets_fx_and_drops_trailing_zero_extents():
    assert Extended.join([b"\xa0", b"\x80", b"\x00"]).hex() == "a180"
    assert Extended.join([b"\xa0", b"\x00", b"\x80"]).hex() == "a10180"  # an inner zero extent stays
    assert Extended.join([b"\xa0", b"\x00"]).hex() == "a0"


def test_repetitive_counts_its_elements():
    r = Repetitive(2)
    data = bytes.fromhex("02 1111 2222 ff")
    assert r.end(data, 0, 6) == 5
    assert r.split(data[:5]) == [b"\x11\x11", b"\x22\x22"]
    assert r.join([b"\x11\x11", b"\x22\x22"]) == data[:5]
    assert r.end(b"\x00", 0, 1) == 1
    with pytest.raises(AsterixError) as e:
        r.end(bytes.fromhex("03 1111 2222"), 0, 5)
    assert e.value.cause == "truncated"
    with pytest.raises(ValueError):
        r.join([b"\x11"])


def test_repetitive_with_fx_ends_at_the_element_with_fx_clear():
    r = RepetitiveFX(1)
    assert r.end(bytes.fromhex("03 05 08 ff"), 0, 4) == 3
    with pytest.raises(AsterixError):
        r.end(bytes.fromhex("03 05"), 0, 2)


def test_explicit_length_counts_itself():
    assert Explicit().end(bytes.fromhex("03 aa bb cc"), 0, 4) == 3
    assert Explicit().end(b"\x01", 0, 1) == 1
    with pytest.raises(AsterixError) as e:
        Explicit().end(b"\x00", 0, 1)
    assert e.value.cause == "malformed"
    with pytest.raises(AsterixError) as e:
        Explicit().end(bytes.fromhex("05 aa"), 0, 2)
    assert e.value.cause == "truncated"


def test_compound_primary_subfield_with_extension():
    c = Compound((("A", Fixed(1)), None, ("B", Fixed(2)), None, None, None, None, ("H", Repetitive(1))))
    # A (bit 8) and B (bit 6) in the first octet, FX; H (bit 8) in the second
    data = bytes.fromhex("a1 80 11 2222 02 33 44")
    assert c.end(data, 0, len(data)) == len(data)
    assert c.split(data) == {"A": b"\x11", "B": b"\x22\x22", "H": b"\x02\x33\x44"}
    assert c.join({"A": b"\x11", "B": b"\x22\x22", "H": b"\x02\x33\x44"}) == data
    with pytest.raises(AsterixError) as e:
        c.end(bytes.fromhex("40 11"), 0, 2)  # the spare second subfield flagged
    assert e.value.cause == "malformed"


UAP = Category(250, "test", (("A", Fixed(1)), None, ("C", Extended()), ("D", Fixed(2))))


def test_category_splits_a_record_and_joins_it_back():
    data = bytes.fromhex("b0 07 81 00 0102") + b"\xff"
    items, end = UAP.split(data, 0, len(data))
    assert end == 6 and items == {"A": b"\x07", "C": b"\x81\x00", "D": b"\x01\x02"}
    assert UAP.join(items) == data[:6]


@pytest.mark.parametrize("octets, cause", [
    ("c0 07", "malformed"),          # FRN 2 is spare
    ("88 07", "malformed"),          # FRN 5 is beyond the UAP
    ("90 07 0102", "malformed"),     # no: FRN 4 only needs 2 octets; see below
    ("a0 07 81", "truncated"),       # C's extent is missing
    ("90 07 01", "truncated"),       # D needs two octets
    ("00", "malformed"),             # an empty FSPEC
    ("01", "truncated"),             # an FSPEC that never ends
])
def test_category_refuses_broken_records(octets, cause):
    data = bytes.fromhex(octets)
    if octets == "90 07 0102":  # a well-formed record, as the control
        assert UAP.split(data, 0, len(data))[1] == len(data)
        return
    with pytest.raises(AsterixError) as e:
        UAP.split(data, 0, len(data))
    assert e.value.cause == cause


def test_blocks_and_their_headers():
    one = bytes.fromhex("30 0006 80 19 01")
    two = bytes.fromhex("22 0007 c0 19 01 02")
    assert list(blocks(one + two)) == [(48, bytes.fromhex("80 19 01")), (34, bytes.fromhex("c0 19 01 02"))]
    assert block(48, [bytes.fromhex("80 19 01")]) == one
    for data, cause in ((one + b"\x30\x00", "truncated"), (bytes.fromhex("30 0003"), "malformed"),
                        (bytes.fromhex("30 0010 80 19 01"), "truncated")):
        with pytest.raises(AsterixError) as e:
            list(blocks(data))
        assert e.value.cause == cause
    with pytest.raises(ValueError):
        block(48, [])


def test_decode_keeps_going_after_what_it_cannot_read():
    good = bytes.fromhex("30 0006 80 19 01")                     # CAT048, SAC 25 SIC 1
    unknown = bytes.fromhex("f0 0005 80 00")                      # CAT240: not read here
    broken = bytes.fromhex("30 000b 80 19 02 c0 19 03 07 08")     # second record's I048/140 cut short
    no_source = bytes.fromhex("30 0007 40 070800")                # I048/140 without I048/010
    out = ax.decode(good + unknown + broken + no_source + good)
    kinds = [type(x).__name__ if not isinstance(x, ax.Undecodable) else x.cause for x in out]
    assert kinds == ["TargetReport", "unknown-category", "TargetReport", "truncated", "missing-item",
                     "TargetReport"]
    assert [(x.sac, x.sic) for x in out if isinstance(x, ax.TargetReport)] == [(25, 1), (25, 2), (25, 1)]
    tail = ax.decode(good + b"\x30\x00")
    assert isinstance(tail[0], ax.TargetReport) and tail[1].cause == "truncated" and tail[1].cat is None


def test_encode_packs_blocks_into_datagrams():
    plots = [ax.TargetReport(sac=1, sic=k) for k in range(10)]  # 3 octets each
    sector = ax.ServiceMessage(sac=1, sic=0, message_type=ax.SECTOR_CROSSING)
    d = ax.encode(plots[:4] + [sector] + plots[4:])
    assert len(d) == 1 and [c for c, _ in blocks(d[0])] == [48, 34, 48]
    small = ax.encode(plots, max_octets=3 + 3 * 4)  # four records a block, one block a datagram
    assert [len(x) for x in small] == [15, 15, 9]
    assert [r.sic for x in small for r in ax.decode(x)] == list(range(10))


def test_icao_characters():
    # "AB 1" padded: A=1, B=2, space=32, '1'=49, then four spaces (32)
    v = 0
    for code in (1, 2, 32, 49, 32, 32, 32, 32):
        v = (v << 6) | code
    assert icao_bytes("AB 1") == v.to_bytes(6, "big")
    assert icao_chars(v.to_bytes(6, "big")) == "AB 1"
    for bad in ("abcdefghi", "A-1"):
        with pytest.raises(ValueError):
            icao_bytes(bad)


def test_quantise_rounds_checks_and_saturates():
    assert quantise(1.0, 0.25, 8, False, "x") == 4
    assert quantise(-0.25, 0.25, 8, True, "x") == 0xFF
    assert sint(0xFF, 8) == -1 and sint(0x7F, 8) == 127 and sint(0x2000, 14) == -8192
    with pytest.raises(ValueError):
        quantise(64.0, 0.25, 8, False, "x")
    assert quantise(1e9, 0.25, 8, False, "x", saturate=True) == 255


DAY = 86400.0
MIDNIGHT = 1_764_633_600.0  # 2025-12-02 00:00:00 UTC


@pytest.mark.parametrize("tod, now, want", [
    (3600.0, MIDNIGHT + 3600.2, MIDNIGHT + 3600.0),
    (DAY - 0.1, MIDNIGHT + 0.2, MIDNIGHT - 0.1),          # sent before midnight, received after
    (0.1, MIDNIGHT - 0.2, MIDNIGHT + 0.1),                # a clock a little behind
    (43_200.0, MIDNIGHT + 43_200.0 - 60.0, MIDNIGHT + 43_200.0),
])
def test_time_of_day_is_placed_next_to_the_clock(tod, now, want):
    assert ax.utc_of_tod(tod, now) == pytest.approx(want, abs=1e-6)


def test_time_of_day_wraps_at_midnight_on_the_wire():
    r = ax.TargetReport(sac=1, sic=2, tod=DAY + 1.5)  # a UTC second of the next day
    assert ax.decode(ax.encode([r])[0])[0].tod == 1.5
    raw = cat048.encode(ax.TargetReport(sac=1, sic=2, tod=DAY - 1 / 128))
    assert raw[-3:] == bytes.fromhex("a8bfff")  # 86400·128 − 1 = 0xA8BFFF, the largest time of day


def test_mangled_datagrams_never_raise():
    good = ax.encode([ax.TargetReport(sac=1, sic=2, tod=5.0, typ=5, rho=1e4, theta=1.0, mode3a=0o1234,
                                      flight_level=100.0, address=0xABCDEF, callsign="AB12",
                                      track_status=ax.cat048.TrackStatus(rad=2)),
                      ax.ServiceMessage(sac=1, sic=2, message_type=2, tod=5.0, sector=0.5, position=(1.0, 2.0, 3.0)),
                      ax.AdsbReport(sac=3, sic=4, tod_position=5.0, lat=1.0, lon=2.0, address=7,
                                    quality=ax.Quality(nacp=9, gva=1, pic=3), mops=2, callsign="X"),
                      ax.SystemTrack(sac=5, sic=6, track_number=9, tod=5.0, x=1.0, y=2.0, address=5,
                                     accuracy=ax.Accuracy(apc_x=1.0, apc_y=2.0)),
                      ax.SdpsStatus(sac=5, sic=6, message_type=1, service=1, tod=5.0, nogo=0)])[0]
    rng = random.Random(11)
    causes = set()
    for k in range(5000):
        data = bytearray(good)
        if k % 4 == 0:
            data = data[:rng.randrange(len(data))]
        for _ in range(rng.randrange(1, 5)):
            if data:
                data[rng.randrange(len(data))] = rng.randrange(256)
        for r in ax.decode(bytes(data)):
            assert isinstance(r, (ax.Undecodable, ax.TargetReport, ax.ServiceMessage, ax.AdsbReport, ax.SystemTrack,
                                  ax.SdpsStatus))
            if isinstance(r, ax.Undecodable):
                causes.add(r.cause)
    assert causes == {"truncated", "malformed", "unknown-category", "missing-item"}
