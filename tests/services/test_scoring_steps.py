"""Steps of an air picture for scoring: targets settle at their third look by any
sensor; with rotating radars the picture is every second, each track's latest estimate
moved along its velocity, gone a slowest turn after its last."""

from __future__ import annotations

import numpy as np

from fusion.types import Estimate
from sensors_sim import load_scenario, sensor_events, truth_trajectory
from services.evaluation import evaluate, merged_measurements, variants_for
from services.scoring import Looks, PICTURE_STEP_S, PictureSteps, TrackSteps, step_maker, track_steps

from conftest import CROSSING, DATA


def _third_looks(scenario) -> dict[str, float]:
    """Independently: per target, the third smallest time it was in a sensor's coverage."""
    times: dict[str, list[float]] = {}
    for sid in scenario.sensors:
        for ev in sensor_events(scenario, sid):
            if ev.in_coverage and not ev.clutter:
                times.setdefault(ev.target, []).append(ev.t)
    return {k: sorted(v)[2] for k, v in times.items() if len(v) >= 3}


def test_targets_settle_at_their_third_look_by_any_sensor():
    """crossing.toml (a 2D radar and an angle sensor, P_D 0.9, clutter): each step marks a
    target settled exactly from its third look on, whether the looks follow the streams
    or were seen while the evaluation generated them; the evaluation reports the held
    fraction over those truth-steps."""
    sc = load_scenario(CROSSING)
    third = _third_looks(sc)
    assert set(third) == set(sc.targets)
    fed = Looks()
    merged_measurements(sc, looks=fed)
    for looks in (Looks.following(sc), fed):
        for step in track_steps(sc, [], looks=looks):
            assert step.settled == {k for k in step.truths if third[k] <= step.t}
    doc = evaluate(sc, variants_for(["SS"]), 1)["methods"]["SS"]
    assert doc["held"] < doc["held_after_init"] <= 1.0 and doc["held_after_init"] > 0.9


def test_a_rotating_scenario_is_scored_on_the_picture_every_second():
    """tests/data/rotating.toml: a perfect tracker's estimates (the truth at a few plot
    times up to 20 s) give a picture held at every step from the first estimate to 20 s
    plus the slowest turn (6 s), the track moved along its velocity (off the CA truth by
    at most ½·a·Δt²), then nothing; steps at 0, 1, ..., 40 s."""
    sc = load_scenario(DATA / "rotating.toml")
    assert isinstance(step_maker(sc), PictureSteps) and isinstance(step_maker(load_scenario(CROSSING)), TrackSteps)
    truth = truth_trajectory(sc, "T1")
    times = [0.7, 3.3, 6.1, 9.8, 14.2, 17.0, 19.9]
    estimates = [Estimate(t, truth.state(t), np.eye(9), "SS", track="T1") for t in times]
    steps = track_steps(sc, estimates)
    assert [s.t for s in steps] == [k * PICTURE_STEP_S for k in range(41)]
    for s in steps:
        if s.t < 0.7 or s.t > 19.9 + 6.0:
            assert not s.tracks, s.t
            continue
        e = max((e for e in estimates if e.t <= s.t), key=lambda e: e.t)
        moved = e.x[:3] + e.x[3:6] * (s.t - e.t)
        np.testing.assert_allclose(s.tracks["T1"], moved, rtol=0, atol=1e-9)
        assert np.linalg.norm(moved - s.truths["T1"]) < 0.5 * 5.0 * (s.t - e.t) ** 2 + 1.0
