"""The ASTERIX gateway core (services/ingest/asterix.py): CAT048 plots to measurements of
the radar the site file names by SAC/SIC, CAT034 crossings to watermarks, CAT021 to
position reports, and everything else counted by cause.

Geometry is checked against pymap3d's own azimuth/elevation/range conversions (an
independent reference); published messages are decoded with the project's strict decoder.
"""

from __future__ import annotations

import math
import random

import numpy as np
import pymap3d
import pytest

from schemas import KeySpace, decode, to_measurement
from schemas import asterix as ax
from sensors_sim import ScenarioError, load_scenario, load_site, sensor_events
from services.ingest.adsb import CPR_CELL_M, K95_2D, vertical_std
from services.ingest.adsb import horizontal_std as adsb_horizontal_std
from services.ingest.asterix import (
    AsterixFeed, AsterixIngest, CaptureError, Radar, ScanMark, StationReport, horizontal_std, pcap_datagrams, radars,
    stations, with_sac_sic,
)
from services.ingest.gateway import Gateway, Reading, Rejected, local_frame, sensor_sites
from services.ingest.krakensdr import Skipped
from services.node import RejectLog

MIDNIGHT = 1_764_633_600.0  # 2025-12-02 00:00:00 UTC
NOW = MIDNIGHT + 36_000.0
FT, NM = 0.3048, 1852.0

SITE = """
[origin]
lat_deg = 52.0
lon_deg = 4.0
alt_m = 0.0

[defaults]
topology = "centralised"
method = "EKF"

[tracker]

[sensors.r2d]
kind = "radar2d"
pos_km = [100, 0, 0.05]
rotation_period_s = 4.0
std_az_deg = 0.1
std_range_m = 50
sac_sic = [25, 1]

[sensors.r3d]
kind = "radar3d"
pos_km = [-30, 60, 0.02]
rotation_period_s = 6.0
std_az_deg = 0.2
std_el_deg = 0.3
std_range_m = 80
sac_sic = [25, 2]

[sensors.df]
kind = "df"
pos_km = [0, 0, 0]
period_s = 1.0
std_az_deg = 1.0

[sensors.gs]
kind = "adsb"
period_s = 1.0
std_pos_m = 30.0
sac_sic = [30, 4]
"""


@pytest.fixture
def site(tmp_path):
    p = tmp_path / "site.toml"
    p.write_text(SITE)
    return load_site(p)


@pytest.fixture
def rig(site):
    frame = local_frame(site)
    rs = radars(site, frame)
    log = RejectLog("asterix")
    gs = stations(site)
    gw = Gateway(sensor_sites(site, [r.sensor for r in rs.values()] + list(gs.values())), frame, KeySpace("t"), log,
                 lag=0.0)
    return AsterixIngest(AsterixFeed(rs, sector_lag=1), gw, log, stations=gs), rs, frame, log


def on_grid(rho: float, theta: float) -> tuple[float, float]:
    """(ρ, θ) on I048/040's grid, so that they cross the wire unchanged."""
    return round(rho * 256 / NM) * NM / 256, round(theta * 65536 / (2 * math.pi)) * 2 * math.pi / 65536


def datagram(*records) -> bytes:
    (d,) = ax.encode(records)
    return d


# ------------------------------------------------------------------ site file and geometry


def test_the_site_file_names_radars_by_sac_sic(site, tmp_path):
    rs = radars(site, local_frame(site))
    assert {k: (r.sensor, r.kind) for k, r in rs.items()} == {(25, 1): ("r2d", "range_az"),
                                                              (25, 2): ("r3d", "az_el_range")}
    shared = tmp_path / "shared.toml"
    shared.write_text(SITE.replace("sac_sic = [25, 2]", "sac_sic = [25, 1]"))
    with pytest.raises(ValueError, match="share sac_sic"):
        radars(load_site(shared), local_frame(site))
    bad = tmp_path / "bad.toml"
    bad.write_text(SITE.replace("sac_sic = [25, 2]", "sac_sic = [25, 300]"))
    with pytest.raises(ScenarioError, match="sac_sic"):
        load_site(bad)


