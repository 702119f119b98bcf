"""Identity on tracks: the many-target tracker keeps on each track the identity of the
position reports assigned to it (the latest; a change counted), and an identity never
decides an association: two aircraft 20 km apart sending one address (a reused or
spoofed one) keep two tracks. Both trackers: frame by frame (air-picture's [tracker])
and over sweeps (region-400's)."""

from __future__ import annotations

import numpy as np
import pytest

from fusion.methods import make_method, method_config
from fusion.types import Identity, Measurement
from sensors_sim import load_scenario
from services.evaluation import run_method

SPOOFED = Identity("4ca7b1", "RYR1")
BEFORE, AFTER = Identity("39b002", "AFR12"), Identity("39b003", "AFR12")  # the third aircraft's, before and after 30 s
STD = np.array([30.0, 30.0, 15.0])


def reports(seconds: int = 60, seed: int = 0) -> tuple[list[Measurement], dict]:
    """Position reports of three aircraft flying east at 200 m/s, 20 km apart, from two
    receivers in turn (one a second); the first two send one address."""
    rng = np.random.default_rng(seed)
    start = {"a": np.array([0.0, 30e3, 9e3]), "b": np.array([20e3, 30e3, 9e3]), "c": np.array([0.0, 10e3, 6e3])}
    out, seq = [], {}
    for k in range(seconds):
        sensor = ("adsb1", "adsb2")[k % 2]
        for name, p0 in start.items():
            identity = SPOOFED if name in "ab" else (BEFORE if k < 30 else AFTER)
            z = p0 + np.array([200.0 * k, 0.0, 0.0]) + rng.normal(0.0, STD)
            out.append(Measurement(t=float(k), sensor=sensor, kind="position", z=z, std=STD, site=np.zeros(3),
                                   seq=seq.setdefault(sensor, 0), identity=identity))
            seq[sensor] += 1
    return out, start


@pytest.mark.parametrize("scenario", ["air-picture", "region-400"])
def test_tracks_carry_the_reports_identity_and_one_address_never_merges_two_aircraft(scenario):
    plots, start = reports()
    estimates = run_method(load_scenario(scenario), "SS", None, measurements=plots)
    last_t = max(e.t for e in estimates)
    final = {e.track: e for e in estimates if e.t == last_t}
    truth = {name: p0 + np.array([200.0 * last_t, 0.0, 0.0]) for name, p0 in start.items()}
    on = {name: [k for k, e in final.items() if np.linalg.norm(e.x[:3] - p) < 300.0] for name, p in truth.items()}
    assert all(len(tracks) == 1 for tracks in on.values()), on  # one track each: a and b not merged
    assert on["a"] != on["b"] and len(final) == 3
    assert final[on["a"][0]].identity == final[on["b"][0]].identity == SPOOFED
    assert final[on["c"][0]].identity == AFTER
    before = [e for e in estimates if e.track == on["c"][0] and e.t < 30]
    assert before and all(e.identity == BEFORE for e in before)


def test_a_change_of_identity_is_counted_once():
    sc = load_scenario("air-picture")
    method = make_method("SS", method_config(sc.tracker, "SS", None))
    plots, _ = reports()
    t_prev = None
    for m in plots:
        if t_prev is not None and m.t > t_prev:
            method.advance(t_prev)
        method.process(m)
        t_prev = m.t
    method.finish()
    changes = {tr.identity: tr.identity_changes for tr in method.tracks if tr.confirmed}
    assert changes == {SPOOFED: 0, AFTER: 1}
