"""fusion.oosm.Refiltering with many targets: a late sensor re-filtered gives the
in-order picture (ids and states), and a checkpoint shares the measurements it holds
but none of the estimator's state."""

from __future__ import annotations

import numpy as np

from fusion.methods import make_method
from fusion.oosm import Refiltering
from services.evaluation import merged_measurements, run_method


def _late_stream(scenario, late_sensor: str, delay_frames: int):
    """Run 0's measurements, the others in order, ``late_sensor``'s ``delay_frames``
    frames late: yields (released batch, release time, late batch)."""
    ms = merged_measurements(scenario, 0)
    times = sorted({m.t for m in ms})
    on_time = {t: [m for m in ms if m.t == t and m.sensor != late_sensor] for t in times}
    late = {t: [m for m in ms if m.t == t and m.sensor == late_sensor] for t in times}
    for k, t in enumerate(times):
        back = times[k - delay_frames] if k >= delay_frames else None
        yield on_time[t], t, (late[back] if back is not None else [])


def test_many_targets_refiltered_are_the_in_order_picture(crossing):
    """The crossing scenario, SS with association, the angle sensor two frames late:
    after each re-filtering the corrected history equals the method run in order on
    what was received, track ids included (a replay that lost or swapped a track, or a
    checkpoint sharing state with the live tracker, would not)."""
    rf = Refiltering(make_method("SS", dict(crossing.tracker)), window=10.0)
    received: list = []
    checked = 0
    for batch, t, late in _late_stream(crossing, "angle", delay_frames=2):
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