def test_sac_sic_is_given_to_the_radars_and_stations_without_one(site, tmp_path):
    text = SITE.replace("sac_sic = [25, 2]\n", "").replace("sac_sic = [30, 4]\n", "").replace(
        "[sensors.r3d]", "[ sensors . 'r3d' ]  # quoted").replace("sac_sic = [25, 1]", "sac_sic = [0, 1]")
    (tmp_path / "in.toml").write_text(text)
    out, assigned = with_sac_sic(text, load_site(tmp_path / "in.toml"))
    assert assigned == {"r2d": (0, 1), "r3d": (0, 2), "gs": (0, 3)}  # 0/1 is taken; the DF sensor has no category
    (tmp_path / "out.toml").write_text(out)
    got = load_site(tmp_path / "out.toml")
    assert {sid: s.sac_sic for sid, s in got.sensors.items()} == {**assigned, "df": None}
    assert {k: r.sensor for k, r in radars(got, local_frame(got)).items()} == {(0, 1): "r2d", (0, 2): "r3d"}
    assert stations(got) == {(0, 3): "gs"}
    with pytest.raises(ValueError, match="header"):
        with_sac_sic(text.replace("[sensors.gs]", "[sensors]\ngs = {}\n[sensors.gs2]"), load_site(tmp_path / "in.toml"))


def _reference_aer(radar: Radar, frame, theta, el, rho):
    """The target's az/el/range from the radar's site, in the site frame, by pymap3d."""
    lat0, lon0, h0 = frame.lat0, frame.lon0, frame.alt0
    rlat, rlon, rh = pymap3d.enu2geodetic(*radar.site, lat0, lon0, h0)
    tlat, tlon, th = pymap3d.aer2geodetic(math.degrees(theta), math.degrees(el), rho, rlat, rlon, rh)
    d = np.array(pymap3d.geodetic2enu(tlat, tlon, th, lat0, lon0, h0)) - radar.site
    return math.atan2(d[0], d[1]) % (2 * math.pi), math.atan2(d[2], math.hypot(d[0], d[1])), float(np.linalg.norm(d))


def test_plots_are_turned_into_the_site_frame(site):
    frame = local_frame(site)
    rs = radars(site, frame)
    r2, r3 = rs[(25, 1)], rs[(25, 2)]
    # 100 km east at 52° N: its north leans west (toward the pole) by about Δλ·sin φ ≈ 1.15°
    dlon = math.degrees(100e3 / (6_391e3 * math.cos(math.radians(52.0))))
    assert math.degrees(r2.gamma) == pytest.approx(-dlon * math.sin(math.radians(52.0)), rel=0.01)
    rng = random.Random(1)
    for _ in range(50):
        theta, el, rho = rng.uniform(0, 2 * math.pi), rng.uniform(0.0, 0.3), rng.uniform(5e3, 200e3)
        for r in (r2, r3):
            # the height that puts the target at elevation el, and back to el, exactly
            a = r.radius + r.height
            height = math.sqrt(a * a + rho * rho + 2 * a * rho * math.sin(el)) - r.radius
            assert r.elevation(rho, height) == pytest.approx(el, abs=1e-12)
            ref = _reference_aer(r, frame, theta, el, rho)
            z = r.to_site(theta, rho, height)
            assert math.remainder(z[0] - ref[0], 2 * math.pi) == pytest.approx(0.0, abs=1e-9)
            assert z[1:] == pytest.approx(ref[1:] if r is r3 else ref[2:], abs=1e-9 * rho)
            assert r.from_site(z, height) == pytest.approx((theta, rho, height), abs=1e-6)
        # a 2D plot without a height: on the radar's horizon
        ref = _reference_aer(r2, frame, theta, 0.0, rho)
        z = r2.to_site(theta, rho)
        assert math.remainder(z[0] - ref[0], 2 * math.pi) == pytest.approx(0.0, abs=1e-9) and z[1] == rho
        assert r2.from_site(z) == pytest.approx((theta, rho, None), abs=1e-9)


