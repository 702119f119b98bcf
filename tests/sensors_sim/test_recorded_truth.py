"""Recorded aircraft as a scenario's truth (``[truth] file = ...``: sensors_sim/loader.py,
sensors_sim/recorded.py's RecordedTraffic): the fixture recording of test_recorded.py (one
aircraft, a 20 s coverage hole, so two segments) as the targets of a small scenario.

References: scipy's CubicHermiteSpline through each segment's smoothed states (the
vectorised Hermite must equal it), and the segment boundaries of test_recorded.py (the
emulators and the scoring must see the aircraft exactly there).
"""

from __future__ import annotations

import importlib.metadata
from pathlib import Path

import numpy as np
import pytest

from fusion.geodetic import LocalFrame
from fusion.types import Estimate, Identity
from sensors_sim import load_scenario, sensor_events, truth_events
from sensors_sim.recorded import RecordedTraffic, Recording, read_jsonl
from sensors_sim.spec import ScenarioError
from sensors_sim.traffic import population
from services.scoring import many_targets, track_steps, truth_positions

DATA = Path(__file__).resolve().parents[1] / "data" / "adsb"
T0 = 1633608000  # the fixture's first record
HOLE = (119.0, 140.0)  # scenario seconds: the first segment's end, the second's start
END = 173.0  # the second segment's last new position

SCENARIO = """
description = "the fixture recording"
seed = 3
duration_s = 200.0
[origin]
lat_deg = 48.85
lon_deg = 2.35
alt_m = 0.0
[defaults]
topology = "centralised"
method = "SS"
[truth]
file = "{file}"
{extra}
[sensors.adsb]
kind = "adsb"
period_s = 1.0
std_pos_m = 30.0
std_alt_m = 15.0
[sensors.radar]
kind = "radar2d"
pos_km = [0.0, 0.0, 0.1]
rotation_period_s = 4.0
std_az_deg = 0.2
std_range_m = 50.0
max_range_km = 80.0
"""


def scenario(tmp_path, file=str(DATA / "recorded.jsonl"), extra=""):
    path = tmp_path / "rec.toml"
    path.write_text(SCENARIO.format(file=file, extra=extra))
    return load_scenario(path)


def test_hermite_of_every_segment_at_once_equals_scipys():
    rec = Recording(read_jsonl(DATA / "recorded.jsonl"), LocalFrame(48.85, 2.35, 0.0, deg=True))
    traffic = RecordedTraffic(rec, T0)
    segs = sorted(rec.segments, key=lambda s: s.start)
    rng = np.random.default_rng(1)
    rows = rng.integers(0, len(segs), 400)
    t = traffic.t0[rows] + rng.random(400) * (traffic.t1[rows] - traffic.t0[rows])
    t[:len(segs)] = traffic.t0[:len(segs)]  # the knots themselves
    rows[:len(segs)] = np.arange(len(segs))
    p, v, a = traffic.kinematics(rows, t)
    ref = np.array([segs[r].state(tt + T0) for r, tt in zip(rows, t)])
    np.testing.assert_allclose(p, ref[:, :3], atol=1e-5)  # (the spline's times are UTC: 1.6e9 s)
    np.testing.assert_allclose(v, ref[:, 3:6], atol=1e-6)
    np.testing.assert_allclose(a, ref[:, 6:], atol=1e-6)
    # outside its segment, a segment goes on along its end velocity, without acceleration
    end = traffic.kinematics([0], [traffic.t1[0]])
    after = traffic.kinematics([0], [traffic.t1[0] + 3.0])
    np.testing.assert_allclose(after[0], end[0] + 3.0 * end[1], atol=1e-9)
    assert not after[2].any()


