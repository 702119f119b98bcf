"""ADS-B receiver parsing and conversion (services/ingest/adsb.py).

Fixtures in tests/data/adsb/ (README.md there says which documentation each follows) are
one scene near Paris on 2021-10-07 around 12:12:53 UTC. Expected values are closed forms
written here from the standards (DO-260B NACp/NACv/GVA tables, the foot, knot and
nautical mile) and the formats' documentation, not taken from the code under test; the
95 % factors are checked against scipy's distributions.
"""

from __future__ import annotations

import calendar
import dataclasses
import json
import math
from collections import Counter

import numpy as np
import pytest
from scipy import stats

from fusion.geodetic import LocalFrame
from fusion.types import Identity
from schemas import KeySpace, decode, to_measurement
from services.node import RejectLog

from conftest import DATA as TESTS_DATA
from services.ingest import adsb
from services.ingest.adsb import (
    AdsbReceiver,
    position_reading,
    PositionReport,
    SbsClock,
    SbsIdentification,
    SbsPosition,
    SbsVelocity,
    horizontal_std,
    nacp_std_m,
    parse_aircraft_json,
    parse_sbs_line,
    velocity_std,
    vertical_std,
)
from services.ingest.gateway import Gateway, Rejected, SensorSite
from services.ingest.krakensdr import Skipped

DATA = TESTS_DATA / "adsb"
FOOT, KNOT, FPM = 0.3048, 1852.0 / 3600.0, 0.3048 / 60.0
T_SCENE = calendar.timegm((2021, 10, 7, 12, 12, 53))  # 1633608773
R95 = math.sqrt(stats.chi2(2).ppf(0.95))  # 95 % radius / σ of a circular Gaussian (Rayleigh)
Z95 = stats.norm.ppf(0.975)  # two-sided 95 % bound / σ
CPR = 5.1 / math.sqrt(12.0)  # airborne CPR cell, uniform
STEP = 25 * FOOT / math.sqrt(12.0)  # 25 ft altitude step, uniform
# DO-260B NACp: EPU < 3 m, 10 m, 30 m, 0.05 NM, 0.1, 0.3, 0.5, 1, 2, 4, 10 NM for 11 .. 1
EPU = {11: 3.0, 10: 10.0, 9: 30.0, 8: 0.05 * 1852, 7: 0.1 * 1852, 6: 0.3 * 1852, 5: 0.5 * 1852,
       4: 1852.0, 3: 2 * 1852.0, 2: 4 * 1852.0, 1: 10 * 1852.0}


def body(name: str) -> bytes:
    return (DATA / name).read_bytes()


def reports(events) -> dict[str, PositionReport]:
    return {e.address: e for e in events if isinstance(e, PositionReport)}


def causes(events, cls) -> Counter:
    return Counter(e.cause for e in events if isinstance(e, cls))


def velocity(gs_kt: float, track_deg: float) -> tuple[float, float]:
    a = math.radians(track_deg)
    return gs_kt * KNOT * math.sin(a), gs_kt * KNOT * math.cos(a)


# ------------------------------------------------------------------ accuracy classes


def test_95_percent_factors_are_the_distributions():
    assert adsb.K95_2D == pytest.approx(R95, rel=1e-12)
    assert adsb.K95_1D == pytest.approx(Z95, rel=1e-12)


@pytest.mark.parametrize("nac_p", range(1, 12))
def test_nacp_is_its_epu_as_a_95_percent_radius(nac_p):
    sigma = nacp_std_m(nac_p)
    assert sigma == pytest.approx(math.hypot(EPU[nac_p] / R95, CPR), rel=1e-12)
    # without the CPR cell, a circular Gaussian of that σ has 95 % of its mass within the EPU
    core = math.sqrt(sigma ** 2 - CPR ** 2)
    assert stats.chi2(2).cdf((EPU[nac_p] / core) ** 2) == pytest.approx(0.95, abs=1e-12)


@pytest.mark.parametrize("nac_p", [0, 12, 15, -1])
def test_nacp_without_a_bound_has_no_sigma(nac_p):
    with pytest.raises(ValueError):
        nacp_std_m(nac_p)
    assert horizontal_std("adsb", nac_p) is None