def test_a_radar_at_the_origin_needs_no_turn(site):
    frame = local_frame(site)
    r = Radar.at("o", (1, 1), "range_az", np.zeros(3), frame)
    assert r.gamma == pytest.approx(0.0, abs=1e-15) and np.allclose(r.rotation, np.eye(3), atol=1e-15)
    assert r.elevation(10e3, 10e3) == pytest.approx(math.pi / 2)  # straight up
    with pytest.raises(ValueError):
        r.elevation(10e3, 20e3)  # 20 km up is out of reach at 10 km
    with pytest.raises(ValueError):
        Radar.at("x", (1, 2), "bearing", np.zeros(3), frame)


# ------------------------------------------------------------------ events


def test_a_plot_becomes_a_reading_of_its_radar(rig):
    ingest, rs, _, _ = rig
    rho, theta = on_grid(40 * NM, math.radians(30))
    plot = ax.TargetReport(sac=25, sic=1, tod=35_999.5, rho=rho, theta=theta, flight_level=100.0)
    (ev,) = ingest.feed.receive(datagram(plot), NOW)
    assert isinstance(ev, Reading) and (ev.sensor, ev.kind, ev.t) == ("r2d", "range_az", NOW - 0.5)
    assert ev.z == pytest.approx(rs[(25, 1)].to_site(theta, rho, 10_000 * FT), abs=1e-12)  # with its Mode C
    assert ev.z[0] == pytest.approx(theta + rs[(25, 1)].gamma, abs=1e-3)


def test_time_of_day_across_midnight(rig):
    ingest = rig[0]
    late = ax.TargetReport(sac=25, sic=1, tod=86_399.75, rho=10e3, theta=0.0)
    (ev,) = ingest.feed.receive(datagram(late), MIDNIGHT + 0.3)
    assert ev.t == MIDNIGHT - 0.25  # yesterday's last quarter second
    early = ax.TargetReport(sac=25, sic=1, tod=0.25, rho=10e3, theta=0.0)
    (ev,) = ingest.feed.receive(datagram(early), MIDNIGHT - 0.1)
    assert ev.t == MIDNIGHT + 0.25  # a receiver clock a little behind


def test_a_3d_radar_takes_its_height_from_i048_110_else_a_valid_mode_c(rig):
    ingest, rs, _, _ = rig
    r3 = rs[(25, 2)]
    rho, theta = on_grid(80e3, 1.0)
    base = dict(sac=25, sic=2, tod=35_999.0, rho=rho, theta=theta)
    (ev,) = ingest.feed.receive(datagram(ax.TargetReport(**base, height_3d=9000 * FT, flight_level=100.0)), NOW)
    assert ev.kind == "az_el_range" and r3.from_site(ev.z)[2] == pytest.approx(9000 * FT)  # I048/110 wins
    (ev,) = ingest.feed.receive(datagram(ax.TargetReport(**base, flight_level=350.0)), NOW)
    assert r3.from_site(ev.z)[2] == pytest.approx(35_000 * FT, abs=1e-6)
    for plot in (ax.TargetReport(**base), ax.TargetReport(**base, flight_level=350.0, fl_garbled=True),
                 ax.TargetReport(**base, flight_level=350.0, fl_validated=False)):
        (ev,) = ingest.feed.receive(datagram(plot), NOW)
        assert isinstance(ev, Rejected) and ev.cause == "no-height"


