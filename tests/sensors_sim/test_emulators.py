"""Sensor emulators: measurement statistics, coverage, detection, determinism."""

from __future__ import annotations

import dataclasses
import itertools
import math

import numpy as np
import pytest
from scipy import stats

from fusion.angles import wrap_pi
from fusion.measurement.kinds import KINDS
from sensors_sim import process_rng, sensor_events, truth_trajectory
from sensors_sim.geometry import finish_measurement, in_coverage, observe

from _scenarios import N_SCANS, write_scenario

ALPHA = 0.01  # significance of every statistical test in this file
@pytest.fixture(scope="module")
def big(tmp_path_factory):
    return write_scenario(tmp_path_factory.mktemp("emu"))


def errors_of(scenario, sensor_id, run=0):
    """(n, m) measurement errors z − h(truth), angles wrapped to (−π, π]."""
    traj = truth_trajectory(scenario, "T1", run)
    out = []
    for ev in sensor_events(scenario, sensor_id, run):
        m = ev.measurement
        e = m.z - observe(m.kind, traj.position(m.t), m.site)
        out.append(np.where(KINDS[m.kind].angles, wrap_pi(e), e))
    return np.array(out)


@pytest.mark.parametrize("sensor_id", ["df", "radar2d", "angle", "radar3d"])
def test_measurement_errors_have_the_configured_gaussian_law(big, sensor_id):
    """Per component, over 10k scans: mean 0 (z-test), variance σ² (two-sided χ²),
    and normal shape (KS), each at 1 %."""
    err = errors_of(big, sensor_id)
    std = big.sensors[sensor_id].std
    assert err.shape == (N_SCANS, len(std))
    n = len(err)
    for j, sigma in enumerate(std):
        e = err[:, j]
        assert abs(e.mean()) / (sigma / math.sqrt(n)) < stats.norm.ppf(1 - ALPHA / 2)
        chi2 = float(np.sum((e - e.mean()) ** 2) / sigma**2)
        assert stats.chi2.ppf(ALPHA / 2, n - 1) < chi2 < stats.chi2.ppf(1 - ALPHA / 2, n - 1)
        assert stats.kstest(e / sigma, "norm").pvalue > ALPHA


def test_measurements_carry_kind_nominal_std_site_and_increasing_seq(big):
    events = list(sensor_events(big, "radar3d"))
    assert [e.t for e in events[:3]] == [0.5, 1.5, 2.5]
    m = events[0].measurement
    assert m.kind == "az_el_range" and m.sensor == "radar3d"
    np.testing.assert_allclose(m.std, [math.radians(1.0), math.radians(2.0), 50.0])
    np.testing.assert_allclose(m.site, [1000.0, -2000.0, 100.0])
    assert [e.measurement.seq for e in events] == list(range(len(events)))
    assert all(e.detected and e.in_coverage and not e.jammed and not e.outlier and e.target == "T1"
               for e in events)
    kinds = {sid: next(sensor_events(big, sid)).measurement.kind for sid in big.sensors}
    assert kinds == {"df": "bearing", "radar2d": "range_az", "angle": "azel", "radar3d": "az_el_range"}


def test_same_seed_same_stream_other_seed_or_run_differs(tmp_path, big):
    def zs(sc, run=0):
        return np.array([e.measurement.z for e in itertools.islice(sensor_events(sc, "radar2d", run), 2000)])

    again = write_scenario(tmp_path)  # another process loading the same scenario
    a = zs(big)
    np.testing.assert_array_equal(a, zs(again))  # bit-identical
    assert not np.any(a == zs(big, run=1))
    assert not np.any(a == zs(dataclasses.replace(big, seed=12)))


def test_process_rng_is_the_documented_seeding():
    import zlib

    want = np.random.Generator(np.random.PCG64(np.random.SeedSequence([5, 2, zlib.crc32(b"radar2d")])))
    np.testing.assert_array_equal(process_rng(5, "radar2d", 2).random(8), want.random(8))
    assert not np.array_equal(process_rng(5, "radar2d").random(8), process_rng(5, "angle").random(8))
    with pytest.raises(ValueError, match="seed"):
        process_rng(-1, "x")


def test_detection_probability_is_respected(tmp_path):
    sc = write_scenario(tmp_path, """
        [sensors.s]
        kind = "angle"
        pos_m = [0.0, 0.0, 0.0]
        period_s = 1.0
        std_az_deg = 0.1
        std_el_deg = 0.1
        p_detect = 0.7
    """, duration=4999.0)
    events = list(sensor_events(sc, "s"))
    hits = sum(e.measurement is not None for e in events)
    assert all(e.detected == (e.measurement is not None) and e.in_coverage for e in events)
    assert stats.binomtest(hits, len(events), 0.7).pvalue > ALPHA
    assert [e.measurement.seq for e in events if e.measurement][-1] == hits - 1


