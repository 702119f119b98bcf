"""KrakenSDR parsing and conversion (services/ingest/krakensdr.py).

Fixtures in tests/data/krakensdr/ are written from the field lists of the KrakenSDR
software (Kraken App CSV, doa.xml, Kraken Pro JSON, Full POST form), one frame of one
station: θ = 30° (counter-clockwise from the array reference), heading 90°, 433.92 MHz,
-42.5 dB, confidence 3.21. The expected bearings are closed forms: the emitter's
compass bearing is heading + (360 − θ) = 60°; references are geometry (pymap3d's
azimuth between two points), not the code under test.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pymap3d
import pytest

from conftest import DATA as TESTS_DATA
from services.ingest.gateway import Rejected
from services.ingest.krakensdr import (
    Bearing,
    DoaReport,
    KrakenOptions,
    KrakenStation,
    Skipped,
    compass_bearing,
    detect,
    parse,
)

DATA = TESTS_DATA / "krakensdr"
T0 = 1764612000.123
FRAME = ["doa_value_1vfo.csv", "doa.xml", "doa_float_conf.xml", "krakenpro.json", "fullpost.form"]


def body(name: str) -> bytes:
    return (DATA / name).read_bytes()


def bearings(events) -> list[Bearing]:
    return [e for e in events if isinstance(e, Bearing)]


@pytest.mark.parametrize("doa, convention, heading, expected", [
    (30.0, "cw", 90.0, 120.0),     # clockwise 30° from an array pointing east
    (30.0, "ccw", 90.0, 60.0),     # raw θ = 30° counter-clockwise from it
    (330.0, "cw", 90.0, 60.0),     # the CSV's 360 − θ of the same frame
    (360.0, "cw", 0.0, 0.0),       # θ = 0 written as 360
    (0.0, "ccw", 0.0, 0.0),
    (350.0, "cw", 20.0, 10.0),     # wraps past north
    (10.0, "ccw", 5.0, 355.0),     # 5 + 350
    (90.0, "ccw", -90.0, 180.0),   # a negative heading
    (180.0, "cw", 270.0, 90.0),
])
def test_compass_bearing_closed_forms(doa, convention, heading, expected):
    az = compass_bearing(doa, convention, heading)
    assert 0.0 <= az < 2 * math.pi
    assert math.degrees(az) == pytest.approx(expected, abs=1e-12)


def test_cw_and_ccw_are_the_two_readings_of_one_doa():
    rng = np.random.default_rng(3)
    for theta, h in zip(rng.uniform(0, 360, 200), rng.uniform(-360, 720, 200)):
        assert compass_bearing(theta, "ccw", h) == pytest.approx(compass_bearing(360.0 - theta, "cw", h), abs=1e-12)


def test_bearing_matches_the_geometry_of_station_and_emitter():
    """A station with its array reference at compass heading h sees an emitter at compass
    bearing β at θ = h − β counter-clockwise (CSV: 360 − θ); the parsed bearing is β,
    as pymap3d's azimuth from station to emitter says."""
    rng = np.random.default_rng(7)
    lat0, lon0 = 21.0285, 105.8542
    for _ in range(50):
        lat, lon = lat0 + rng.uniform(-0.2, 0.2), lon0 + rng.uniform(-0.2, 0.2)
        beta, _, _ = pymap3d.geodetic2aer(lat, lon, 0.0, lat0, lon0, 0.0)
        h = rng.uniform(0, 360)
        theta = (h - beta) % 360
        csv = (f"{int(T0 * 1000)}, {360 - theta}, 2.0, -40.0, 433920000, UCA, 100, X, {lat0}, {lon0}, {h}, {h}, "
               f"GPS, R, R, R, R\n").encode()
        xml = (f"<DATA><TIME>{int(T0 * 1000)}</TIME><DOA>{theta}</DOA><LOCATION><HEADING>{h}</HEADING>"
               f"</LOCATION></DATA>").encode()
        for doc in (csv, xml):
            (b,) = bearings(KrakenStation("df1").receive(doc))
            err = (math.degrees(b.az) - beta + 180) % 360 - 180
            assert abs(err) < 1e-9


