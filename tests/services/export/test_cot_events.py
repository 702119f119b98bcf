"""Cursor-on-Target events: the 95 % error ellipse against closed forms and Monte Carlo,
the identity, the breadcrumb trail, the DF bearing lines and every sensor, each event
checked against the CoT 2.0 structure (_cot_schema.py)."""

from __future__ import annotations

import datetime as dt
import math
import xml.etree.ElementTree as ET

import numpy as np
import pymap3d
import pytest

from _cot_schema import check_event
from fusion.types import Estimate, Identity, Measurement
from schemas import KeySpace, encode_measurement
from sensors_sim import load_scenario
from sensors_sim.loader import list_scenarios
from sensors_sim.spec import SENSOR_KINDS
from services import geo
from services.export import cot, geojson
from services.export.tracks import Bearings, TrackTable, sensor_sites
from services.node import RejectLog

WGS84 = pymap3d.Ellipsoid.from_name("wgs84")
ORIGIN = (51.5, -0.12, 10.0)
FRAME = geo.frame_of(ORIGIN)
NOW = 1_796_000_000.0
K2 = -2.0 * math.log(0.05)  # χ²₂(0.95) = 5.991


def _rotated(major_std: float, minor_std: float, angle_deg: float) -> np.ndarray:
    """The covariance whose major axis points at compass angle ``angle_deg``."""
    a = math.radians(angle_deg)
    u = np.array([math.sin(a), math.cos(a)])  # (e, n) of the major axis
    w = np.array([math.cos(a), -math.sin(a)])
    return major_std**2 * np.outer(u, u) + minor_std**2 * np.outer(w, w)


def _enu(point: str | tuple) -> np.ndarray:
    lat, lon, hae = (float(v) for v in (point.split(",") if isinstance(point, str) else point))
    return np.array(pymap3d.geodetic2enu(lat, lon, hae, *ORIGIN, ell=WGS84, deg=True))


# -- the error ellipse -------------------------------------------------------------------------


def test_ellipse_of_a_diagonal_covariance_is_its_stds_times_the_95_percent_radius():
    major, minor, angle = cot.error_ellipse(np.diag([900.0, 100.0]))  # σe = 30 m, σn = 10 m
    assert major == pytest.approx(30.0 * math.sqrt(K2)) and minor == pytest.approx(10.0 * math.sqrt(K2))
    assert angle == pytest.approx(90.0)  # the major axis east-west
    major, minor, angle = cot.error_ellipse(np.diag([4.0, 25.0]))
    assert (major, minor) == pytest.approx((5.0 * math.sqrt(K2), 2.0 * math.sqrt(K2)))
    assert angle == pytest.approx(0.0, abs=1e-9) or angle == pytest.approx(180.0)  # north-south


@pytest.mark.parametrize("angle", [0.0, 30.0, 75.0, 120.0, 179.0])
def test_ellipse_of_a_rotated_covariance_points_its_major_axis_at_the_compass_angle(angle):
    major, minor, got = cot.error_ellipse(_rotated(40.0, 15.0, angle))
    assert (major, minor) == pytest.approx((40.0 * math.sqrt(K2), 15.0 * math.sqrt(K2)))
    assert min(abs(got - angle), 180.0 - abs(got - angle)) < 1e-6


@pytest.mark.parametrize("angle", [20.0, 135.0])
def test_95_percent_of_gaussian_samples_fall_inside_the_ellipse(angle):
    P2 = _rotated(50.0, 8.0, angle)
    major, minor, got = cot.error_ellipse(P2)
    d = np.random.default_rng(7).multivariate_normal(np.zeros(2), P2, size=40_000)
    a = math.radians(got)  # the ellipse as the event states it: axes and angle, not P2
    along = d @ np.array([math.sin(a), math.cos(a)])
    across = d @ np.array([math.cos(a), -math.sin(a)])
    inside = np.mean((along / major) ** 2 + (across / minor) ** 2 <= 1.0)
    assert abs(inside - 0.95) < 4 * math.sqrt(0.95 * 0.05 / len(d))  # ±0.0044
    # the angle matters: the same axes turned by 90° hold far fewer
    wrong = np.mean((across / major) ** 2 + (along / minor) ** 2 <= 1.0)
    assert wrong < 0.5


