"""fusion.oosm.Refiltering: a late sensor re-filtered gives the in-order estimates (one
target; many targets, ids included), what is older than the buffer is refused, and a
checkpoint shares the measurements it holds but none of the estimator's state."""

from __future__ import annotations

import numpy as np
import pytest

from fusion.methods import make_method, method_config
from fusion.oosm import Refiltering
from sensors_sim import load_scenario
from services.evaluation import merged_measurements, run_method


def _late_stream(scenario, late_sensor: str, delay_scans: int):
    """The scenario's measurements, the others in order, ``late_sensor``'s ``delay_scans``
    scans late: yields (released batch, release time, late batch)."""
    ms = merged_measurements(scenario, 0)
    times = sorted({m.t for m in ms})
    on_time = {t: [m for m in ms if m.t == t and m.sensor != late_sensor] for t in times}
    late = {t: [m for m in ms if m.t == t and m.sensor == late_sensor] for t in times}
    for k, t in enumerate(times):
        back = times[k - delay_scans] if k >= delay_scans else None
        yield on_time[t], t, (late[back] if back is not None else [])


def _in_order(sc, method: str, received: list) -> dict:
    """The in-order result: the method run on what was received, sorted, as if nothing
    had been late; its (last) centre estimate at each time."""
    out = run_method(sc, method, measurements=sorted(received, key=lambda m: m.order_key))
    return {e.t: e for e in out if e.node == "centre"}


@pytest.mark.parametrize("scenario_name, method, late_sensor", [
    ("patent-3d", "SS", "angle"),
    ("patent-3d", "LCDD", "radar2d"),
    ("thesis-fixed-c1", "EKF", None),
])
def test_refiltering_gives_the_in_order_estimate(scenario_name, method, late_sensor):
    sc = load_scenario(scenario_name)
    late_sensor = late_sensor or list(sc.sensors)[0]
    rf = Refiltering(make_method(method, method_config(sc.tracker, method)), window=10.0)
    received: list = []
    republished = 0
    for batch, t, late in _late_stream(sc, late_sensor, delay_scans=2):
        received += late
        fixed = [e for e in rf.insert(late) if e.node == "centre"]
        if fixed:  # the corrected history, from the late data's time to the current picture
            assert fixed[-1].t >= max(m.t for m in late) and fixed == sorted(fixed, key=lambda e: e.t)
            ref = _in_order(sc, method, received)
            for e in fixed:
                np.testing.assert_allclose(e.x, ref[e.t].x, rtol=0, atol=1e-9)
                np.testing.assert_allclose(e.P, ref[e.t].P, rtol=0, atol=1e-9 * max(1.0, np.abs(ref[e.t].P).max()))
            republished += 1
        received += batch
        rf.step(batch, t)
    assert republished >= 10
    assert len(rf) <= 10 / min(s.period for s in sc.sensors.values()) + 3  # bounded by the window


def test_a_late_measurement_dropped_would_change_the_estimate():
    """The guard of the test above: without re-filtering the late sensor, the estimate is
    not the in-order one (so equality there is not an accident of the scenario)."""
    sc = load_scenario("patent-3d")
    ref = [e for e in run_method(sc, "SS") if e.node == "centre"]
    rf = Refiltering(make_method("SS", method_config(sc.tracker, "SS")), window=10.0)
    out = []
    for batch, t, _late in _late_stream(sc, "angle", delay_scans=2):
        out.extend(rf.step(batch, t))
    assert abs(out[-1].x[0] - ref[-1].x[0]) > 1e-3 or abs(out[-1].x[1] - ref[-1].x[1]) > 1e-3


