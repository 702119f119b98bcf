"""Rotating radars: a plot's time is the beam's crossing of the target, plots come out
sector by sector, false alarms at the time of their azimuth; the streams are
deterministic and the snapshot sensors' are untouched."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest
from scipy import stats

from fusion.angles import wrap_pi
from fusion.measurement.kinds import KINDS
from sensors_sim import ScenarioError, load_scenario, sensor_events, truth_trajectory
from sensors_sim.emulators import beam_crossings, sensor_batches
from sensors_sim.geometry import observe
from sensors_sim.spec import TrafficSpec

ROTATING = Path(__file__).parents[1] / "data" / "rotating.toml"
SC = load_scenario(ROTATING)
TWO_PI = 2.0 * math.pi
ALPHA = 0.01


def busy(duration: float = 600.0, clutter: float = 8.0):
    """rotating.toml's radars over manoeuvring traffic, with clutter: many crossings."""
    traffic = TrafficSpec(rate=30 / 60.0, max_alive=60, box=(-40e3, 70e3, -50e3, 50e3), speed=(120.0, 260.0),
                          alt=(1000.0, 9000.0), waypoints=2, waypoint_offset=15e3, level_changes=1)
    sensors = {k: dataclasses.replace(s, clutter_rate=clutter if s.sectors else 0.0) for k, s in SC.sensors.items()}
    return dataclasses.replace(SC, duration=duration, traffic=traffic, sensors=sensors)


BUSY = busy()


def beam_azimuth(sensor, t: float) -> float:
    return TWO_PI * ((t - sensor.start) % sensor.period) / sensor.period


@pytest.mark.parametrize("scenario", [SC, BUSY], ids=["one target", "traffic"])
@pytest.mark.parametrize("sensor_id", ["radar2d", "radar3d"])
def test_a_plot_is_where_the_beam_was_when_it_was_taken(scenario, sensor_id):
    """Every target plot's time puts the beam on the target's true azimuth at that time
    (to 1e-7 rad), and the plot's error about the truth at its time has the radar's
    Gaussian law (mean, variance and shape at 1 %): the time is the one the measurement
    is of."""
    sensor = scenario.sensor(sensor_id)
    site = sensor.site.position(0.0)
    traffic = {}
    if scenario.traffic is not None:
        from sensors_sim.traffic import Traffic
        cursor = Traffic(scenario.traffic, scenario.seed)
        for t in np.arange(0.0, scenario.duration + 1.0, 1.0):
            traffic.update({a.id: a for a in cursor.alive(float(t))})
    errors = []
    for ev in sensor_events(scenario, sensor_id):
        if ev.measurement is None or ev.clutter:
            continue
        truth = truth_trajectory(scenario, ev.target) if ev.target in scenario.targets else traffic[ev.target]
        h = observe(ev.measurement.kind, truth.position(ev.t), site)
        assert abs(wrap_pi(h[0] - beam_azimuth(sensor, ev.t))) < 1e-7
        e = ev.measurement.z - h
        errors.append(np.where(KINDS[ev.measurement.kind].angles, wrap_pi(e), e) / sensor.std)
    errors = np.array(errors)
    assert len(errors) >= (7 if scenario is SC else 1000)
    if scenario is BUSY:
        n = len(errors)
        for e in errors.T:
            assert abs(e.mean()) * math.sqrt(n) < stats.norm.ppf(1 - ALPHA / 2)
            chi2 = float(np.sum((e - e.mean()) ** 2))
            assert stats.chi2.ppf(ALPHA / 2, n - 1) < chi2 < stats.chi2.ppf(1 - ALPHA / 2, n - 1)
            assert stats.kstest(e, "norm").pvalue > ALPHA


