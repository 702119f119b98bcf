"""The recursive DF methods' start-up is bounded (fusion/df/methods.py): a station alone
for hundreds of bearings, then a second one, gives the fix of its latest
``HELD_PER_STATION`` bearings and the second's first, with the dropped ones counted and
an NIS the wire carries."""

from __future__ import annotations

import math

import numpy as np
import pytest

from fusion.df.methods import HELD_PER_STATION, make
from fusion.types import Measurement
from schemas import encode_estimate

EMITTER = np.array([5000.0, 8000.0])
SIGMA = math.radians(1.0)
SITES = {"df1": (0.0, 0.0), "df2": (12000.0, 0.0), "df3": (0.0, 14000.0)}


def bearing(sensor: str, t: float, seq: int, rng) -> Measurement:
    site = np.array([*SITES[sensor], 0.0])
    d = EMITTER - site[:2]
    az = (math.atan2(d[0], d[1]) + rng.normal(0.0, SIGMA)) % (2 * math.pi)
    return Measurement(t=t, sensor=sensor, kind="bearing", z=np.array([az]), std=np.array([SIGMA]), site=site,
                       seq=seq)


def run(name: str, measurements, config=None):
    m = make(name, config)
    out = []
    for x in measurements:
        out += m.process(x)
    return out + m.finish(), m


@pytest.mark.parametrize("name", ["EKF", "MEKF2", "IMM"])
@pytest.mark.parametrize("alone", [41, 81, 300])
def test_a_station_alone_then_a_second(name, alone):
    rng = np.random.default_rng(alone)
    first = [bearing("df1", float(k), k, rng) for k in range(alone)]
    rest = [bearing(s, float(alone + k), alone + k, rng) for k in range(5) for s in ("df1", "df2")]
    out, m = run(name, [*first, *rest])
    # The fix is the one from df1's latest 16 bearings and df2's: equal to a run that
    # never saw the older ones.
    held = first[-HELD_PER_STATION:]
    ref, _ = run(name, [*held, *rest])
    assert len(out) == len(ref) == 5
    for a, b in zip(out, ref):
        assert np.array_equal(a.x, b.x) and np.array_equal(a.P, b.P) and a.nis == b.nis
    dropped = alone + 1 - HELD_PER_STATION  # df1's bearing of the pair's epoch is held first
    assert m.n_dropped == dropped and out[0].extra["n_dropped"] == dropped
    assert name == "IMM" or out[0].nis_dof == HELD_PER_STATION - 1  # the held bearings but the pair's
    for e in out:
        encode_estimate(e, "fuser", 1)
        assert np.linalg.norm(e.x[:2] - EMITTER) < 2000.0


def test_held_bearings_older_than_max_gap_are_dropped():
    rng = np.random.default_rng(7)
    first = [bearing("df1", 100.0 * k, k, rng) for k in range(10)]  # df1 every 100 s, for 900 s
    second = bearing("df2", 1000.0, 10, rng)
    out, m = run("EKF", [*first, second])
    ref, _ = run("EKF", [*[b for b in first if 1000.0 - b.t <= 600.0], second])
    assert m.n_dropped == 4 and np.array_equal(out[0].x, ref[0].x) and np.array_equal(out[0].P, ref[0].P)


def test_an_epoch_of_more_than_64_bearings():
    """100 stations in one epoch (one time stamp): the filter takes them all, the NIS
    the latest 64 (a χ² of 64 dof)."""
    rng = np.random.default_rng(3)
    angles = np.linspace(0.0, 2 * math.pi, 100, endpoint=False)
    sites = {f"s{k:03d}": (EMITTER[0] + 20000.0 * math.sin(a), EMITTER[1] + 20000.0 * math.cos(a))
             for k, a in enumerate(angles)}
    SITES.update(sites)
    try:
        epochs = [[bearing(s, float(t), t * 100 + k, rng) for k, s in enumerate(sites)] for t in range(3)]
        out, _ = run("EKF", [m for e in epochs for m in e])
    finally:
        for s in sites:
            del SITES[s]
    assert [e.nis_dof for e in out] == [64, 64, 64] and [e.extra["n_bearings"] for e in out] == [100, 200, 300]
    for e in out:
        encode_estimate(e, "fuser", 1)


def test_the_robust_window_is_bounded_too():
    rng = np.random.default_rng(5)
    first = [bearing("df1", float(k), k, rng) for k in range(200)]  # the window stays open: one site only
    rest = [bearing(s, 200.0 + k, 200 + k, rng) for k in range(5) for s in ("df1", "df2")]
    out, m = run("EKF", [*first, *rest], {"init": "robust"})
    ref, _ = run("EKF", [*first[-HELD_PER_STATION:], *rest], {"init": "robust"})
    assert m.n_dropped == 200 + 1 - HELD_PER_STATION
    assert len(out) == len(ref) and all(np.array_equal(a.x, b.x) for a, b in zip(out, ref))
