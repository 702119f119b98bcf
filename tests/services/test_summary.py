"""The incremental scoring of one run (services.summary.Running, RunScorer; many targets:
fusion.mtt_metrics.TrackScorer) against the batch aggregation and closed forms: a live
run's summary must be the one the batch would give on the same estimates, in bounded
memory."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from fusion.types import Estimate
from sensors_sim import load_scenario
from services.evaluation import run_method
from sensors_sim.traffic import Traffic
from services import summary as summary_module
from services.scoring import score_run, score_tracks_of, truth_function
from services.summary import (SERIES_MAX, RunScorer, Running, aggregate, method_summary, on_time_base,
                              scenario_times, tracks_summary)

EPOCH = 1.7e9  # a UTC time base


def _record(t: float, pos2: float, nees: float = 3.0) -> dict:
    return {"t": t, "n": 6, "pos2": pos2, "vel2": 2.0 * pos2, "acc2": None, "nees": nees, "nis": 2.0,
            "nis_dof": 2, "eh": (0.0, 0.0)}


def _same(got: dict, ref: dict) -> None:
    """Equal to the bit but for the means, which NumPy takes pairwise (equal to rounding)."""
    got, ref = {**got, "second_half": dict(got["second_half"])}, {**ref, "second_half": dict(ref["second_half"])}
    for a, b in ((got, ref), (got["second_half"], ref["second_half"])):
        assert a.pop("anees") == pytest.approx(b.pop("anees"), rel=1e-12)
    assert got == ref


def _running(records) -> dict:
    r = Running()
    for er in records:
        r.add(er)
    return r.summary()


@pytest.fixture(scope="module")
def orbit():
    sc = dataclasses.replace(load_scenario("patent-3d-orbit"), duration=300.0)
    return sc, run_method(sc, "SS")


def test_running_is_the_batch_aggregate_on_a_real_run(orbit):
    sc, estimates = orbit
    records = score_run(estimates, truth_function(sc), 0)
    assert len(records) > 200
    _same(_running(records), aggregate([records]))  # the sums are taken in the batch's order


def test_running_series_binned_in_closed_form():
    """pos2 = t at t = 1..n: the overall RMS is √((n+1)/2), a point of k times the RMS of its t."""
    n = 2 * SERIES_MAX + 10  # the batch bins ⌈n / SERIES_MAX⌉ = 3 times a point, Running 4 (a power of two)
    records = [_record(float(t), float(t)) for t in range(1, n + 1)]
    got = _running(records)
    assert got["rmse_pos"] == pytest.approx(math.sqrt((n + 1) / 2), rel=1e-12)
    assert got["anees"] == 3.0 and got["n_updates"] == n
    s = got["series"]
    assert s["bin"] == 4 and len(s["t"]) == math.ceil(n / 4) <= SERIES_MAX
    for j in (0, 1, len(s["t"]) // 2):
        ts = range(4 * j + 1, 4 * j + 5)
        assert s["t"][j] == ts[-1] and s["n"][j] == 4
        assert s["rmse_pos"][j] == pytest.approx(math.sqrt(sum(ts) / 4), rel=1e-12)
    # the second half to within one point: pos2 = t from t = (1 + n)/2 on
    lo = math.ceil((1 + n) / 2)
    assert got["second_half"]["rmse_pos"] == pytest.approx(math.sqrt((lo + n) / 2), rel=4 / n)
    # where the batch bins the same (2 times a point), the series are the batch's
    records = records[:SERIES_MAX + 100]
    ref, got = aggregate([records]), _running(records)
    assert got["series"] == ref["series"] and ref["series"]["bin"] == 2


def test_live_scorer_is_the_batch_on_the_latest_estimates_and_holds_only_the_window(orbit):
    """A live stream (UTC times) where a re-filtering re-publishes corrected estimates of
    the last seconds: settled as it goes, scored as the batch scores the latest of each
    (track, t), while holding only the settle window."""
    sc, estimates = orbit
    utc = [dataclasses.replace(e, t=e.t + EPOCH) for e in estimates]
    stream = []
    for i, e in enumerate(utc):
        # two of every five estimates published wrong, corrected 2-3 updates later (a
        # re-filtering), one of them twice
        stream.append(dataclasses.replace(e, x=e.x + 50.0) if i % 5 in (1, 2) else e)
        if i % 5 == 4:
            stream += [utc[i - 3], dataclasses.replace(utc[i - 2], nis=None), utc[i - 2]]
    settle_s = 5.0
    scorer = RunScorer(sc, EPOCH, settle_s)
    held = 0
    for e in stream:
        scorer.add(e)
        held = max(held, len(scorer.pending))
    got = scorer.method_summary()
    ref = on_time_base(method_summary([scenario_times(stream, EPOCH)], truth_function(sc)), EPOCH)
    _same(got, ref)
    assert scorer.late == 0 and scorer.n == len(stream)
    period = float(np.median(np.diff([e.t for e in estimates])))
    assert held <= (settle_s + 1.0) / period + 2  # the window, not the run


def test_scenario_scorer_is_method_summary_in_arrival_order(orbit):
    sc, estimates = orbit
    scorer = RunScorer(sc)
    for e in estimates:
        scorer.add(e)
    assert scorer.method_summary() == method_summary([estimates], truth_function(sc))


def test_live_scorer_memory_is_bounded_by_the_window_and_series():
    """Ten hours of 1 Hz estimates: what is held is the settle window and SERIES_MAX points."""
    sc = load_scenario("patent-3d-orbit")
    scorer = RunScorer(sc, EPOCH, 3.0)
    P = np.eye(9)
    for k in range(36_000):
        scorer.add(Estimate(t=EPOCH + k, x=np.zeros(9), P=P, method="SS"))
        assert len(scorer.pending) <= 5
    assert len(scorer.running.series) <= SERIES_MAX and not scorer.kept
    assert scorer.method_summary()["n_updates"] == 36_000


@pytest.fixture(scope="module")
def air_live():
    """A real many-target run: 200 s of endless traffic (aircraft leave and are born)."""
    sc = dataclasses.replace(load_scenario("air-picture-live"), duration=200.0)
    return sc, run_method(sc, "SS")


def test_live_many_target_scorer_is_the_batch(air_live, monkeypatch):
    """Many targets, live: the settled estimates cut into steps and folded into the
    streaming score (forgetting what is 20 steps gone) give the batch's summary of the
    latest estimates, to the bit, while holding the window and the recent targets and tracks."""
    monkeypatch.setattr(summary_module, "FORGET_STEPS", 20)
    sc, estimates = air_live
    utc = [dataclasses.replace(e, t=e.t + EPOCH) for e in estimates]
    stream = []
    for i, e in enumerate(utc):  # every fifth estimate published wrong, corrected 3 estimates later
        stream.append(dataclasses.replace(e, x=e.x + 500.0) if i % 5 == 1 else e)
        if i % 5 == 4:
            stream.append(utc[i - 3])
    scorer = RunScorer(sc, EPOCH, 5.0)
    held = 0
    for e in stream:
        scorer.add(e)
        held = max(held, len(scorer.tracks.on_counts))
    played = dataclasses.replace(sc, duration=scorer.played())
    got = scorer.method_summary(played)
    ref = on_time_base(tracks_summary([score_tracks_of(played, scenario_times(stream, EPOCH))]), EPOCH)
    assert got == ref
    assert scorer.tracks.closed.n_tracks > 10 and scorer.tracks.worst_forgotten is not None  # forgetting exercised
    assert held <= ref["tracks"] - scorer.tracks.closed.n_tracks // 2 and not scorer.kept and scorer.steps.late == 0


def test_live_many_target_scorer_memory_is_bounded(monkeypatch):
    """2,000 s of air-picture-live traffic, each aircraft followed by a track named after
    it and a clutter track now and then, forgetting after 100 steps, in 500 points: what
    is held is the live aircraft and tracks, the settle window and the points."""
    monkeypatch.setattr(summary_module, "FORGET_STEPS", 100)
    monkeypatch.setattr(summary_module, "SERIES_MAX", 500)
    sc = load_scenario("air-picture-live")
    traffic = Traffic(sc.traffic, sc.seed, 0)
    scorer = RunScorer(sc, EPOCH, 3.0)
    P = np.eye(9)
    flown = set()
    for k in range(2_000):
        t = float(k)
        for a in traffic.alive(t):
            flown.add(a.id)
            scorer.add(Estimate(t=EPOCH + t, x=np.concatenate([a.position(t), np.zeros(6)]), P=P, method="SS",
                                track=f"T{a.id}"))
        if k % 10 < 3:
            scorer.add(Estimate(t=EPOCH + t, x=np.zeros(9), P=P, method="SS", track=f"G{k // 10}"))
        assert len(scorer.tracks.on_counts) <= sc.traffic.max_alive + 10 + 100 * 0.1 + 100 / 15 + 2
        assert len(scorer.tracks.found) <= sc.traffic.max_alive + 10 + 100 / 15 + 2
    doc = scorer.method_summary(dataclasses.replace(sc, duration=scorer.played()))
    assert len(scorer.tracks.binned) <= 500 and scorer.tracks.closed.n_tracks > 200
    assert doc["steps"] == 2_000 and doc["series"]["bin"] == 4 and len(doc["series"]["t"]) == 500
    assert doc["held"] == 1.0 and doc["false_tracks"] == 200 and doc["tracks"] == 200 + len(flown)


def _lose(sc, estimates, epoch: float | None, at: float) -> dict:
    scorer = RunScorer(sc) if epoch is None else RunScorer(sc, epoch, 5.0)
    scorer.lose("fuser", at)
    for e in estimates:
        scorer.add(e if epoch is None else dataclasses.replace(e, t=e.t + epoch))
    scorer.method_summary(dataclasses.replace(sc, duration=scorer.played()))
    return scorer.loss("fuser")


def test_a_loss_is_followed_through_the_run_s_steps_live_or_not(air_live):
    """A fuser lost at 100 s and its output gone until 130 s: each of the 13 aircraft the
    picture held at the loss (its step at 100 s) is absent until the first step after
    the gap, 131 s (or until it leaves: not back), over two of the 1 s radars' periods;
    live (settling) and not, the same counts. Undisturbed, one step: 1 s."""
    sc, estimates = air_live
    gone = [e for e in estimates if not 100.0 < e.t <= 130.0]
    got = _lose(sc, gone, None, 100.0)
    assert got == {"aircraft": 13, "longest_absence_s": 31.0, "absent_over_2_periods": 13, "not_back": 2,
                   "period_s": 1.0}
    assert _lose(sc, gone, EPOCH, 100.0) == got
    assert _lose(sc, estimates, None, 100.0) == {**got, "longest_absence_s": 1.0, "absent_over_2_periods": 0,
                                                 "not_back": 0}
