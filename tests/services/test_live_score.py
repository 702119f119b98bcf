"""The recorder's panels are scored in services/scoring.py (LiveScore), in any arrival
order, with the numbers of the batch scoring zfusion run and zfusion eval report."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.stats import chi2

from fusion.types import Estimate
from services.scoring import LiveScore, chi2_interval, score_run


def _truth(t: float) -> np.ndarray:
    return np.array([100.0 * t, 50.0, 1000.0, 100.0, 0.0, 0.0, 0.0, 0.0, 0.0])


def _estimates(n: int) -> list[Estimate]:
    rng = np.random.default_rng(7)
    P = np.diag(rng.uniform(1.0, 9.0, 9))
    return [Estimate(float(k), _truth(k) + rng.normal(0.0, 2.0, 9), P, "SS", "centre", "T1", float(k), 3)
            for k in range(n)]


@pytest.mark.parametrize("truth_first", [True, False])
def test_errors_and_nees_are_the_batch_scorings_in_either_order(truth_first):
    estimates = _estimates(6)
    live = LiveScore(many=False)
    got = []
    if truth_first:
        for e in estimates:
            got += live.truth("T1", e.t, _truth(e.t))
        for e in estimates:
            got += live.estimate(e, fused=True)
    else:
        for e in estimates:
            got += live.estimate(e, fused=True)
        for e in estimates:
            got += live.truth("T1", e.t, _truth(e.t))
    batch = score_run(estimates, lambda run, track, t: _truth(t), 0)
    err = {p.t: p.value for p in got if p.metric == "error_pos"}
    nees = {p.t: p for p in got if p.metric == "nees"}
    assert sorted(err) == [e.t for e in estimates]
    for r in batch:
        assert err[r["t"]] == pytest.approx(math.sqrt(r["pos2"]), rel=1e-12)
        assert nees[r["t"]].value == pytest.approx(r["nees"], rel=1e-12)
        assert nees[r["t"]].dof == 9
    nis = [p for p in got if p.metric == "nis"]
    assert [p.value for p in nis] == [e.nis for e in estimates] and all(p.dof == 3 for p in nis)


def test_the_bounds_are_the_95_percent_interval_of_one_chi2_sample():
    for dof in (1, 2, 3, 6, 9):
        assert chi2_interval(dof) == pytest.approx(tuple(chi2.ppf([0.025, 0.975], dof)), rel=1e-12)


def test_a_many_target_frame_is_scored_once_a_later_frame_and_truth_close_it():
    live = LiveScore(many=True)
    a, b = _truth(1.0), _truth(1.0) + np.r_[0.0, 3000.0, np.zeros(7)]
    out = live.truth("A", 1.0, a) + live.truth("B", 1.0, b)
    out += live.estimate(Estimate(1.0, a.copy(), np.eye(9), "SS", "centre", "T1"), fused=True)
    assert [p.metric for p in out] == []  # the frame may still grow
    out = live.truth("A", 2.0, _truth(2.0))
    assert out == []  # the method may still add to its frame of t = 1
    out = live.estimate(Estimate(2.0, _truth(2.0), np.eye(9), "SS", "centre", "T1"), fused=True)
    assert [(p.metric, p.t) for p in out] == [("gospa", 1.0), ("missed", 1.0), ("false", 1.0)]
    assert out[0].value == pytest.approx(1000.0 / math.sqrt(2))  # one target missed: c / 2^(1/p)
    assert (out[1].value, out[2].value) == (1.0, 0.0)
    assert [(p.metric, p.t) for p in live.finish()] == [("gospa", 2.0), ("missed", 2.0), ("false", 2.0)]