def test_what_cannot_be_used_is_refused_by_cause(rig):
    ingest = rig[0]
    records = [ax.TargetReport(sac=9, sic=9, tod=1.0, rho=1e3, theta=0.0),    # unknown-source
               ax.TargetReport(sac=25, sic=1, rho=1e3, theta=0.0),            # no-time
               ax.TargetReport(sac=25, sic=1, tod=1.0),                       # no-position
               ax.TargetReport(sac=25, sic=2, tod=1.0, rho=1e3, theta=0.0, height_3d=50e3)]  # geometry
    got = [ev.cause for ev in ingest.feed.receive(datagram(*records), NOW)]
    assert got == ["unknown-source", "no-time", "no-position", "geometry"]
    # a range of 0 has no elevation: a 3D plot is refused, a 2D one goes on to the range check
    zero = [ax.TargetReport(sac=25, sic=k, tod=35_999.0, rho=0.0, theta=0.0, flight_level=50.0) for k in (2, 1)]
    three_d, two_d = ingest.feed.receive(datagram(*zero), NOW)
    assert three_d.cause == "geometry" and two_d.z[1] == 0.0
    assert ingest.receive(datagram(zero[1]), NOW) == [] and rig[3].by_cause == {"range": 1}


def test_several_categories_and_radars_in_one_datagram(rig):
    ingest = rig[0]
    d = (datagram(ax.TargetReport(sac=25, sic=1, tod=35_999.0, rho=5e3, theta=0.1))
         + datagram(ax.ServiceMessage(sac=25, sic=2, message_type=ax.SECTOR_CROSSING, tod=35_998.0, sector=0.0))
         + bytes.fromhex("f0 0005 80 00")  # CAT240 video: not read
         + datagram(ax.TargetReport(sac=25, sic=2, tod=35_999.0, rho=5e3, theta=0.1, height_3d=1000.0),
                    ax.TargetReport(sac=25, sic=1, tod=35_999.1, rho=6e3, theta=0.2))
         + datagram(ax.SdpsStatus(sac=1, sic=1, message_type=1, service=1, tod=1.0)))
    evs = ingest.feed.receive(d, NOW)
    summary = [(type(e).__name__, getattr(e, "sensor", getattr(e, "cause", None))) for e in evs]
    assert summary == [("Reading", "r2d"), ("Rejected", "unknown-category"), ("Reading", "r3d"), ("Reading", "r2d"),
                       ("Skipped", "cat065")]  # the first crossing of r3d promises nothing yet (lag 1)
    assert ingest.feed.counters["records.cat048"] == 3 and ingest.feed.counters["records.cat034"] == 1


def test_sector_crossings_promise_what_is_a_sector_behind(rig):
    ingest = rig[0]
    crossing = lambda tod, k: ax.ServiceMessage(sac=25, sic=1, message_type=ax.SECTOR_CROSSING, tod=tod,  # noqa: E731
                                                sector=k * 2 * math.pi / 32)
    feed = ingest.feed
    assert feed.receive(datagram(crossing(100.0, 0)), NOW) == []
    north = ax.ServiceMessage(sac=25, sic=1, message_type=ax.NORTH_MARKER, tod=100.0)
    assert feed.receive(datagram(north), NOW) == []  # beside sector 0's crossing: the same instant
    (mark,) = feed.receive(datagram(crossing(100.125, 1)), NOW)
    assert mark == ScanMark("r2d", math.nextafter(MIDNIGHT + 100.0, -math.inf))
    (mark,) = feed.receive(datagram(crossing(100.25, 2)), NOW)
    assert mark.t == math.nextafter(MIDNIGHT + 100.125, -math.inf)
    jam = ax.ServiceMessage(sac=25, sic=1, message_type=4, tod=100.3)
    assert feed.receive(datagram(jam), NOW) == [Skipped("service-message")]
    zero_lag = AsterixFeed(feed.radars, sector_lag=0)
    (mark,) = zero_lag.receive(datagram(crossing(100.0, 0)), NOW)
    assert mark.t == math.nextafter(MIDNIGHT + 100.0, -math.inf)