@pytest.mark.parametrize("limits, covered", [
    ('fov_az_deg = [30.0, 80.0]', True),
    ('fov_az_deg = [300.0, 40.0]', False),  # a sector through north
    ('fov_el_deg = [20.0, 60.0]', False),
    ('max_range_km = 10.0', False),
    ('max_range_km = 11.0', True),
])
def test_coverage_limits_suppress_measurements(tmp_path, limits, covered):
    sc = write_scenario(tmp_path, f"""
        [sensors.s]
        kind = "radar3d"
        pos_m = [0.0, 0.0, 0.0]
        period_s = 1.0
        std_az_deg = 1.0
        std_el_deg = 1.0
        std_range_m = 10.0
        {limits}
    """, duration=20.0)
    events = list(sensor_events(sc, "s"))
    assert len(events) == 21
    assert all(e.in_coverage == covered and (e.measurement is not None) == covered for e in events)


def test_azimuth_sector_through_north():
    sc_sensor = dataclasses.replace(
        _dummy_sensor(), fov_az=(math.radians(300.0), math.radians(120.0)))
    for az_deg, inside in ((310, True), (0, True), (59, True), (61, False), (180, False), (299, False)):
        d = np.array([math.sin(math.radians(az_deg)), math.cos(math.radians(az_deg)), 0.0]) * 1000.0
        assert in_coverage(sc_sensor, d) == inside, az_deg


def _dummy_sensor():
    from sensors_sim.spec import SensorSpec, Site

    return SensorSpec("s", "df", Site(np.zeros((1, 3))), 1.0, 0.0, np.array([0.01]))


def test_azimuth_is_compass_and_wrapped_near_north(tmp_path):
    sc = write_scenario(tmp_path, """
        [sensors.df]
        kind = "df"
        pos_m = [0.0, 0.0, 0.0]
        period_s = 1.0
        std_az_deg = 2.0
    """, targets="""
        [targets.T1]
        pos_m = [0.0, 5000.0, 0.0]
    """, duration=999.0)
    z = np.array([e.measurement.z[0] for e in sensor_events(sc, "df")])
    assert np.all((z >= 0) & (z < 2 * math.pi))
    assert np.any(z < 0.5) and np.any(z > 2 * math.pi - 0.5)  # both sides of north
    assert abs(np.mean(wrap_pi(z))) < 3 * math.radians(2.0) / math.sqrt(len(z))


def test_geometry_closed_forms_and_domains():
    # east: az 90°, 45° up: el 45°, slant range √2·1000
    np.testing.assert_allclose(observe("az_el_range", np.array([1000.0, 0.0, 1000.0]), np.zeros(3)),
                               [math.pi / 2, math.pi / 4, math.sqrt(2) * 1000.0])
    np.testing.assert_allclose(observe("bearing", np.array([-1.0, -1.0, 5.0]), np.zeros(3)), [5 * math.pi / 4])
    np.testing.assert_allclose(finish_measurement("az_el_range", np.array([-0.1, 1.7, -3.0])),
                               [2 * math.pi - 0.1, math.pi / 2, 0.0])


def test_airborne_df_site_follows_its_flight_path(tmp_path):
    sc = write_scenario(tmp_path, """
        [sensors.adf]
        kind = "airborne_df"
        path_km = [[0.0, 0.0, 5.0], [30.0, 30.0, 5.0]]
        path_t_s = [0.0, 300.0]
        period_s = 150.0
        std_az_rad = 0.0175
    """, targets="""
        [targets.T1]
        pos_km = [141.0, 141.0]
    """, duration=450.0)
    sites = [e.measurement.site for e in sensor_events(sc, "adf")]
    np.testing.assert_allclose(sites, [[0, 0, 5000], [15000, 15000, 5000], [30000, 30000, 5000],
                                       [30000, 30000, 5000]])


def test_one_event_per_scan_per_target_in_configured_order(tmp_path):
    sc = write_scenario(tmp_path, """
        [sensors.df]
        kind = "df"
        pos_m = [0.0, 0.0, 0.0]
        period_s = 2.0
        std_az_rad = 0.01
        targets = ["B", "A"]
    """, targets="""
        [targets.A]
        pos_km = [10.0, 0.0]
        [targets.B]
        pos_km = [0.0, 10.0]
    """, duration=4.0)
    events = list(sensor_events(sc, "df"))
    assert [(e.t, e.target) for e in events] == [(0.0, "B"), (0.0, "A"), (2.0, "B"), (2.0, "A"),
                                                 (4.0, "B"), (4.0, "A")]
    assert [e.measurement.seq for e in events] == list(range(6))


def test_unknown_sensor_is_a_clear_error(big):
    with pytest.raises(KeyError, match="no sensor 'nope'"):
        next(sensor_events(big, "nope"))