def test_track_event_carries_the_ellipse_and_1_sigma_ce_le():
    P = np.zeros((6, 6))
    P[:2, :2] = _rotated(30.0, 12.0, 60.0)
    P[2, 2] = 400.0
    P[3:, 3:] = np.eye(3)
    e = Estimate(12.0, np.array([1000.0, 2000.0, 3000.0, 50.0, 0.0, 0.0]), P, "SS", "centre", "T3")
    ev = check_event(cot.track_event(e, FRAME, "zfusion.x.T3", cot.Types(), NOW, 60.0, live=False))
    el = ev.find("detail/shape/ellipse")
    assert float(el.get("major")) == pytest.approx(30.0 * math.sqrt(K2), abs=0.05)
    assert float(el.get("minor")) == pytest.approx(12.0 * math.sqrt(K2), abs=0.05)
    assert float(el.get("angle")) == pytest.approx(60.0, abs=0.05)
    pt = ev.find("point")  # ce, le: 1σ, as the CoT schema defines an error
    assert float(pt.get("ce")) == pytest.approx(30.0, abs=0.05) and float(pt.get("le")) == pytest.approx(20.0)
    assert ev.find("detail/contact").get("callsign") == "T3" and ev.find("detail/zfusion").get("track") == "T3"
    assert ev.find("detail/zfusion").get("address") is None


# -- identity ---------------------------------------------------------------------------------


def test_a_track_with_an_identity_is_shown_by_its_callsign_with_its_address():
    e = Estimate(5.0, np.array([0.0, 1000.0, 2000.0, 100.0, 0.0, 0.0]), np.eye(6), "SS", "centre", "T7",
                 identity=Identity(address="4ca1fa", callsign="RYR12AB"))
    ev = check_event(cot.track_event(e, FRAME, "zfusion.x.T7", cot.Types(), NOW, 60.0, live=False))
    assert ev.find("detail/contact").get("callsign") == "RYR12AB"
    z = ev.find("detail/zfusion")
    assert z.get("address") == "4ca1fa" and z.get("track") == "T7"
    (point,) = geojson.estimate_features(e, FRAME, live=False)
    assert point["properties"]["callsign"] == "RYR12AB" and point["properties"]["address"] == "4ca1fa"
    half = Estimate(5.0, e.x, e.P, "SS", "centre", "T8", identity=Identity(address="4ca1fb"))
    ev = ET.fromstring(cot.track_event(half, FRAME, "u", cot.Types(), NOW, 60.0, live=False))
    assert ev.find("detail/contact").get("callsign") == "T8" and ev.find("detail/zfusion").get("address") == "4ca1fb"
    props = geojson.estimate_features(half, FRAME, live=False)[0]["properties"]
    assert props["address"] == "4ca1fb" and "callsign" not in props


# -- the trail --------------------------------------------------------------------------------


def _picture(**kw) -> cot.CoTPicture:
    return cot.CoTPicture(FRAME, {}, "x", cot.Types(), 60.0, live=False, **kw)


def _track(t: float, track: str = "T1") -> Estimate:
    return Estimate(t, np.array([100.0 * t, 50.0, 1000.0, 100.0, 0.0, 0.0]), np.eye(6), "SS", "centre", track)


