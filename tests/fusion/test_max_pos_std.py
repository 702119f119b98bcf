"""``max_pos_std`` deletion (:class:`fusion.tracking.table.TrackLogic`) in the many-target
trackers: a centralised track that coasts is deleted at the first frame where its
predicted position σ (√trace P_pos) exceeds the limit — the frame the motion model's
covariance growth from its last update says, computed here independently — and lives
on without the limit; the network centre, the DF emitter tracker and an HNV node's
local tracks (``local_max_pos_std``) apply it too.

Two aircraft seen by a co-located 2D radar and angle sensor; the second falls silent
at ``T_SILENT`` while the first keeps the frames coming."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sim3d import run_method  # noqa: E402

from fusion.links import Drop  # noqa: E402
from fusion.tracking.table import CONFIRMED, DELETED, ManagementRule, TrackLogic  # noqa: E402
from fusion.methods import make_method, method_config  # noqa: E402
from fusion.motion import make_motion  # noqa: E402
from fusion.measurement.models import SphericalModel  # noqa: E402
from fusion.types import Measurement  # noqa: E402
from sensors_sim import load_scenario  # noqa: E402
from services.evaluation import merged_measurements  # noqa: E402

PERIOD, DURATION, T_SILENT = 1.0, 40.0, 15.0
SITE = np.array([0.0, 0.0, 10.0])
STD = {"range_az": np.array([0.002, 15.0]), "azel": np.array([0.002, 0.002])}
START = [np.array([9000.0, 14000.0, 3000.0, -120.0, 40.0, 0.0]), np.array([-12000.0, 10000.0, 4000.0, 150.0, 30.0, 0.0])]
Q = 0.5
TABLE = {"association": "gnn", "motion": "cv", "q": Q, "confirm_m": 2, "confirm_n": 3, "delete_misses": 1000,
         "merge_frames": 0}


def _stream() -> list[Measurement]:
    rng = np.random.default_rng(5)
    out, seq = [], 0
    for k in range(int(DURATION / PERIOD)):
        t = k * PERIOD
        for target, x0 in enumerate(START):
            if target == 1 and t >= T_SILENT:
                continue
            p = x0[:3] + t * x0[3:]
            for sensor, kind, comps in (("angle", "azel", ("az", "el")), ("radar", "range_az", ("az", "range"))):
                z = SphericalModel(comps, SITE, STD[kind], 6).h(np.r_[p, 0.0, 0.0, 0.0]) + rng.normal(0.0, STD[kind])
                z[0] %= 2 * math.pi
                seq += 1
                out.append(Measurement(t, sensor, kind, z, STD[kind], SITE, seq))
    return sorted(out, key=lambda m: m.order_key)


def _silent_track(estimates):
    """The reported estimates of the track on the aircraft that falls silent."""
    by_track: dict[str, list] = {}
    for e in estimates:
        if e.node == "centre":
            by_track.setdefault(e.track, []).append(e)
    return min(by_track.values(), key=lambda es: np.linalg.norm(es[0].x[:2] - START[1][:2]))


def _expected_last(last_update, limit: float) -> float:
    """The last frame at which a track coasting from ``last_update`` has σ ≤ ``limit``."""
    motion = make_motion("cv", Q)
    t = last_update.t
    while True:
        dt = t + PERIOD - last_update.t
        P = motion.F(dt) @ last_update.P @ motion.F(dt).T + motion.Q(dt)
        if math.sqrt(np.trace(P[:3, :3])) > limit:
            return t
        t += PERIOD


@pytest.mark.parametrize("name", ["SS", "LCDD"])
def test_centralised_tracks_are_deleted_past_max_pos_std(name):
    stream = _stream()
    free = _silent_track(run_method(make_method(name, dict(TABLE)), stream))
    last_update = [e for e in free if e.t < T_SILENT][-1]
    sigma = math.sqrt(np.trace(last_update.P[:3, :3]))
    limit = 4.0 * sigma
    assert free[-1].t == DURATION - PERIOD  # without a limit it coasts to the end
    held = _silent_track(run_method(make_method(name, {**TABLE, "max_pos_std": limit}), stream))
    assert [e.t for e in held] == [e.t for e in free if e.t <= _expected_last(last_update, limit)]
    assert held[-1].t < DURATION - 5 * PERIOD


def test_hnv_local_tracks_are_dropped_past_local_max_pos_std():
    """An HNV node deletes a local track whose σ exceeds ``local_max_pos_std`` and tells
    the centre (a ``drop`` uplink); without the limit the local track lives on."""
    stream = _stream()

    def drops(table):
        """The position σ of every local track a node deleted, as it deleted it."""
        method = make_method("HNV", table)
        sigmas = []
        for node_id in ("angle", "radar"):
            node = method._node(node_id)
            step = node.step

            def spy(alone=False, step=step, node=node):
                tracks = dict(node.tracks)  # the trackers, as the step leaves them
                out = step(alone)
                sigmas.extend(math.sqrt(np.trace(tracks[u.track].P[:3, :3])) for u in out if isinstance(u, Drop))
                return out

            node.step = spy
        run_method(method, stream)
        return sigmas

    table = {**TABLE, "local_max_pos_std": 1000.0}
    dropped = drops(table)
    assert dropped and all(sigma > 1000.0 for sigma in dropped)
    assert not drops(dict(TABLE))


def test_track_logic_deletes_past_max_pos_std():
    rule = ManagementRule(1, 1, delete_misses=100, max_pos_std=100.0)
    inside, outside = np.diag([50.0**2, 50.0**2, 70.0**2]), np.diag([60.0**2, 60.0**2, 60.0**2])  # σ 100, 103.9
    assert TrackLogic(rule).record(True, inside) == CONFIRMED
    assert TrackLogic(rule).record(True, outside) == DELETED
    assert TrackLogic(ManagementRule(1, 1)).record(True, outside * 1e6) == CONFIRMED  # no limit by default


def test_the_network_centre_deletes_past_max_pos_std():
    """The HNV centre's fused tracks, whose σ at birth exceeds a limit set below it
    (the nodes' own limit lifted), never get to be reported; without it they are."""
    stream = _stream()
    hnv = {**TABLE, "local_max_pos_std": 1e9}
    assert _centre_tracks(run_method(make_method("HNV", dict(hnv)), stream))
    assert not _centre_tracks(run_method(make_method("HNV", {**hnv, "max_pos_std": 1.0}), stream))


def test_the_emitter_tracker_deletes_past_max_pos_std():
    """As the centre's, for the DF tracker's emitters (df-multi, its first 120 s)."""
    scenario = load_scenario("df-multi")
    bearings = [m for m in merged_measurements(scenario, 0) if m.t < 120.0]
    table = {**method_config(scenario.tracker, "EKF")}
    assert _centre_tracks(run_method(make_method("EKF", dict(table)), bearings))
    assert not _centre_tracks(run_method(make_method("EKF", {**table, "max_pos_std": 1.0}), bearings))


def _centre_tracks(estimates) -> set[str]:
    return {e.track for e in estimates if e.node == "centre" and e.track is not None}
