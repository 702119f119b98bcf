"""Built-in scenarios: all load and produce data; the decided parameters are as agreed."""

from __future__ import annotations

import dataclasses
import math
import shutil
from importlib import resources

import numpy as np
import pytest

from sensors_sim.geometry import coverage_mask
from sensors_sim.recorded import RecordedTraffic
from sensors_sim.traffic import Traffic, population

from fusion.methods import method_config
from sensors_sim import (
    jam_state,
    list_scenarios,
    load_scenario,
    scan_times,
    sensor_events,
    truth_events,
    truth_trajectory,
)

BUILTINS = [name for name, _ in list_scenarios()]
REQUIRED = ["patent-3d", "patent-3d-60", "patent-3d-separated", "patent-3d-radar3d",
            *(f"thesis-fixed-c{i}" for i in range(1, 7)), "thesis-moving-2", "thesis-moving-9", "jammed-df"]


def test_listing_has_every_required_scenario_with_a_description():
    files = sorted(p.name[:-5] for p in resources.files("sensors_sim").joinpath("scenarios").iterdir()
                   if p.name.endswith(".toml"))
    assert sorted(BUILTINS) == files
    assert set(REQUIRED) <= set(BUILTINS)
    for name, description in list_scenarios():
        assert description and "\n" not in description, name


@pytest.mark.parametrize("name", BUILTINS)
def test_builtin_loads_and_every_sensor_produces_measurements(name):
    sc = load_scenario(name)
    assert sc.name == name and sc.source == f"{name}.toml"
    assert sc.process_ids()[-1] == "truth"
    recorded = isinstance(sc.traffic, RecordedTraffic)
    if sc.traffic is not None and sc.traffic.max_alive > 100:  # the regions: their first 20 s
        sc = dataclasses.replace(sc, duration=20.0)
    if recorded:  # a recording's first 10 minutes
        sc = dataclasses.replace(sc, duration=600.0)
    for sid in sc.sensors:
        sensor = sc.sensors[sid]
        events = [e for e in sensor_events(sc, sid) if not e.clutter]
        traffic = population(sc)
        if sensor.sectors:  # a rotating radar: an event per beam crossing in coverage
            lives = {}
            for t in (0.0, sc.duration):  # (every synthetic life is longer than the run)
                fleet = traffic.fleet(t)
                lives.update(zip(fleet.ids, zip(fleet.t0, fleet.t1)))
            if recorded:  # an aircraft's every segment: when it is alive
                lives = {a: list(zip(sc.traffic.t0[sc.traffic.ids == a], sc.traffic.t1[sc.traffic.ids == a]))
                         for a in set(sc.traffic.ids.tolist())}
            for e in events:
                assert e.in_coverage
                if e.target not in sensor.targets:
                    spans = lives[e.target] if recorded else [lives[e.target]]
                    assert any(t0 <= e.t < t1 for t0, t1 in spans)
            assert len(events) > 0
        else:  # one per scan per target, and per aircraft alive in view (with ADS-B, for a receiver)
            alive = 0
            sending = sc.traffic.equipped(sc.seed) if recorded and sensor.kind == "adsb" else None
            for t in scan_times(sc, sid) if traffic else ():
                fleet = traffic.fleet(float(t))
                seen = coverage_mask(sensor, fleet.positions(float(t)) - sensor.site.position(float(t)))
                if sending is not None:
                    seen &= np.isin(fleet.ids, list(sending))
                alive += seen.sum()
            assert len(events) == len(scan_times(sc, sid)) * len(sensor.targets) + alive > 0
        assert any(e.measurement is not None for e in events), sid
    for jid in sc.jammers:
        assert jam_state(sc, jid, sc.duration).jammer == jid
    assert next(truth_events(sc)).t == 0.0