def test_horizontal_std_per_source():
    assert horizontal_std("adsb", None) == nacp_std_m(adsb.DEFAULT_NACP) == pytest.approx(math.hypot(185.2 / R95, CPR))
    assert horizontal_std("mlat", 11) == adsb.MLAT_STD_M  # the aircraft's NACp is not the MLAT's
    assert horizontal_std("tisb", 9, own_nacp=False) == adsb.TISB_STD_M
    assert horizontal_std("tisb", 9, own_nacp=True) == nacp_std_m(9)
    assert horizontal_std("tisb", None) == adsb.TISB_STD_M
    assert horizontal_std("other", 10) == nacp_std_m(10)


def test_vertical_std():
    assert vertical_std("geometric", gva=2) == pytest.approx(math.hypot(45 / Z95, STEP))
    assert vertical_std("geometric", gva=1) == pytest.approx(math.hypot(150 / Z95, STEP))
    assert vertical_std("geometric", gva=0, nac_p=10) == pytest.approx(math.hypot(15 / Z95, STEP))  # VEPU
    assert vertical_std("geometric", nac_p=8) == pytest.approx(math.hypot(150 / Z95, STEP))  # no VEPU below 9
    assert vertical_std("barometric", gva=2) == adsb.BARO_STD_M
    assert vertical_std("ground") is None and vertical_std("none") is None


@pytest.mark.parametrize("nac_v, h, v", [(1, 10.0, 50), (2, 3.0, 15), (3, 1.0, 5), (4, 0.3, 1.5)])
def test_nacv(nac_v, h, v):
    assert velocity_std(nac_v) == pytest.approx((h / R95, v * FOOT / Z95))


@pytest.mark.parametrize("nac_v", [None, 0, 5, 7])
def test_nacv_unknown(nac_v):
    assert velocity_std(nac_v) is None


@pytest.mark.parametrize("text, expected", [
    ("MSR799  ", "MSR799"), ("afr1234", "AFR1234"), ("A B", "A B"), ("", None), ("    ", None),
    ("DLH@12", None), ("ABCDEFGHI", None), (None, None), (42, None)])
def test_callsign(text, expected):
    assert adsb.callsign(text) == expected


# ------------------------------------------------------------------ aircraft.json


def test_readsb_document():
    events = parse_aircraft_json(body("readsb_aircraft.json"))
    r = reports(events)
    assert set(r) == {"0101de", "3944ef", "4ca7b1", "~2a1f0c", "3c6586", "a1b2c3"}
    assert causes(events, Skipped) == Counter({"no-position": 2, "accuracy-unknown": 1})
    assert not causes(events, Rejected)
    now = T_SCENE + 0.5

    a = r["0101de"]  # ADS-B, NACp 9, GVA 2, geometric altitude preferred to barometric
    assert a.t == pytest.approx(now - 0.4, abs=1e-9)
    assert (a.lat_deg, a.lon_deg) == (48.482437, 3.828806)
    assert (a.alt_ref, a.alt_m) == ("geometric", pytest.approx(13900 * FOOT))
    assert a.source == "adsb" and a.callsign == "MSR799" and a.nac_p == 9 and a.fmt == "json"
    assert a.std_h_m == pytest.approx(math.hypot(30 / R95, CPR))
    assert a.std_v_m == pytest.approx(math.hypot(45 / Z95, STEP))
    assert a.velocity_m_s == pytest.approx(velocity(325.0, 311.14))
    assert a.vrate_m_s == pytest.approx(-928 * FPM)  # the geometric rate with the geometric altitude
    assert a.std_vel_m_s == pytest.approx((3 / R95, 15 * FOOT / Z95))

    g = r["3944ef"]  # on the surface: no height
    assert (g.alt_ref, g.alt_m, g.std_v_m) == ("ground", None, None)
    assert g.t == pytest.approx(now - 1.25, abs=1e-9)
    assert g.std_h_m == pytest.approx(math.hypot(10 / R95, CPR))

    m = r["4ca7b1"]  # MLAT: its own σ, although the aircraft's ADS-B said NACp 8
    assert (m.source, m.std_h_m, m.nac_p) == ("mlat", adsb.MLAT_STD_M, 8)
    assert (m.alt_ref, m.alt_m, m.std_v_m) == ("barometric", pytest.approx(24000 * FOOT), adsb.BARO_STD_M)
    assert m.vrate_m_s == 0.0

    tis = r["~2a1f0c"]  # a non-ICAO address keeps its ~
    assert (tis.source, tis.std_h_m) == ("tisb", adsb.TISB_STD_M)
    assert tis.t == pytest.approx(now - 3.0, abs=1e-9)

    v0 = r["3c6586"]  # a version 0 transponder: no NACp, pressure altitude only
    assert v0.nac_p is None and v0.std_h_m == nacp_std_m(adsb.DEFAULT_NACP)
    assert (v0.alt_ref, v0.alt_m, v0.std_v_m) == ("barometric", pytest.approx(36000 * FOOT), adsb.BARO_STD_M)
    assert v0.velocity_m_s == pytest.approx(velocity(452.0, 92.5)) and v0.std_vel_m_s is None

    c = r["a1b2c3"]  # ADS-C: an old position, no NACp
    assert c.source == "adsc" and c.t == pytest.approx(now - 412.0, abs=1e-9)
    assert c.std_h_m == nacp_std_m(adsb.DEFAULT_NACP)


