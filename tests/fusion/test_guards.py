"""The estimators' guards (fusion/guards.py): a track more than ``max_gap_s`` after its
state starts afresh exactly as a new one would; an epoch's NIS stays within the wire's 64
degrees of freedom; the positive-definiteness test."""

from __future__ import annotations

import dataclasses
from functools import lru_cache
from pathlib import Path

import numpy as np
import pytest

from fusion.guards import MAX_GAP_S, NIS_MAX_DOF, epoch_nis, gap_too_long, positive_definite
from fusion.methods import make_method, method_config
from schemas.messages import MAX_DIM
from sensors_sim import load_scenario, sensor_events

CROSSING = Path(__file__).resolve().parents[1] / "data" / "crossing.toml"


@lru_cache(maxsize=None)
def _scenario(name: str):
    sc = load_scenario(name)
    ms = [ev.measurement for s in sc.sensors for ev in sensor_events(sc, s) if ev.measurement is not None]
    return sc, tuple(sorted(ms, key=lambda m: m.order_key))


def _run(sc, name: str, measurements, overrides=None) -> list:
    m = make_method(name, method_config(sc.tracker, name, overrides))
    out = []
    for x in measurements:
        out += m.process(x)
    return out + m.finish()


CASES = [("patent-3d", n) for n in ("SS", "LCDD", "HNDD", "RADAR2D", "ANGLE", "HNV", "PHHNV", "DDHNV")] + \
        [("thesis-fixed-c1", n) for n in ("EKF", "MEKF1", "MEKF4", "IMM")] + \
        [(str(CROSSING), n) for n in ("SS", "HNV", "PHHNV")]  # many targets: the track table's rule


@pytest.mark.parametrize("scenario,name", CASES)
def test_after_a_gap_beyond_max_gap_a_track_starts_as_a_new_one(scenario, name):
    """The scenario's stream, then the same stream again ``gap`` later: beyond
    ``max_gap_s`` (600 s) the second half's estimates are those of a new method given the
    second half alone, bit for bit (track-fusion nodes and centre included); within it the
    track is predicted across (they differ)."""
    sc, base = _scenario(scenario)
    end = base[-1].t
    for gap, restarts in ((MAX_GAP_S + 100.0, True), (MAX_GAP_S - 100.0, False)):
        later = [dataclasses.replace(m, t=m.t + end + gap, seq=m.seq + 100_000) for m in base]
        after = [e for e in _run(sc, name, [*base, *later]) if e.t > end]
        fresh = _run(sc, name, later)
        same = len(after) == len(fresh) and all(np.array_equal(a.x, b.x) and np.array_equal(a.P, b.P)
                                                for a, b in zip(after, fresh))
        assert same == restarts, (gap, len(after), len(fresh))


def test_max_gap_is_a_tracker_key():
    sc, base = _scenario("patent-3d")
    end = base[-1].t
    later = [dataclasses.replace(m, t=m.t + end + 100.0, seq=m.seq + 100_000) for m in base]
    after = [e for e in _run(sc, "SS", [*base, *later], {"max_gap_s": 50.0}) if e.t > end]
    fresh = _run(sc, "SS", later, {"max_gap_s": 50.0})
    assert all(np.array_equal(a.x, b.x) and np.array_equal(a.P, b.P) for a, b in zip(after, fresh))
    with pytest.raises(ValueError, match="max_gap_s"):
        make_method("SS", {"max_gap_s": 0.0})
    with pytest.raises(ValueError, match="max_gap_s"):
        make_method("EKF", {"max_gap_s": -1.0})
    assert gap_too_long(600.5, 600.0) and not gap_too_long(600.0, 600.0)


def test_epoch_nis_keeps_the_latest_terms_within_64_dof():
    assert NIS_MAX_DOF <= MAX_DIM  # what the wire carries
    rng = np.random.default_rng(1)
    terms = [(float(v), 1) for v in rng.chisquare(1, 100)]
    assert epoch_nis(terms[:40]) == (sum(v for v, _ in terms[:40]), 40)  # below the limit: the plain sum
    nis, dof = epoch_nis(terms)
    assert dof == 64 and nis == pytest.approx(sum(v for v, _ in terms[-64:]), rel=1e-15)
    three = [(float(v), 3) for v in rng.chisquare(3, 30)]  # a radar's 3 components per term
    nis, dof = epoch_nis(three)
    assert dof == 63 and nis == pytest.approx(sum(v for v, _ in three[-21:]), rel=1e-15)
    assert epoch_nis([]) == (None, None) and epoch_nis([(1.0, 65)]) == (None, None)
    # For a consistent filter the kept statistic is a χ² of its dof: 2,000 epochs of 200
    # unit terms average 64 within 5 standard errors.
    means = [epoch_nis([(float(v), 1) for v in rng.chisquare(1, 200)])[0] for _ in range(2000)]
    assert abs(np.mean(means) - 64.0) < 5 * np.sqrt(2 * 64 / 2000)


def test_positive_definite():
    A = np.array([[4.0, 1.0], [1.0, 3.0]])
    assert positive_definite(A)
    assert positive_definite(np.diag([1e-6, 1e12]))  # scale alone is not a defect
    assert positive_definite(np.array([[1e12, 0.99e6], [0.99e6, 1.0]]))  # correlation 0.99
    assert not positive_definite(np.array([[1e12, 1e6], [1e6, 1.0]]))  # correlation 1: singular
    assert not positive_definite(np.array([[1.0, 2.0], [2.0, 1.0]]))  # indefinite
    assert not positive_definite(np.diag([1.0, -1e-9]))
    assert not positive_definite(np.diag([1.0, 0.0]))
    assert not positive_definite(np.array([[np.nan, 0.0], [0.0, 1.0]]))
    assert not positive_definite(np.diag([1.0, np.inf]))