def test_refiltering_refuses_what_is_older_than_its_buffer():
    sc = load_scenario("patent-3d")
    rf = Refiltering(make_method("SS", method_config(sc.tracker, "SS")), window=3.0)
    stream = list(_late_stream(sc, "angle", delay_scans=0))
    for batch, t, _ in stream[:10]:
        rf.step(batch, t)
    assert rf.oldest <= 9.0 - 3.0 and rf.oldest > 9.0 - 3.0 - 1.0 - 1e-9
    old = [m for m in merged_measurements(sc, 0) if m.sensor == "angle" and m.t <= rf.oldest][-1]
    with pytest.raises(ValueError, match="older than the re-filtering buffer"):
        rf.insert([old])


def test_many_targets_refiltered_are_the_in_order_picture(crossing):
    """The crossing scenario, SS with association, the angle sensor two frames late:
    after each re-filtering the corrected history equals the method run in order on
    what was received, track ids included (a replay that lost or swapped a track, or a
    checkpoint sharing state with the live tracker, would not)."""
    rf = Refiltering(make_method("SS", dict(crossing.tracker)), window=10.0)
    received: list = []
    checked = 0
    for batch, t, late in _late_stream(crossing, "angle", delay_scans=2):
        received += late
        fixed = rf.insert(late)
        if fixed:
            ref = {(e.t, e.track): e for e in run_method(crossing, "SS",
                                                            measurements=sorted(received, key=lambda m: m.order_key))}
            for e in fixed:
                r = ref[(e.t, e.track)]
                np.testing.assert_array_equal(e.x, r.x)
                np.testing.assert_array_equal(e.P, r.P)
            checked += len(fixed)
        received += batch
        rf.step(batch, t)
    assert checked > 250


def test_a_checkpoint_shares_the_measurements_and_nothing_else(crossing):
    """After 20 frames the method holds an open frame; the latest checkpoint holds the
    very measurement objects of the log, and its own copies of every track."""
    rf = Refiltering(make_method("SS", dict(crossing.tracker)), window=10.0)
    stream = merged_measurements(crossing, 0)
    times = sorted({m.t for m in stream})[:20]
    for t in times:
        rf.step([m for m in stream if m.t == t], t - 0.5)  # the frame at t stays open
    copy = rf._checkpoints[-1].method
    logged = {id(m) for _, m in rf._log}
    held = copy._grouper.finish()[0]
    assert held and all(id(m) in logged for m in held)
    live_tracks, copied_tracks = rf.method.tracks, copy.tracks
    assert len(live_tracks) == len(copied_tracks) > 0
    for a, b in zip(live_tracks, copied_tracks):
        assert a is not b and a.filter is not b.filter and a.logic is not b.logic
        np.testing.assert_array_equal(a.filter.x, b.filter.x)


def test_items_released_past_the_watermark_then_a_late_one_of_their_time():
    """A live release forced past a lagging source's watermark hands ``step`` items later
    than its ``t``; a late measurement of one of their times then replays from a
    checkpoint that has not seen them, in order: the in-order estimate (before, the
    checkpoint was stamped ``t`` but held the later items, and the replay raised "out of
    order" out of the DF EKF, which stopped a live fuser)."""
    sc = load_scenario("thesis-fixed-c1")
    ms = merged_measurements(sc, 0)
    times = sorted({m.t for m in ms})[:6]
    first = min(sc.sensors)
    rf = Refiltering(make_method("EKF", method_config(sc.tracker, "EKF")), window=10.0)
    received: list = []
    for k, t in enumerate(times):
        scan = [m for m in ms if m.t == t]
        on_time = scan if k < 4 else [m for m in scan if m.sensor != first]
        received += on_time
        rf.step(on_time, times[k - 1] if k else -np.inf)  # released past the merged watermark
    late = [m for m in ms if m.t in times[4:] and m.sensor == first]
    received += late
    fixed = [e for e in rf.insert(late) if e.node == "centre"]
    ref = _in_order(sc, "EKF", received)
    assert fixed and fixed[-1].t == times[-1]
    for e in fixed:
        np.testing.assert_allclose(e.x, ref[e.t].x, rtol=0, atol=1e-9)