def test_a_position_carries_its_aircrafts_identity_to_the_wire():
    """Each reading of the readsb scene, through the gateway: the published measurement
    carries the aircraft's address and callsign (none: the address alone), and two
    aircraft at one position at one time are two measurements, not a repeat."""
    r = reports(parse_aircraft_json(body("readsb_aircraft.json")))
    gw = Gateway({"rx": SensorSite("rx", "position", np.array([30.0, 30.0, 45.0]), None)},
                 LocalFrame(48.85, 2.35, 0.0, deg=True), KeySpace("t"), RejectLog("gw"), max_age=1e6)
    now = T_SCENE + 0.5
    got = {}
    for report in sorted((x for x in r.values() if x.alt_m is not None), key=lambda x: x.t):
        reading = position_reading(report, "rx")
        assert reading.identity == Identity(report.address, report.callsign)
        (_, data), *_ = gw.offer(reading, now)
        got[report.address] = to_measurement(decode(data)).identity
    assert got["0101de"] == Identity("0101de", "MSR799") and got["~2a1f0c"] == Identity("~2a1f0c", None)
    twin = dataclasses.replace(r["0101de"], address="0101df", callsign=None)
    (_, data), *_ = gw.offer(position_reading(twin, "rx"), now)
    assert to_measurement(decode(data)).identity == Identity("0101df", None) and gw.counters["repeats"] == 0


def test_dump1090fa_document():
    events = parse_aircraft_json(body("dump1090fa_aircraft.json"))
    r = reports(events)
    now = T_SCENE + 1.0
    a = r["0101de"]  # dump1090-fa omits type for adsb_icao
    assert a.source == "adsb" and a.t == pytest.approx(now - 0.3, abs=1e-9)
    assert a.alt_m == pytest.approx(13875 * FOOT) and a.vrate_m_s == pytest.approx(-864 * FPM)
    assert r["3944ef"].alt_ref == "ground"
    m = r["4ca7b1"]  # no type: MLAT is told by the mlat field list
    assert (m.source, m.std_h_m) == ("mlat", adsb.MLAT_STD_M)
    assert r["a4c2d1"].std_h_m == pytest.approx(math.hypot(185.2 / R95, CPR))  # TIS-B's own NACp 7
    assert r["a4c2d2"].std_h_m == adsb.TISB_STD_M  # NACp 9, but not from the TIS-B message
    assert causes(events, Skipped) == Counter({"no-position": 1})


def test_malformed_records_are_counted_by_cause():
    events = parse_aircraft_json(body("malformed.json"))
    assert causes(events, Rejected) == Counter({"address": 2, "missing": 1, "range": 3, "non-finite": 2,
                                                "value": 5, "aircraft": 1})
    assert causes(events, Skipped) == Counter({"no-position": 1})
    ok = reports(events)["3944ff"]
    assert (ok.alt_ref, ok.alt_m, ok.std_v_m) == ("none", None, None)
    assert len(events) == 16  # one event per aircraft