def test_patent_3d_decided_parameters():
    sc = load_scenario("patent-3d")
    assert (sc.duration, sc.origin) == (30.0, (21.0285, 105.8542, 10.0))
    assert sc.process_ids() == ["radar2d", "angle", "truth"]  # no 3D radar in the fusion run
    assert sc.defaults == {"topology": "centralised", "method": "SS"}
    assert method_config(sc.tracker, None) == {"motion": "ca", "q": 0.01}
    t1 = sc.targets["T1"]
    np.testing.assert_array_equal(t1.x0, [6000, 8000, 2000, -120, -60, 5, 0.5, 1.0, -0.05])
    assert t1.jerk_psd == 0.01
    r, a = sc.sensors["radar2d"], sc.sensors["angle"]
    np.testing.assert_allclose(r.std, [math.radians(1.0), 20.0])
    np.testing.assert_allclose(a.std, [math.radians(0.05), math.radians(0.05)])
    for s in (r, a):
        np.testing.assert_array_equal(s.site.position(0.0), [0.0, 0.0, 0.0])
        np.testing.assert_array_equal(scan_times(sc, s.id), np.arange(31.0))  # t = 0..30
    np.testing.assert_array_equal(truth_trajectory(sc, "T1").state(0.0), t1.x0)


def test_patent_variants_differ_only_where_they_say():
    base, long = load_scenario("patent-3d"), load_scenario("patent-3d-60")
    assert long.duration == 60.0 and len(scan_times(long, "radar2d")) == 61
    np.testing.assert_array_equal(long.targets["T1"].x0, base.targets["T1"].x0)
    sep = load_scenario("patent-3d-separated")
    d = sep.sensors["angle"].site.position(0.0) - sep.sensors["radar2d"].site.position(0.0)
    assert np.linalg.norm(d) == pytest.approx(5000.0)
    r3 = load_scenario("patent-3d-radar3d")
    assert r3.process_ids() == ["radar3d", "truth"] and r3.kind_of("radar3d") == "radar3d"
    np.testing.assert_allclose(r3.sensors["radar3d"].std, [math.radians(1.0), math.radians(1.0), 20.0])
    np.testing.assert_array_equal(r3.targets["T1"].x0, base.targets["T1"].x0)
    # same seed and target: the three-sensor-set variants share one truth
    np.testing.assert_array_equal(truth_trajectory(r3, "T1").state(30.0), truth_trajectory(base, "T1").state(30.0))
    # one tracker configuration, per-method tables included, for every variant
    for variant in (long, sep, r3, load_scenario("patent-3d-jammed")):
        assert variant.tracker == base.tracker, variant.name


STATIONS = {1: [(0, 0), (20, 0)], 2: [(20, 0), (40, 0)], 3: [(0, 0), (20, 0), (30, 0)],
            4: [(20, 0), (40, 0), (60, 0)], 5: [(0, 0), (20, 0), (30, 0), (40, 0)],
            6: [(20, 0), (40, 0), (60, 0), (80, 0)]}


@pytest.mark.parametrize("case", sorted(STATIONS))
def test_thesis_fixed_cases(case):
    sc = load_scenario(f"thesis-fixed-c{case}")
    np.testing.assert_array_equal(sc.targets["E1"].x0, [15e3, 15e3, 0, 0, 0, 0, 0, 0, 0])
    sites = [tuple(s.site.position(0.0)[:2] / 1e3) for s in sc.sensors.values()]
    assert sites == STATIONS[case]
    for s in sc.sensors.values():
        assert s.kind == "df" and s.std.tolist() == [0.0175]
        np.testing.assert_array_equal(scan_times(sc, s.id), np.arange(1.0, 41.0))  # 40 epochs
    assert sc.defaults["method"] == "EKF" and sc.tracker == {"q22": 625.0, "sigma": 0.0175}


@pytest.mark.parametrize("name, n", [("thesis-moving-2", 2), ("thesis-moving-9", 9)])
def test_thesis_moving_observer(name, n):
    sc = load_scenario(name)
    np.testing.assert_array_equal(sc.targets["E1"].x0[:3], [141e3, 141e3, 0])
    events = list(sensor_events(sc, "adf"))
    assert [e.t for e in events] == [300.0 * k for k in range(n)]
    np.testing.assert_allclose([e.measurement.site[:2] for e in events],
                               [[(130 + 30 * k) * 1e3, (11 + 30 * k) * 1e3] for k in range(n)])
    assert all(e.measurement.kind == "bearing" and e.measurement.std[0] == 0.0175 for e in events)