# ------------------------------------------------------------------ ADS-B


def _cpr(bound_m: float) -> float:
    """The ADS-B gateways' σ for a 95 % bound: bound/2.448 and the CPR cell in quadrature."""
    return math.hypot(bound_m / K95_2D, CPR_CELL_M / math.sqrt(12.0))


def test_an_adsb_report_becomes_a_position_report():
    rep = ax.AdsbReport(sac=30, sic=4, tod_position=35_999.5, lat=52.1, lon=4.2, address=0x484C53,
                        geometric_height=11_000 * FT, quality=ax.Quality(nucp_nic=8, nacp=9, gva=2), mops=2,
                        callsign="KLM1023", ground_speed=0.125 * NM, track_angle=math.pi / 2)
    (ev,) = AsterixFeed({}).receive(datagram(rep), NOW)
    assert isinstance(ev, StationReport) and ev.sac_sic == (30, 4)
    p = ev.report
    assert (p.address, p.t, p.callsign, p.alt_ref, p.source, p.fmt, p.nac_p) == (
        "484c53", NOW - 0.5, "KLM1023", "geometric", "adsb", "asterix", 9)
    assert (p.lat_deg, p.lon_deg) == (pytest.approx(52.1, abs=1e-7), pytest.approx(4.2, abs=1e-7))
    assert p.alt_m == pytest.approx(11_000 * FT)
    assert p.std_h_m == pytest.approx(_cpr(30.0))  # NACp 9: 95 % within 30 m
    assert p.std_v_m == pytest.approx(math.hypot(45.0 / 1.959964, 25 * FT / math.sqrt(12)), rel=1e-6)  # GVA 2
    assert p.velocity_m_s == pytest.approx((0.125 * NM, 0.0), abs=1e-9)  # due east
    anonymous = ax.AdsbReport(**{**{f: getattr(rep, f) for f in rep.__dataclass_fields__}, "atp": 3})
    (ev,) = AsterixFeed({}).receive(datagram(anonymous), NOW)
    assert ev.report.address == "~484c53"  # not an ICAO address: an identity, not a proof of one


def test_position_accuracy_follows_the_mops_version():
    q = ax.Quality(nucp_nic=7, nacp=10)
    assert horizontal_std(q, 2) == pytest.approx(_cpr(10.0))          # NACp 10: 10 m
    assert horizontal_std(q, 0) == pytest.approx(_cpr(0.05 * NM))     # NUCp 7: 0.05 NM
    assert horizontal_std(ax.Quality(nucp_nic=9), None) == pytest.approx(_cpr(3.0))  # no NACp sent: NUCp
    assert horizontal_std(ax.Quality(nucp_nic=7, nacp=0), 2) is None   # NACp 0: unknown
    assert horizontal_std(ax.Quality(nucp_nic=0), 0) is None           # NUCp 0: unknown
    assert horizontal_std(None, 2) == pytest.approx(_cpr(0.1 * NM))    # no I021/090: the gateways' default, NACp 7


def test_adsb_reports_that_cannot_be_used():
    base = dict(sac=30, sic=4, tod_position=1.0, lat=52.0, lon=4.0, address=1, quality=ax.Quality(nacp=9), mops=2)
    cases = [({"tod_position": None}, "no-time"), ({"lat": None, "lon": None}, "no-position"),
             ({"address": None}, "no-address"), ({"quality": ax.Quality(nacp=0)}, "no-accuracy")]
    for change, cause in cases:
        (ev,) = AsterixFeed({}).receive(datagram(ax.AdsbReport(**{**base, **change})), NOW)
        assert isinstance(ev, Rejected) and ev.cause == cause, change
    (ev,) = AsterixFeed({}).receive(datagram(ax.AdsbReport(**base, flight_level=300.0)), NOW)
    assert (ev.report.alt_m, ev.report.alt_ref) == (pytest.approx(30_000 * FT), "barometric")