def test_json_port_lines_carry_their_own_now():
    lines = body("readsb_jsonport.jsonl").splitlines()
    a, b = (reports(parse_aircraft_json(x))["0101de"] for x in lines)
    assert a.t == pytest.approx(T_SCENE + 0.5, abs=1e-9)
    assert b.t == pytest.approx(T_SCENE + 1.0, abs=1e-9)


def test_jv2_answer_in_milliseconds():
    doc = json.loads(body("readsb_aircraft.json"))
    jv2 = {"now": doc["now"] * 1000.0, "ac": doc["aircraft"], "total": len(doc["aircraft"])}
    a = reports(parse_aircraft_json(json.dumps(jv2)))
    b = reports(parse_aircraft_json(body("readsb_aircraft.json")))
    assert a.keys() == b.keys()
    assert all(a[k].t == pytest.approx(b[k].t, abs=1e-6) for k in a)


@pytest.mark.parametrize("data, cause", [
    (b"", "json"),
    (b"not json", "json"),
    (b"[" * 200_000 + b"]" * 200_000, "too-deep"),  # RecursionError inside the decoder
    (b'{"now": 1633608774, "aircraft": ' + b"[" * 100_000 + b"]" * 100_000 + b"}", "too-deep"),
    (b'\xff\xfe\x00{"now"', "encoding"),  # not decodable
    (b"[]", "document"),
    (b'{"now": 1633608774}', "document"),
    (b'{"now": 1633608774, "aircraft": {}}', "document"),
    (b'{"now": "yesterday", "aircraft": []}', "value"),
    (b'{"now": 12, "aircraft": []}', "time"),
    (b'{"now": 1e300, "aircraft": []}', "time"),
    (b'{"now": NaN, "aircraft": []}', "non-finite"),
    (b'{"now": ' + b"9" * 400 + b', "aircraft": []}', "range"),  # an int beyond any float
    (b'{"now": ' + b"9" * 5000 + b', "aircraft": []}', "json"),  # beyond int's digit limit
])
def test_bad_documents(data, cause):
    events = parse_aircraft_json(data)
    assert [type(e) for e in events] == [Rejected] and events[0].cause == cause


def test_a_position_needs_now():
    events = parse_aircraft_json(b'{"aircraft": [{"hex": "0101de", "lat": 48.5, "lon": 2.5, "seen_pos": 1}]}')
    assert causes(events, Rejected) == Counter({"time": 1})


def test_too_large(monkeypatch):
    monkeypatch.setattr(adsb, "MAX_BODY", 1000)
    assert parse_aircraft_json(b" " * 1001)[0].cause == "too-large"


# ------------------------------------------------------------------ the receiver: repeats


def test_stale_repeats_are_not_published_again():
    rx = AdsbReceiver()
    first = rx.receive_json(body("dump1090fa_aircraft.json"))
    assert len(reports(first)) == 5
    again = rx.receive_json(body("dump1090fa_aircraft.json"))  # the same page polled twice
    assert not reports(again) and causes(again, Skipped)["repeat"] == 5
    nxt = rx.receive_json(body("dump1090fa_aircraft_next.json"))
    # 0101de moved; 3944ef is the same position at the same now − seen_pos; 4ca7b1's
    # derived time moved by 0.1 s, the rounding of now and seen_pos to 0.1 s each
    assert set(reports(nxt)) == {"0101de"}
    assert causes(nxt, Skipped) == Counter({"repeat": 2})


def test_an_older_position_is_skipped():
    rx = AdsbReceiver()
    newer, older = (json.dumps({"now": T_SCENE + 10, "aircraft": [
        {"hex": "0101de", "lat": lat, "lon": 2.5, "seen_pos": age}]}) for lat, age in [(48.5, 1.0), (48.4, 3.0)])
    assert len(reports(rx.receive_json(newer))) == 1
    assert causes(rx.receive_json(older), Skipped) == Counter({"older": 1})