def test_jammed_df_is_the_imm_thesis_setup():
    sc = load_scenario("jammed-df")
    assert sc.process_ids() == ["df1", "df2", "df3", "jammer", "truth"]
    assert [tuple(s.site.position(0.0)[:2] / 1e3) for s in sc.sensors.values()] == [(0, 0), (10, 0), (20, 0)]
    j = sc.jammers["jammer"]
    assert (j.mode, j.p_outlier, j.outlier_law, j.outlier_std) == ("barrage", 0.3, "laplacian", 0.25)
    assert jam_state(sc, "jammer", 1.0).affects == ("df1", "df2", "df3")
    assert sc.defaults["method"] == "IMM"
    events = [e for sid in sc.sensors for e in sensor_events(sc, sid)]
    assert len(events) == 120 and all(e.jammed for e in events)
    assert 0 < sum(e.outlier for e in events) < 120


def test_a_builtin_copied_to_a_path_loads_the_same(tmp_path):
    src = resources.files("sensors_sim").joinpath("scenarios", "patent-3d.toml")
    dst = tmp_path / "my-copy.toml"
    with resources.as_file(src) as f:
        shutil.copy(f, dst)
    a, b = load_scenario("patent-3d"), load_scenario(str(dst))
    assert b.name == "my-copy"
    za = [e.measurement.z for e in sensor_events(a, "angle")]
    zb = [e.measurement.z for e in sensor_events(b, "angle")]
    np.testing.assert_array_equal(za, zb)


def test_patent_3d_maneuver_is_patent_3d_with_a_turning_aircraft():
    base, man = load_scenario("patent-3d"), load_scenario("patent-3d-maneuver")
    assert man.tracker == base.tracker and man.process_ids() == base.process_ids()
    for sid in ("radar2d", "angle"):
        np.testing.assert_array_equal(man.sensors[sid].std, base.sensors[sid].std)
    np.testing.assert_array_equal(scan_times(man, "radar2d"), np.arange(81.0))
    tr = truth_trajectory(man, "T1")
    g = [np.linalg.norm(tr.state(float(t))[6:9]) / 9.80665 for t in range(81)]
    speed = [np.linalg.norm(tr.state(float(t))[3:6]) for t in range(81)]
    np.testing.assert_allclose(speed, 250.0)
    assert max(g[:20]) == 0.0 and max(g[56:]) == 0.0
    np.testing.assert_allclose(g[21:40], 4.0, rtol=1e-4)
    np.testing.assert_allclose(g[41:55], 6.0, rtol=1e-4)


def test_the_two_regions_differ_only_in_their_traffic():
    """region-400 and region-4000: the same 30 sensors (26 rotating radars, 4 angle
    sensors) and tracker; traffic ten times as dense, each keeping its count alive."""
    small, large = load_scenario("region-400"), load_scenario("region-4000")
    assert small.tracker == large.tracker and small.origin == large.origin
    assert list(small.sensors) == list(large.sensors) and len(small.sensors) == 30
    for sid, a in small.sensors.items():
        b = large.sensors[sid]
        for f in dataclasses.fields(a):
            x, y = getattr(a, f.name), getattr(b, f.name)
            assert np.array_equal(x.points, y.points) if f.name == "site" else np.array_equal(x, y), (sid, f.name)
    assert sum(s.sectors > 0 for s in small.sensors.values()) == 26
    assert {s.period for s in small.sensors.values() if s.sectors} <= set(np.arange(4.0, 12.5, 0.1).round(1))
    scaled = dataclasses.replace(small.traffic, rate=10 * small.traffic.rate, max_alive=10 * small.traffic.max_alive)
    np.testing.assert_allclose(np.hstack(dataclasses.astuple(scaled)), np.hstack(dataclasses.astuple(large.traffic)),
                               rtol=1e-12)
    for sc, n in ((small, 400), (large, 4000)):
        counts = [len(Traffic(sc.traffic, sc.seed).fleet(t)) for t in (0.0, 300.0)]
        assert all(abs(c - n) < 0.03 * n for c in counts), counts