def _crossings_by_sampling(p0, v, site, t_north, period, dt=1e-4):
    """Independent count: the beam-minus-target angle, unwrapped on a fine grid, passes
    a multiple of 2π at each crossing."""
    t = np.arange(t_north, t_north + period, dt)
    d = p0 + v * t[:, None] - site
    az = np.unwrap(np.arctan2(d[:, 0], d[:, 1]))
    phi = TWO_PI * (t - t_north) / period - az
    k = np.floor(phi / TWO_PI)
    return t[1:][np.diff(k) != 0]


@pytest.mark.parametrize("p0, v", [
    ([500.0, 3000.0, 1000.0], [-250.0, 0.0, 0.0]),  # west across north, close: crossed twice in a turn
    ([-400.0, 3000.0, 1000.0], [250.0, 0.0, 0.0]),  # east across north: a turn without a crossing
    ([-2000.0, -800.0, 500.0], [300.0, 40.0, 0.0]),  # a fast pass 800 m south of the radar
    ([20000.0, 15000.0, 8000.0], [-200.0, 120.0, 5.0]),  # far, slow in azimuth
    ([0.0, 50.0, 3000.0], [200.0, 0.0, 0.0]),  # overhead: faster in azimuth than the beam
])
def test_beam_crossings_are_those_a_fine_sampling_finds(p0, v):
    """Straight flights past a radar turning in 12 s, turn by turn over 120 s: the
    crossings (how many in each turn, and when) are those of a 0.1 ms sampling of the
    beam's angle to the target."""
    p0, v, site, period = np.array(p0), np.array(v), np.zeros(3), 12.0

    def kinematics(rows, t):
        return p0 + v * t[:, None], np.broadcast_to(v, (len(t), 3))

    found = 0
    for k in range(10):
        t_north = k * period
        rows, times = beam_crossings(kinematics, 1, site, t_north, period)
        ref = _crossings_by_sampling(p0, v, site, t_north, period)
        assert len(times) == len(ref), (k, times, ref)
        np.testing.assert_allclose(times, ref, atol=2e-4)
        found += len(times)
    assert found >= 7


def test_sectors_cut_each_turn_and_carry_its_plots_in_time_order():
    """Per turn ``sectors`` batches, each a T/S slice of time, back to back from the
    first north crossing to the end; every event inside its slice; seq in time order;
    a false alarm at the time its azimuth has under the beam."""
    for sensor_id in ("radar2d", "radar3d"):
        s = BUSY.sensor(sensor_id)
        batches = list(sensor_batches(BUSY, sensor_id))
        assert batches[0].t0 == s.start
        assert batches[-1].t1 == BUSY.duration
        assert all(a.t1 == b.t0 for a, b in zip(batches, batches[1:]))
        widths = np.array([b.t1 - b.t0 for b in batches[:-1]])
        np.testing.assert_allclose(widths, s.period / s.sectors, rtol=1e-9)
        turns = (BUSY.duration - s.start) / s.period
        assert len(batches) == math.ceil(turns * s.sectors - 1e-9)
        seqs, times, clutter = [], [], 0
        for b in batches:
            for ev in b.events:
                assert b.t0 <= ev.t < b.t1
                if ev.measurement is not None:
                    assert ev.measurement.t == ev.t
                    seqs.append(ev.measurement.seq)
                    times.append(ev.t)
                if ev.clutter:
                    clutter += 1
                    assert abs(wrap_pi(ev.measurement.z[0] - beam_azimuth(s, ev.t))) < 1e-9
        assert seqs == list(range(len(seqs))) and times == sorted(times)
        # false alarms per turn: Poisson(clutter_rate), mean by a z test at 1 %
        mu = s.clutter_rate * turns
        assert abs(clutter - mu) / math.sqrt(mu) < stats.norm.ppf(1 - ALPHA / 2)


def test_detection_probability_over_the_crossings_in_coverage():
    """Of the crossings in coverage, the share detected is P_D (binomial, 1 %)."""
    s = BUSY.sensor("radar2d")
    events = [ev for ev in sensor_events(BUSY, "radar2d") if not ev.clutter]
    assert all(ev.in_coverage for ev in events)
    hits = sum(ev.detected for ev in events)
    assert stats.binomtest(hits, len(events), s.p_detect).pvalue > ALPHA and len(events) > 1000