def test_reports_come_out_in_time_order():
    out = [e for e in AdsbReceiver().receive_json(body("readsb_aircraft.json")) if isinstance(e, PositionReport)]
    assert [e.t for e in out] == sorted(e.t for e in out)
    assert len(out) == 6


def test_sources_filter():
    rx = AdsbReceiver(sources=frozenset({"adsb"}))
    events = rx.receive_json(body("readsb_aircraft.json"))
    assert {r.source for r in reports(events).values()} == {"adsb"}
    assert causes(events, Skipped)["source"] == 3  # mlat, tisb, adsc
    with pytest.raises(ValueError):
        AdsbReceiver(sources=frozenset({"radar"}))


def test_memory_is_bounded(monkeypatch):
    monkeypatch.setattr(adsb, "MAX_ADDRESSES", 50)
    rx = AdsbReceiver()
    aircraft = [{"hex": f"{i:06x}", "lat": 48.0 + i * 1e-3, "lon": 2.5, "seen_pos": 0.5} for i in range(200)]
    assert len(reports(rx.receive_json(json.dumps({"now": T_SCENE, "aircraft": aircraft})))) == 200
    assert len(rx._last) == 50
    lines = "\n".join(f"MSG,1,1,1,{i:06X},1,2021/10/07,12:12:53.000,2021/10/07,12:12:53.000,C{i}" for i in range(200))
    rx.receive_sbs(lines, T_SCENE)
    assert len(rx._callsign) == 50 and "0000c7" in rx._callsign and "000000" not in rx._callsign


# ------------------------------------------------------------------ SBS-1


def sbs_events(name: str, now: float, **kw) -> list:
    return AdsbReceiver(**kw).receive_sbs(body(name), now)


def test_sbs_dump1090fa_local_time():
    events = sbs_events("sbs_dump1090fa.txt", T_SCENE + 1.0, clock=SbsClock("Europe/Paris"))
    positions = [e for e in events if isinstance(e, PositionReport)]
    assert [(p.address, p.t) for p in positions] == [
        ("0101de", pytest.approx(T_SCENE + 0.1, abs=1e-6)),  # 14:12:53.100 CEST, generated
        ("3944ef", pytest.approx(T_SCENE + 0.3, abs=1e-6)),
        ("0101de", pytest.approx(T_SCENE + 0.6, abs=1e-6))]
    a, g, b = positions
    assert (a.lat_deg, a.lon_deg) == (48.48244, 3.82881)
    assert (a.alt_ref, a.alt_m, a.std_v_m) == ("barometric", pytest.approx(13650 * FOOT), adsb.BARO_STD_M)
    assert a.callsign == "MSR799" and a.source == "adsb" and a.fmt == "sbs"
    assert a.std_h_m == nacp_std_m(adsb.DEFAULT_NACP)  # SBS carries no NACp
    assert a.velocity_m_s == pytest.approx(velocity(325, 311)) and a.vrate_m_s == pytest.approx(-896 * FPM)
    assert (g.alt_ref, g.alt_m) == ("ground", None) and g.velocity_m_s == pytest.approx(velocity(12, 265))
    assert b.velocity_m_s == a.velocity_m_s  # MSG,4 0.61 s before: still attached
    assert causes(events, Skipped) == Counter({"identification": 1, "velocity": 1, "no-position": 2, "repeat": 1})
    assert causes(events, Rejected) == Counter({"fields": 1})  # the torn line; blank lines are heartbeats


def test_sbs_auto_time_zone_equals_the_stated_one():
    stated = sbs_events("sbs_dump1090fa.txt", T_SCENE + 1.0, clock=SbsClock("Europe/Paris"))
    auto = sbs_events("sbs_dump1090fa.txt", T_SCENE + 1.0)
    assert [r.t for r in reports(auto).values()] == [r.t for r in reports(stated).values()]
    # taken for UTC, a CEST receiver's positions are two hours in the future
    utc = sbs_events("sbs_dump1090fa.txt", T_SCENE + 1.0, clock=SbsClock("UTC"))
    assert reports(utc)["0101de"].t - reports(stated)["0101de"].t == pytest.approx(7200.0)