def test_the_trail_holds_the_latest_positions_one_per_second_sent_at_a_bounded_rate():
    p = _picture(trail_points=5)
    trails = []
    for i in range(200):  # 20 s of updates at 10 Hz, the wall clock keeping pace
        t = 0.1 * i
        for uid, data in p.update(_track(t), NOW + t, t):
            if uid.endswith(".trail"):
                trails.append((t, check_event(data)))
    # one at the second point (t = 1 s), then every TRAIL_PERIOD_S (5 s) of wall clock
    assert [round(t, 1) for t, _ in trails] == [1.0, 6.0, 11.0, 16.0]
    t, ev = trails[-1]
    assert ev.get("type") == "u-d-f" and ev.get("uid") == "zfusion.x.fuser.T1.trail"
    vertices = [_enu(link.get("point")) for link in ev.iterfind("detail/link")]
    assert len(vertices) == 5  # the bound
    assert [v[0] for v in vertices] == pytest.approx([100.0 * s for s in (12.0, 13.0, 14.0, 15.0, 16.0)], abs=0.02)
    assert np.allclose([v[1] for v in vertices], 50.0, atol=0.02)
    assert _enu((ev.find("point").get(k) for k in ("lat", "lon", "hae")))[0] == pytest.approx(1600.0, abs=0.02)


def test_trails_are_forgotten_with_their_tracks():
    p = _picture(trail_points=3)
    for t in range(10):
        for track in ("T1", "T2"):
            p.update(_track(float(t), track), NOW + t, float(t))
    assert sorted(p.trails) == ["T1", "T2"] and all(len(tr) == 3 for tr in p.trails.values())
    p.tick({"T2": None}, NOW, 10.0)
    assert list(p.trails) == ["T2"]


# -- DF bearings ------------------------------------------------------------------------------


def test_a_bearing_is_a_line_from_the_station_along_its_azimuth_rate_limited():
    p = _picture()
    site = np.array([-3000.0, 1000.0, 5.0])
    fix = Estimate(0.0, np.array([1000.0, 4000.0]), np.eye(2), "EKF", "centre", "E1")  # 5 km from the site
    out = p.bearing("df1", "df", site, math.radians(53.13), 3.0, [fix], NOW, 100.0)
    assert [uid for uid, _ in out] == ["zfusion.x.sensor.df1", "zfusion.x.sensor.df1.bearing"]  # a new station
    ev = check_event(out[1][1])
    assert ev.get("type") == "u-d-f"
    vertices = np.array([_enu(link.get("point")) for link in ev.iterfind("detail/link")])
    assert vertices[0] == pytest.approx(site, abs=0.02)
    ray = vertices[-1] - site
    assert np.hypot(ray[0], ray[1]) == pytest.approx(1.5 * 5000.0, abs=0.02)  # 1.5 × the fix's distance
    assert math.degrees(math.atan2(ray[0], ray[1])) == pytest.approx(53.13, abs=1e-4)  # 1 cm in 7.5 km
    stale = dt.datetime.fromisoformat(ev.get("stale").replace("Z", "+00:00")).timestamp()
    assert stale - NOW == pytest.approx(cot.BEARING_STALE_S, abs=1e-3)
    assert p.bearing("df1", "df", site, 0.5, 3.2, [fix], NOW, 100.5) == []  # within BEARING_PERIOD_S
    assert len(p.bearing("df2", "df", site, 0.5, 3.2, [fix], NOW, 100.5)) == 2  # another station
    (_, data), = p.bearing("df1", "df", site, 0.0, 4.0, [], NOW, 101.0)  # the same station, where it was
    end = _enu(ET.fromstring(data).findall("detail/link")[-1].get("point"))
    assert end - site == pytest.approx([0.0, cot.BEARING_RANGE_M, 0.0], abs=0.05)  # no fix: the range


def test_a_mobile_df_station_is_placed_where_its_bearings_come_from():
    p = _picture()
    assert p.tick({}, NOW, 0.0) == []  # no position before its first bearing
    for i, pos in enumerate(([100.0, 200.0, 0.0], [100.5, 200.0, 0.0], [300.0, 200.0, 0.0])):
        out = dict(p.bearing("kraken", "df", np.array(pos), 1.0, float(i), [], NOW, float(i)))
        moved = i != 1  # first seen, then within MOVED_M, then 200 m on
        assert ("zfusion.x.sensor.kraken" in out) == moved
        if moved:
            ev = check_event(out["zfusion.x.sensor.kraken"])
            assert _enu((ev.find("point").get(k) for k in ("lat", "lon", "hae"))) == pytest.approx(pos, abs=0.02)
            assert ev.get("type") == "a-f-G-E-S"
    (_, data), = p.tick({}, NOW, 40.0)  # and re-sent where it was last, with the other sensors
    assert _enu((ET.fromstring(data).find("point").get(k) for k in ("lat", "lon", "hae"))) == pytest.approx(
        [300.0, 200.0, 0.0], abs=0.02)