@pytest.mark.parametrize("name", FRAME)
def test_every_encoding_of_one_frame_gives_the_same_bearing(name):
    (b,) = KrakenStation("df1").receive(body(name))
    assert b.sensor == "df1"
    assert b.t == pytest.approx(T0, abs=1e-6)
    assert math.degrees(b.az) == pytest.approx(60.0, abs=1e-9)
    assert (b.lat_deg, b.lon_deg) == (21.0285, 105.8542)
    assert b.freq_hz == pytest.approx(433.92e6)       # MHz in doa.xml, Hz elsewhere
    assert b.power_db == pytest.approx(-42.5)          # PWR = dB + 100 in doa.xml
    assert b.conf == pytest.approx(3.21)               # ×100 int in doa.xml, the float in older firmware


def test_encodings_are_detected_by_content():
    assert [detect(body(n)) for n in FRAME] == ["csv", "xml", "xml", "json", "form"]
    assert detect(b'{"a": 1}', "text/plain") == "json"
    assert detect(b"1764612000123, 330", "application/json") == "json"  # the header wins
    # The df-aggregator quirk: a CSV served where XML was expected still reads.
    (b,) = bearings(KrakenStation("df1").receive(body("doa_value_1vfo.csv"), "auto", "text/xml"))
    assert math.degrees(b.az) == pytest.approx(60.0)


def test_missing_fields_default():
    """No heading (0), no position (None: the site file must pin it), no CONF."""
    (b,) = KrakenStation("df1").receive(body("doa_missing.xml"))
    assert math.degrees(b.az) == pytest.approx(330.0)
    assert b.lat_deg is None and b.conf is None
    (b,) = KrakenStation("df1").receive(body("krakenpro_numbers.json"))  # no gpsBearing, freq a string
    assert math.degrees(b.az) == pytest.approx(330.0) and b.freq_hz == 433.92e6


def test_quirks_of_the_kraken_app_csv():
    events = parse(body("doa_value_quirks.csv"))
    assert len(events) == 8
    r360, compass, empty, torn, short, mhz, bad_time, nan = events
    assert isinstance(r360, DoaReport) and r360.doa_deg == 360.0
    assert compass_bearing(r360.doa_deg, r360.convention, r360.heading_deg) == 0.0
    # Heading source "Compass": the compass heading (45), not the GPS one (0); 0, 0 = no fix.
    assert compass.heading_deg == 45.0 and compass.lat_deg is None and compass.lon_deg is None
    assert math.degrees(compass_bearing(compass.doa_deg, "cw", compass.heading_deg)) == pytest.approx(15.0)
    assert empty.heading_deg is None and empty.lat_deg is None
    assert (torn.cause, short.cause) == ("spectrum", "fields")
    assert mhz.freq_hz == pytest.approx(433.92e6)
    assert bad_time.cause == "value" and nan.cause == "non-finite"
    assert all(isinstance(e, Rejected) for e in (torn, short, bad_time, nan))


def test_vfo_channels():
    doc = body("doa_value_3vfo.csv")
    # Default: VFO 0 (what doa.xml carries), the others skipped.
    ev = KrakenStation("df1").receive(doc)
    assert [type(e) for e in ev] == [Bearing, Skipped, Skipped] and ev[1].cause == "other-vfo"
    # One chosen channel: published under the gateway's id.
    (b,) = bearings(KrakenStation("df1", KrakenOptions(vfos=(446.00625e6,))).receive(doc))
    assert b.sensor == "df1" and math.degrees(b.az) == pytest.approx((90 + 260) % 360)
    # Several: channel k as <id>-<k>; an unlisted frequency is skipped.
    opts = KrakenOptions(vfos=(462.5625e6, 433.92e6))
    ev = KrakenStation("df1", opts).receive(doc)
    assert [(e.sensor, round(math.degrees(e.az), 6)) for e in bearings(ev)] == [("df1-1", 60.0), ("df1-0", 199.5)]
    assert [e.cause for e in ev if isinstance(e, Skipped)] == ["other-vfo"]
    assert opts.channel_ids("df1") == ["df1-0", "df1-1"]
    # Out of the tolerance: skipped.
    assert not bearings(KrakenStation("df1", KrakenOptions(vfos=(433.95e6,))).receive(doc))