def _stream(scenario, sensor_id, run=0):
    return [(ev.t, ev.target, None if ev.measurement is None else (ev.measurement.seq, ev.measurement.z.tobytes()))
            for ev in sensor_events(scenario, sensor_id, run)]


def test_streams_are_a_function_of_seed_and_run_and_of_the_sensor_alone():
    """The same stream twice; another run, another; dropping the other sensors, or
    turning radar2d's sectors from 16 to 8, changes nothing in its plots (only in how
    they are batched); the snapshot angle sensor's stream is the one it has without the
    radars."""
    short = dataclasses.replace(BUSY, duration=120.0)
    a = _stream(short, "radar2d")
    assert a == _stream(short, "radar2d") and a != _stream(short, "radar2d", run=1)
    alone = dataclasses.replace(short, sensors={"radar2d": short.sensor("radar2d")})
    assert _stream(alone, "radar2d") == a
    eight = dataclasses.replace(short, sensors={"radar2d": dataclasses.replace(short.sensor("radar2d"), sectors=8)})
    assert _stream(eight, "radar2d") == a and len(list(sensor_batches(eight, "radar2d"))) == 240
    angle = dataclasses.replace(short, sensors={"angle": short.sensor("angle")})
    assert _stream(angle, "angle") == _stream(short, "angle")


HEADER = """
description = "x"
seed = 1
duration_s = 10.0
[origin]
lat_deg = 0.0
lon_deg = 0.0
alt_m = 0.0
[defaults]
topology = "centralised"
method = "SS"
[targets.T1]
pos_m = [1000.0, 2000.0, 300.0]
"""


@pytest.mark.parametrize("sensor, why", [
    ('kind = "radar2d"\npos_m = [0, 0, 0]\nperiod_s = 1.0\nrotation_period_s = 4.0\nstd_az_deg = 1\nstd_range_m = 5',
     "period_s: give period_s (a snapshot sensor) or rotation_period_s (a rotating radar), not both"),
    ('kind = "radar2d"\npos_m = [0, 0, 0]\nperiod_s = 1.0\nsectors = 16\nstd_az_deg = 1\nstd_range_m = 5',
     "sectors: sectors are a rotating radar's: give rotation_period_s"),
    ('kind = "radar2d"\npos_m = [0, 0, 0]\nrotation_period_s = 4.0\nsectors = 0\nstd_az_deg = 1\nstd_range_m = 5',
     "sectors: must be >= 1"),
    ('kind = "angle"\npos_m = [0, 0, 0]\nrotation_period_s = 4.0\nstd_az_deg = 1\nstd_el_deg = 1',
     "rotation_period_s: only a radar's antenna rotates (radar2d, radar3d), not a angle's"),
    ('kind = "radar3d"\npath_m = [[0, 0, 0], [10, 0, 0]]\npath_t_s = [0, 10]\nrotation_period_s = 4.0\n'
     'std_az_deg = 1\nstd_el_deg = 1\nstd_range_m = 5',
     "rotation_period_s: a rotating radar stands still: give it a fixed position"),
])
def test_rotation_keys_are_checked(tmp_path, sensor, why):
    path = tmp_path / "case.toml"
    path.write_text(HEADER + "[sensors.s]\n" + sensor + "\n")
    with pytest.raises(ScenarioError) as e:
        load_scenario(path)
    assert f"sensors.s.{why}" in str(e.value)


def test_rotation_keys_load():
    s = SC.sensor("radar3d")
    assert (s.period, s.sectors, s.start) == (6.0, 32, 1.5)
    assert SC.sensor("radar2d").sectors == 16 and SC.sensor("angle").sectors == 0