# -- sensors ----------------------------------------------------------------------------------


@pytest.mark.parametrize("name", [n for n, _ in list_scenarios()])
def test_every_sensor_with_a_site_is_a_point_of_its_kinds_type(name):
    scenario = load_scenario(name)
    sites = sensor_sites(scenario)
    p = cot.CoTPicture(geo.frame_of(scenario.origin), sites, "x", cot.Types(), 60.0, live=False)
    events = {ev.find("detail/zfusion").get("sensor"): ev for ev in (check_event(d) for _, d in p.tick({}, NOW, 0.0))}
    assert set(events) == {sid for sid, s in scenario.sensors.items() if s.site is not None}
    for sid, ev in events.items():
        kind = SENSOR_KINDS[scenario.sensors[sid].kind]
        want = "a-f-G-E-S-R" if kind.active else "a-f-A" if kind.airborne else "a-f-G-E-S"
        assert ev.get("type") == want and ev.find("detail/zfusion").get("sensor_kind") == kind.name
    assert p.tick({}, NOW, 10.0) == []  # again only after stale_s / 2
    assert len(p.tick({}, NOW, 30.0)) == len(events)


def test_bearings_off_meas_pass_the_intake_and_bad_ones_are_counted():
    keys = KeySpace("x")
    reject = RejectLog("x")
    feed = Bearings(TrackTable(keys, reject, duration=100.0))
    m = Measurement(3.0, "df1", "bearing", np.array([0.7]), np.array([0.02]), np.array([10.0, 20.0, 0.0]), seq=1)
    got = feed.offer(keys.meas("df1"), encode_measurement(m, "df1"))
    assert got == m
    radar = Measurement(3.0, "r1", "range_az", np.array([0.5, 1000.0]), np.array([0.01, 10.0]), np.zeros(3), seq=1)
    assert feed.offer(keys.meas("r1"), encode_measurement(radar, "r1")) is None and not reject.by_cause
    bad = {"malformed": (keys.meas("df1"), b"\x93garbage"),
           "future": (keys.meas("df1"), encode_measurement(Measurement(1e6, "df1", "bearing", m.z, m.std, m.site, 2),
                                                          "df1")),
           "spoofed-src": (keys.meas("df2"), encode_measurement(Measurement(4.0, "df1", "bearing", m.z, m.std, m.site, 3),
                                                               "df1"))}
    for cause, (key, data) in bad.items():
        assert feed.offer(key, data) is None, cause
        assert reject.by_cause[cause] == 1, (cause, dict(reject.by_cause))


def test_a_moving_emitters_fix_is_a_fix_with_its_ellipse_not_an_air_track():
    P = np.diag([400.0, 100.0, 4.0, 4.0])
    e = Estimate(9.0, np.array([1500.0, -700.0, 3.0, 4.0]), P, "EKF", "centre", "E1")  # [e n ve vn]
    ev = check_event(cot.track_event(e, FRAME, "u", cot.Types(), NOW, 60.0, live=False))
    assert ev.get("type") == cot.Types().emitter and ev.find("detail/zfusion").get("kind") == "fix"
    assert float(ev.find("point").get("le")) == cot.UNKNOWN  # no height
    assert float(ev.find("detail/track").get("speed")) == pytest.approx(5.0)
    assert float(ev.find("detail/track").get("course")) == pytest.approx(math.degrees(math.atan2(3.0, 4.0)), abs=0.05)
    point, ellipse = geojson.estimate_features(e, FRAME, live=False)
    assert point["properties"]["kind"] == "fix" and ellipse["properties"]["kind"] == "ellipse"
    assert point["properties"]["velocity_enu_mps"] == [3.0, 4.0, 0.0]