# ------------------------------------------------------------------ to the wire


def test_datagrams_become_checked_measurements_and_watermarks(rig):
    ingest, rs, _, log = rig
    rho, theta = on_grid(30e3, 2.0)
    plot = ax.TargetReport(sac=25, sic=1, tod=35_999.0, rho=rho, theta=theta)
    crossings = [ax.ServiceMessage(sac=25, sic=1, message_type=ax.SECTOR_CROSSING, tod=tod) for tod in
                 (35_999.5, 35_999.625)]
    out = [(k, decode(b)) for k, b in ingest.receive(datagram(plot, *crossings), NOW)]
    assert [k for k, _ in out] == ["zf/t/meas/r2d"] * 3
    meas, wm1, wm2 = (m for _, m in out)
    m = to_measurement(meas)
    assert (m.sensor, m.kind, m.t) == ("r2d", "range_az", NOW - 1.0)
    assert m.z == pytest.approx(rs[(25, 1)].to_site(theta, rho), abs=1e-12)
    assert m.std == pytest.approx([math.radians(0.1), 50.0]) and m.site == pytest.approx([100e3, 0.0, 50.0])
    assert wm1.kind == wm2.kind == "watermark"
    assert wm2.t == math.nextafter(MIDNIGHT + 35_999.5, -math.inf)  # the crossing a sector back
    # a plot older than what the radar promised is late; an unknown radar and CAT240 are counted
    stale = ax.TargetReport(sac=25, sic=1, tod=35_999.25, rho=30e3, theta=2.0)
    assert ingest.receive(datagram(stale, ax.TargetReport(sac=7, sic=7)) + bytes.fromhex("f0 0005 80 00"),
                          NOW) == []
    assert log.by_cause == {"late": 1, "unknown-source": 1, "unknown-category": 1}
    # CAT021 of the ground station gs: a position measurement with its own noise; of an
    # unknown station, refused; without altitude, skipped
    adsb = ax.AdsbReport(sac=30, sic=4, tod_position=35_999.5, lat=52.1, lon=4.2, address=1,
                         quality=ax.Quality(nacp=9, gva=2), mops=2, geometric_height=9000.0)
    (meas, _) = [decode(b) for _, b in ingest.receive(datagram(adsb), NOW)]
    m = to_measurement(meas)
    frame = ingest.gateway.frame
    assert (m.sensor, m.kind, m.t) == ("gs", "position", NOW - 0.5)
    (sent,) = ax.decode(datagram(adsb))  # on the wire's grid (6.25 ft, 180/2³⁰ °)
    assert m.z == pytest.approx(frame.to_enu(sent.lat, sent.lon, sent.geometric_height), abs=1e-6)
    C = np.outer(m.std, m.std) * (np.eye(3) if m.corr is None else m.corr)
    want = [adsb_horizontal_std("adsb", 9)] * 2 + [vertical_std("geometric", gva=2)]
    assert np.trace(C) == pytest.approx(sum(x * x for x in want), rel=1e-9)
    other = ax.AdsbReport(**{**{f: getattr(adsb, f) for f in adsb.__dataclass_fields__}, "sic": 5})
    low = ax.AdsbReport(**{**{f: getattr(adsb, f) for f in adsb.__dataclass_fields__}, "geometric_height": None,
                           "tod_position": 35_999.75})
    assert ingest.receive(datagram(other, low), NOW) == []
    c = ingest.counters()
    assert c["skipped.no-altitude"] == 1 and log.by_cause["unknown-source"] == 2
    assert c["published"] == 2 and c["records.cat048"] == 3 and c["records.cat021"] == 3