def test_the_recording_is_the_scenarios_targets(tmp_path):
    sc = scenario(tmp_path)
    traffic = population(sc)
    assert many_targets(sc) and sc.targets == {} and traffic is sc.traffic
    assert traffic.t_zero == T0 and traffic.ids.tolist() == ["39b002", "39b002"]
    np.testing.assert_allclose(np.c_[traffic.t0, traffic.t1], [[0.0, HOLE[0]], [HOLE[1], END]])
    assert traffic.max_alive == 1
    for t, alive in ((0.0, ["39b002"]), (60.5, ["39b002"]), (130.0, []), (150.0, ["39b002"]), (END + 1, [])):
        assert traffic.fleet(t).ids == alive
        assert list(truth_positions({}, traffic, t)) == alive  # scored only while it exists
    truths = [s for s in truth_events(sc, period=1.0)]
    assert {s.t for s in truths} == set(range(0, 119)) | set(range(140, 173))


def test_sensors_see_the_aircraft_only_within_its_segments(tmp_path):
    sc = scenario(tmp_path)
    for sid in sc.sensors:
        events = [e for e in sensor_events(sc, sid) if e.target]
        assert events and all(e.target == "39b002" for e in events), sid
        assert all(0.0 <= e.t < HOLE[0] or HOLE[1] <= e.t < END for e in events), sid
        assert {e.t < HOLE[0] for e in events} == {True, False}, sid  # both segments seen
    reports = [e.measurement for e in sensor_events(sc, "adsb")]
    assert len(reports) == 119 + 33 and all(m.identity == Identity("39b002", "FHMAC") for m in reports)
    truth = population(sc)
    errors = [np.linalg.norm(m.z - truth.fleet(m.t).positions(m.t)[0]) for m in reports]
    assert 20.0 < np.sqrt(np.mean(np.square(errors))) < 70.0  # 30 m x √2 horizontally, 15 m up: 45 m
    assert all(m.identity is None for m in (e.measurement for e in sensor_events(sc, "radar")) if m)


def test_a_quarter_without_adsb_is_drawn_from_the_seed():
    rec = Recording(read_jsonl(DATA / "recorded.jsonl"), LocalFrame(48.85, 2.35, 0.0, deg=True))
    many = RecordedTraffic(rec, T0, without_adsb=0.25)
    many.ids = np.array([f"{i:06x}" for i in range(40)])  # forty aircraft's names
    for seed in (1, 2):
        assert len(many.equipped(seed)) == 30 and many.equipped(seed) == many.equipped(seed)
    assert many.equipped(1) != many.equipped(2)


def test_the_steps_score_the_aircraft_only_while_it_exists(tmp_path):
    sc = scenario(tmp_path)
    traffic = population(sc)
    estimates = [Estimate(t=float(t), x=np.r_[traffic.fleet(t).positions(t)[0], 0, 0, 0], P=np.eye(6), method="SS",
                          track="T1") for t in np.arange(0.0, END, 1.0) if traffic.fleet(t).ids]
    steps = track_steps(sc, estimates)
    held = [s for s in steps if s.truths]
    assert {s.t for s in held} == set(range(0, 119)) | set(range(140, 173))
    assert all(np.linalg.norm(s.tracks["T1"] - s.truths["39b002"]) < 250.0 for s in held if "T1" in s.tracks)


@pytest.mark.parametrize("file, extra, message", [
    ("nowhere.jsonl", "", r"rec.toml:\d+: truth.file: no such file: .*nowhere.jsonl"),
    (str(DATA / "recorded.jsonl"), "start_s = 5000.0",
     r"truth.start_s: no aircraft in the window \[5000, 5200\] s of the recording \(217 s long\)"),
    (str(DATA / "recorded.jsonl"), "format = \"csv\"", r"truth.format: "),
    (str(DATA / "recorded.jsonl"), "keep_ground = 1", r"truth.keep_ground: must be true or false"),
])
def test_one_line_errors(tmp_path, file, extra, message):
    with pytest.raises(ScenarioError, match=message) as e:
        scenario(tmp_path, file, extra)
    assert "\n" not in str(e.value)


def test_a_missing_traffic_package_says_the_pip_command(tmp_path, monkeypatch):
    def missing(name):
        raise importlib.metadata.PackageNotFoundError(name)

    monkeypatch.setattr(importlib.metadata, "distribution", missing)
    with pytest.raises(ScenarioError, match=r"truth.file: .*pip install --no-deps traffic==2.13$"):
        scenario(tmp_path, "traffic:quickstart")