def test_sbs_readsb_utc_geometric_and_mlat():
    events = sbs_events("sbs_readsb.txt", T_SCENE + 1.0, clock=SbsClock("UTC"))
    positions = [e for e in events if isinstance(e, PositionReport)]
    assert [(p.address, p.source) for p in positions] == [("0101de", "adsb"), ("4ca7b1", "mlat"),
                                                          ("0101de", "adsb")]
    a, m, b = positions
    assert a.t == pytest.approx(T_SCENE + 0.1, abs=1e-6)
    assert (a.alt_ref, a.alt_m) == ("geometric", pytest.approx(13900 * FOOT))  # "13900H"
    assert a.std_v_m == pytest.approx(math.hypot(150 / Z95, STEP))  # no GVA: GVA 1's bound
    assert a.velocity_m_s is None  # no MSG,4 yet
    assert m.std_h_m == adsb.MLAT_STD_M and m.t == pytest.approx(T_SCENE - 1.6, abs=1e-6)
    assert b.vrate_m_s == pytest.approx(-928 * FPM) and b.velocity_m_s == pytest.approx(velocity(325, 311))
    assert causes(events, Skipped) == Counter({"not-msg": 1, "velocity": 1})
    assert causes(events, Rejected) == Counter({"message-type": 2, "position": 1})


def test_sbs_mlat_feed():
    plain = sbs_events("sbs_mlat_client.txt", calendar.timegm((2019, 12, 10, 19, 10, 48)))
    mlat = sbs_events("sbs_mlat_client.txt", calendar.timegm((2019, 12, 10, 19, 10, 48)), sbs_mlat=True)
    assert reports(plain)["4ac8b3"].source == "adsb"
    r = reports(mlat)["4ac8b3"]
    assert (r.source, r.std_h_m) == ("mlat", adsb.MLAT_STD_M)
    assert r.t == pytest.approx(calendar.timegm((2019, 12, 10, 19, 10, 46)) + 0.32, abs=1e-6)


def test_sbs_old_velocity_is_not_attached():
    rx = AdsbReceiver(clock=SbsClock("UTC"))
    rx.receive_sbs("MSG,4,1,1,0101DE,1,2021/10/07,12:12:40.000,2021/10/07,12:12:40.000,,,325,311,,,-896,,,,,0",
                   T_SCENE)
    late = rx.receive_sbs("MSG,3,1,1,0101DE,1,2021/10/07,12:12:53.000,2021/10/07,12:12:53.000,,13650,,,48.5,2.5,,,,,,0",
                          T_SCENE)
    assert reports(late)["0101de"].velocity_m_s is None


