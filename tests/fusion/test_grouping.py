"""The one time grouper (fusion.grouping): scans, frames and epochs cut by the same rule,
checked case by case, and the groups independent of when watermarks arrive."""

from __future__ import annotations

import random

import numpy as np
import pytest

from fusion.grouping import TimeGrouper
from fusion.types import Measurement


def m(t: float, sensor: str = "a", seq: int = 0) -> Measurement:
    return Measurement(t, sensor, "bearing", np.array([0.1]), np.array([0.01]), np.zeros(3), seq)


def times(groups) -> list[list[tuple[float, str]]]:
    return [[(x.t, x.sensor) for x in g] for g in groups]


def test_a_group_takes_what_lies_within_tol_of_its_first():
    g = TimeGrouper(0.5)
    assert g.push(m(1.0)) == [] and g.push(m(1.5, "b")) == []  # t − t₀ = tol joins
    assert times(g.push(m(1.5000001, "c"))) == [[(1.0, "a"), (1.5, "b")]]
    assert times(g.finish()) == [[(1.5000001, "c")]] and g.finish() == []


def test_a_watermark_at_t0_plus_tol_closes_the_group():
    """Everything up to the watermark has been sent: nothing can still join."""
    g = TimeGrouper(0.5)
    g.push(m(1.0))
    assert g.advance(1.4999) == [] and g.held_since() == 1.0
    assert times(g.advance(1.5)) == [[(1.0, "a")]] and g.held_since() is None
    z = TimeGrouper(0.0)  # tol 0 (the DF default): one epoch per timestamp, closed by its own watermark
    z.push(m(2.0))
    z.push(m(2.0, "b"))
    assert times(z.advance(2.0)) == [[(2.0, "a"), (2.0, "b")]]


def test_scans_take_one_per_sensor_and_close_when_complete():
    g = TimeGrouper(1.0, one_per_sensor=True)
    g.push(m(0.0, "a"))
    assert g.push(m(0.1, "b")) == []  # the first scan never closes on completion
    assert times(g.push(m(0.2, "a", 1))) == [[(0.0, "a"), (0.1, "b")]]  # a second from the same sensor
    assert times(g.push(m(0.3, "b", 1))) == [[(0.2, "a"), (0.3, "b")]]  # every sensor seen so far: complete
    g.push(m(1.5, "a", 2))
    assert times(g.push(m(1.6, "a", 3))) == [[(1.5, "a")]]
    frames = TimeGrouper(1.0)  # frames: any number of plots per sensor
    frames.push(m(0.0, "a"))
    assert frames.push(m(0.2, "a", 1)) == []


def test_order_is_guarded():
    g = TimeGrouper(0.1)
    g.push(m(1.0, "b"))
    with pytest.raises(ValueError, match="out of order"):
        g.push(m(1.0, "a"))
    g.advance(3.0)
    with pytest.raises(ValueError, match="late measurement.*after watermark"):
        g.push(m(2.5, "c"))
    with pytest.raises(ValueError, match="pair_tol"):
        TimeGrouper(-1.0)


@pytest.mark.parametrize("one_per_sensor", [False, True])
def test_the_groups_do_not_depend_on_when_watermarks_come(one_per_sensor):
    """The same stream with watermarks at random places (each a time already passed)
    gives the same groups as with none: only how early a group is released differs."""
    rng = random.Random(7)
    stream = sorted((round(rng.uniform(0, 20), 1), rng.choice("abc"), k) for k in range(200))
    stream = [s for i, s in enumerate(stream) if i == 0 or s[:2] != stream[i - 1][:2]]
    ms = [m(t, s, k) for t, s, k in stream]

    def run(watermarks: bool):
        g, out = TimeGrouper(0.3, one_per_sensor), []
        for i, x in enumerate(ms):
            out += g.push(x)
            if watermarks and rng.random() < 0.5 and (i + 1 == len(ms) or ms[i + 1].t > x.t):
                out += g.advance(x.t + rng.uniform(0, ms[i + 1].t - x.t if i + 1 < len(ms) else 1.0) * 0.999)
        return times(out + g.finish())

    ref = run(False)
    assert len(ref) > 30 and run(True) == ref