def test_a_scenario_runs_end_is_a_final_watermark_per_sensor(rig):
    """``Gateway.end``: each stream ends at the given time, or later where the sensor
    already sent or was promised later (a radar's trailing crossings)."""
    ingest, _, _, _ = rig
    gw = ingest.gateway
    rho, theta = on_grid(30e3, 2.0)
    ingest.receive(datagram(ax.TargetReport(sac=25, sic=1, tod=100.0, rho=rho, theta=theta),
                            *(ax.ServiceMessage(sac=25, sic=2, message_type=ax.SECTOR_CROSSING, tod=tod)
                              for tod in (110.0, 120.0))), MIDNIGHT + 100.0)
    ends = {m.src: m for m in (decode(b) for _, b in gw.end(MIDNIGHT + 105.0))}
    assert all(m.kind == "watermark" and m.body["final"] for m in ends.values())
    assert {s: m.t for s, m in ends.items()} == {"r2d": MIDNIGHT + 105.0, "r3d": math.nextafter(MIDNIGHT + 110.0,
                                                                                               -math.inf),
                                                 "gs": MIDNIGHT + 105.0}


def test_garbage_never_raises_and_is_counted(rig):
    ingest, _, _, log = rig
    good = datagram(ax.TargetReport(sac=25, sic=1, tod=35_999.0, rho=30e3, theta=2.0, flight_level=90.0,
                                    address=0xABCDEF, callsign="ABC123"),
                    ax.ServiceMessage(sac=25, sic=1, message_type=2, tod=35_999.0, sector=1.0))
    rng = random.Random(5)
    for k in range(2000):
        data = bytearray(good)
        if k % 3 == 0:
            data = data[:rng.randrange(len(data))]
        else:
            for _ in range(rng.randrange(1, 4)):
                data[rng.randrange(len(data))] = rng.randrange(256)
        ingest.receive(bytes(data), NOW + k * 1e-3)
    for k in range(500):
        ingest.receive(bytes(rng.randrange(256) for _ in range(rng.randrange(40))), NOW)
    assert set(log.by_cause) <= {"truncated", "malformed", "unknown-category", "missing-item", "unknown-source",
                                 "no-time", "no-position", "geometry", "late", "future", "stale", "range",
                                 "no-accuracy", "no-address"}
    assert sum(log.by_cause.values()) > 1000


# ------------------------------------------------------------------ a scenario through ASTERIX


@pytest.mark.parametrize("name", ["air-picture", "patent-3d-radar3d"])
def test_a_scenarios_radar_measurements_through_cat048_and_back(name):
    """Every radar measurement of a built-in scenario, written as the CAT048 plot a radar
    at that site would send (Radar.plot, by Radar.from_site; a 3D plot's height in I048/110, a 2D plot
    without a height: on the horizon) and read back by the gateway core, equals itself to
    the items' resolution: θ 360°/2¹⁶, ρ 1/256 NM, height 25 ft, time 1/128 s."""
    sc = load_scenario(name)
    frame = local_frame(sc)
    rs = {(25, k): Radar.at(sid, (25, k), spec.measurement_kind, spec.site.points[0], frame)
          for k, (sid, spec) in enumerate(sc.sensors.items(), 1) if spec.kind in ("radar2d", "radar3d")}
    assert rs
    feed = AsterixFeed(rs)
    checked = 0
    for radar in rs.values():
        for ev in sensor_events(sc, radar.sensor):
            m = ev.measurement
            if m is None:
                continue
            plot = radar.plot(m.z, m.t)
            rho, height = plot.rho, plot.height_3d
            try:
                (r,) = feed.receive(datagram(plot), MIDNIGHT + m.t + 1.0)
            except ValueError:  # beyond what the items hold (I048/110: ±204,800 ft)
                continue
            assert isinstance(r, Reading) and r.sensor == radar.sensor and r.kind == m.kind
            assert r.t - MIDNIGHT == pytest.approx(m.t, abs=1 / 256 + 1e-9)
            rho_tol = NM / 512
            assert r.z[-1] == pytest.approx(m.z[-1], abs=rho_tol + 1e-9)
            az_tol = math.pi / 65536 * 1.01 + (0.0 if height is None else 12.5 * FT / rho)
            assert abs(math.remainder(r.z[0] - m.z[0], 2 * math.pi)) <= az_tol
            if m.kind == "az_el_range":
                assert r.z[1] == pytest.approx(m.z[1], abs=12.5 * FT / rho * 1.01 + rho_tol / rho + 1e-12)
            checked += 1
    assert checked >= 31  # patent-3d-radar3d: 31 scans of one aircraft