@pytest.mark.parametrize("line, cls, cause", [
    ("MSG,3,1,1,0101DE,1,2021/02/30,12:00:00.000,2021/02/30,12:00:00.000,,1000,,,48.5,2.5,,,,,,0", Rejected, "time"),
    ("MSG,3,1,1,0101DE,1,2021/10/07,25:00:00.000,2021/10/07,25:00:00.000,,1000,,,48.5,2.5,,,,,,0", Rejected, "time"),
    ("MSG,3,1,1,0101DE,1,,,,,,1000,,,48.5,2.5,,,,,,0", Rejected, "time"),
    ("MSG,3,1,1,0101DE,1,2021/10/07,12:00:00,2021/10/07,12:00:00,,1000,,,48.5,2.5,,,,,,0", PositionReport, None),
    ("MSG,3,1,1,0101DE,1,2021/10/07,12:12:53.1,,,,1000,,,48.5,2.5", PositionReport, None),  # generated only
    ("MSG,3,1,1,0101DE,1,,,2021/10/07,12:12:53.1,,1000,,,48.5,2.5", PositionReport, None),  # logged only
    ("MSG,3,1,1,0101DE,1,2021/10/07,12:12:53.1,2021/10/07,12:12:53.1,,1000,,,91.0,2.5,,,,,,0", Rejected, "range"),
    ("MSG,3,1,1,0101DE,1,2021/10/07,12:12:53.1,2021/10/07,12:12:53.1,,1000,,,nan,2.5,,,,,,0", Rejected, "non-finite"),
    ("MSG,3,1,1,0101DE,1,2021/10/07,12:12:53.1,2021/10/07,12:12:53.1,,1k,,,48.5,2.5,,,,,,0", Rejected, "value"),
    ("MSG,3,1,1,0101DE,1,2021/10/07,12:12:53.1,2021/10/07,12:12:53.1,,1000,,,48.5", Rejected, "fields"),
    ("MSG,3,1,1,0101D,1,2021/10/07,12:12:53.1,2021/10/07,12:12:53.1,,1000,,,48.5,2.5,,,,,,0", Rejected, "address"),
    ("MSG,0,1,1,0101DE,1,2021/10/07,12:12:53.1,2021/10/07,12:12:53.1,,1000,,,48.5,2.5,,,,,,0", Rejected,
     "message-type"),
    ("MSG,33,1,1,0101DE,1,2021/10/07,12:12:53.1,2021/10/07,12:12:53.1,,1000,,,48.5,2.5,,,,,,0", Rejected,
     "message-type"),
    ("MSG,1,1,1,0101DE,1,2021/10/07,12:12:53.1,2021/10/07,12:12:53.1,DLH@1,,,,,,,,,,,0", Rejected, "value"),
    ("MSG,4,1,1,0101DE,1,2021/10/07,12:12:53.1,2021/10/07,12:12:53.1,,,325", Rejected, "fields"),
    ("MSG,3,1,1,0101DE,1,2021/10/07,12:12:53.1,2021/10/07,12:12:53.1,,,,,,,,,,,,0", Skipped, "no-position"),
    ("CLK,,,,,,2021/10/07,12:12:53.1,2021/10/07,12:12:53.1", Skipped, "not-msg"),
    ("MSG," + "9" * 2000, Rejected, "line-too-long"),
])
def test_sbs_lines(line, cls, cause):
    (event,) = AdsbReceiver(clock=SbsClock("UTC")).receive_sbs(line, T_SCENE)
    assert isinstance(event, cls)
    if cause is not None:
        assert event.cause == cause


def test_sbs_auto_zone_refuses_a_clock_far_off():
    line = "MSG,3,1,1,0101DE,1,2021/10/07,12:12:53.1,2021/10/07,12:12:53.1,,1000,,,48.5,2.5,,,,,,0"
    assert parse_sbs_line(line, T_SCENE + 20 * 3600).cause == "time"
    assert isinstance(parse_sbs_line(line, T_SCENE + 5.5 * 3600), SbsPosition)  # UTC−05:30
    for now in (math.nan, math.inf, -math.inf, 1e300):
        assert parse_sbs_line(line, now).cause == "time"


def test_sbs_messages_are_typed():
    date = "2021/10/07,12:12:53.000,2021/10/07,12:12:53.000"
    assert isinstance(parse_sbs_line(f"MSG,1,1,1,0101DE,1,{date},MSR799,,,,,,,,,,,0", T_SCENE), SbsIdentification)
    v = parse_sbs_line(f"MSG,4,1,1,0101DE,1,{date},,,325,311,,,-896,,,,,0", T_SCENE)
    assert isinstance(v, SbsVelocity) and v.vrate_m_s == pytest.approx(-896 * FPM)
    p = parse_sbs_line(f"MSG,3,1,1,0101DE,1,{date},,13650,,,48.5,2.5,,,,,,-1", T_SCENE)
    assert isinstance(p, SbsPosition) and p.on_ground and p.alt_ref == "ground"  # field 22: on the ground


def test_sbs_bytes_and_crlf_and_blank_lines():
    data = body("sbs_dump1090fa.txt")
    assert b"\r\n\r\n" in data  # a heartbeat
    a = AdsbReceiver(clock=SbsClock("Europe/Paris")).receive_sbs(data, T_SCENE)
    b = AdsbReceiver(clock=SbsClock("Europe/Paris")).receive_sbs(data.replace(b"\r\n", b"\n").decode(), T_SCENE)
    assert a == b and len(a) == 9


def test_sbs_clock_refuses_an_unknown_zone():
    with pytest.raises(ValueError, match="IANA"):
        SbsClock("Nowhere/Atlantis")