def test_second_vfo_post_of_a_frame_is_skipped_but_a_repeat_is_not():
    st = KrakenStation("df1")
    post = json.loads(body("krakenpro.json"))
    other = dict(post, freq=446006250, radioBearing="100")
    assert bearings(st.receive(json.dumps(post).encode()))
    (e,) = st.receive(json.dumps(other).encode())
    assert isinstance(e, Skipped) and e.cause == "other-vfo"
    assert bearings(st.receive(json.dumps(post).encode()))  # the gateway counts it as a repeat


@pytest.mark.parametrize("options, expected", [
    (KrakenOptions(heading="none"), 330.0),
    (KrakenOptions(heading=10.0), 340.0),
    (KrakenOptions(convention="ccw"), 120.0),  # a firmware that writes θ in the CSV
    (KrakenOptions(convention="cw", heading="none"), 330.0),
])
def test_options(options, expected):
    (b,) = KrakenStation("df1", options).receive(body("doa_value_1vfo.csv"))
    assert math.degrees(b.az) == pytest.approx(expected)


def test_confidence_and_station_filters():
    (e,) = KrakenStation("df1", KrakenOptions(min_conf=5.0)).receive(body("doa.xml"))
    assert isinstance(e, Skipped) and e.cause == "low-conf"
    (e,) = KrakenStation("df1", KrakenOptions(station="OTHER")).receive(body("doa.xml"))
    assert isinstance(e, Skipped) and e.cause == "other-station"
    assert bearings(KrakenStation("df1", KrakenOptions(station="KRK1", min_conf=3.0)).receive(body("doa.xml")))


@pytest.mark.parametrize("doc, cause", [
    (b'<?xml version="1.0"?><!DOCTYPE d [<!ENTITY a "aaaa">]><DATA><DOA>&a;</DOA></DATA>', "xml"),
    (b"<DATA><DOA>30</DOA>", "xml"),
    (b"<ROOT><DOA>30</DOA></ROOT>", "xml"),
    (b"<DATA><TIME>1764612000123</TIME><DOA>abc</DOA></DATA>", "value"),
    (b"<DATA><TIME>1764612000123</TIME></DATA>", "missing"),
    (b"<DATA><TIME>1764612000123</TIME><DOA>30</DOA><LOCATION><LATITUDE>95</LATITUDE>"
     b"<LONGITUDE>1</LONGITUDE></LOCATION></DATA>", "range"),
    (b"<DATA><TIME>-5</TIME><DOA>30</DOA></DATA>", "time"),
    (b"<DATA><TIME>1764612000123</TIME><DOA>-30</DOA></DATA>", "range"),  # not wrapped to 330
    (b"<DATA><TIME>1764612000123</TIME><DOA>400</DOA></DATA>", "range"),
    (b'{"tStamp": 1764612000123, "radioBearing": "361"}', "range"),
    (b'{"tStamp": 1764612000123', "json"),
    (b'[1, 2]', "json"),
    (b'{"tStamp": 1764612000123, "radioBearing": "north"}', "value"),
    (b'{"tStamp": 1764612000123, "radioBearing": true}', "value"),
    (b"", "empty"),
    (b"\n \n", "empty"),
    (b"1" * (2 << 20), "too-large"),
])
def test_malformed_documents_are_refused_with_a_cause(doc, cause):
    events = KrakenStation("df1").receive(doc)
    assert events and all(isinstance(e, Rejected) for e in events)
    assert events[0].cause == cause