# ------------------------------------------------------------------ captures


def _pcap(link: int, frames: list[bytes], magic: str = "d4c3b2a1") -> bytes:
    """A classic pcap file by hand: the global header (little-endian µs magic, v2.4,
    snaplen 65535, this link type), then one record header per frame at t = 10 + k s."""
    out = bytes.fromhex(magic) + (2).to_bytes(2, "little") + (4).to_bytes(2, "little") + bytes(8) \
        + (65535).to_bytes(4, "little") + link.to_bytes(4, "little")
    for k, f in enumerate(frames):
        out += (10 + k).to_bytes(4, "little") + (500_000).to_bytes(4, "little") + len(f).to_bytes(4, "little") * 2 + f
    return out


def _ipv4_udp(payload: bytes, flags_frag: int = 0x4000, proto: int = 17) -> bytes:
    udp = (8600).to_bytes(2, "big") * 2 + (8 + len(payload)).to_bytes(2, "big") + b"\x00\x00" + payload
    return (bytes((0x45, 0)) + (20 + len(udp)).to_bytes(2, "big") + b"\x00\x01" + flags_frag.to_bytes(2, "big")
            + bytes((64, proto)) + b"\x00\x00" + bytes((10, 0, 0, 1, 239, 1, 2, 3)) + udp)


def test_pcap_link_types_and_what_is_skipped():
    ether = bytes(12) + b"\x08\x00"                       # destination, source, IPv4
    vlan = bytes(12) + b"\x81\x00\x00\x05" + b"\x08\x00"   # one 802.1Q tag
    frames = [ether + _ipv4_udp(b"one"), vlan + _ipv4_udp(b"two"),
              ether + _ipv4_udp(b"frag", flags_frag=0x2000),  # more fragments follow: skipped
              ether + _ipv4_udp(b"tcp", proto=6),             # not UDP: skipped
              ether + _ipv4_udp(b"cut")[:30],                 # cut by the snap length: what there is
              ether + _ipv4_udp(b"")[:25]]                    # cut inside the UDP header: nothing
    # (a cut datagram goes on as it is: the codec counts it as truncated)
    assert list(pcap_datagrams(_pcap(1, frames))) == [(10.5, b"one"), (11.5, b"two"), (14.5, b"cu")]
    ipv6 = bytes.fromhex("60000000") + (8 + 3).to_bytes(2, "big") + bytes((17, 64)) + bytes(32) \
        + (1).to_bytes(2, "big") * 2 + (11).to_bytes(2, "big") + b"\x00\x00" + b"six"
    cooked = bytes(14) + b"\x08\x00"
    assert list(pcap_datagrams(_pcap(101, [ipv6]))) == [(10.5, b"six")]
    assert list(pcap_datagrams(_pcap(113, [cooked + _ipv4_udp(b"sll")]))) == [(10.5, b"sll")]
    truncated = _pcap(101, [_ipv4_udp(b"whole"), _ipv4_udp(b"last")])[:-2]
    assert list(pcap_datagrams(truncated)) == [(10.5, b"whole")]  # a capture cut short: its last record goes
    for bad in (b"\x0a\x0d\x0d\x0a" + bytes(40), _pcap(147, [])):  # pcapng; a user link type
        with pytest.raises(CaptureError):
            list(pcap_datagrams(bad))
