"""Many targets: the centralised many-target methods (fusion.mtt, a configuration of
fusion.tracking), their reduction to the one-target method, and the track-quality metrics
(fusion.mtt_metrics)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from fusion.tracking.table import CONFIRMED
from fusion.methods import make_method, method_config
from fusion.init3d import InitPriors
from fusion.mtt import MultiTargetMethod
from fusion.tracking.initiators import Initiator
from fusion.mtt_metrics import Step, score_tracks
from fusion.types import Measurement
from sensors_sim import load_scenario, sensor_events, truth_trajectory
from services.evaluation import merged_measurements, run_method, score_tracks_run
from services.scoring import score_tracks_of, track_steps
from services.summary import tracks_summary



# Reduction to the one-target method ---------------------------------------------------
@pytest.mark.parametrize("method", ["SS", "LCDD"])
def test_one_target_without_clutter_is_exactly_the_wrapped_method(method):
    """patent-3d (one target, P_D = 1, no clutter): with M = N = 1 every estimate equals
    the method's own, bit for bit; with the default 3-of-4 the first two scans are the
    tentative track's and the rest are equal."""
    sc = load_scenario("patent-3d")
    plain = run_method(sc, method)
    for extra, skip in (({"confirm_m": 1, "confirm_n": 1}, 0), ({}, 2)):
        multi = run_method(sc, method, {"association": "gnn", **extra})
        assert len(multi) == len(plain) - skip
        for a, b in zip(plain[skip:], multi):
            assert (a.t, a.track, a.method, a.node) == (b.t, b.track, b.method, b.node) == (a.t, "T1", method, "centre")
            np.testing.assert_array_equal(a.x, b.x)
            np.testing.assert_array_equal(a.P, b.P)
            assert a.nis == b.nis


def test_association_keys_are_checked():
    with pytest.raises(ValueError, match="need 'association'"):
        make_method("SS", {"confirm_m": 2})
    with pytest.raises(ValueError, match="'association' must be one of"):
        make_method("SS", {"association": "jpda"})
    with pytest.raises(ValueError, match="confirm_m <= confirm_n"):
        make_method("SS", {"association": "gnn", "confirm_m": 5, "confirm_n": 4})
    with pytest.raises(ValueError, match="'merge_frames' must be an integer"):
        make_method("SS", {"association": "gnn", "merge_frames": 1.5})
    with pytest.raises(ValueError, match="merge_frames must be >= 0"):
        make_method("SS", {"association": "gnn", "merge_frames": -1})
    with pytest.raises(ValueError, match="'local_max_pos_std' must be > 0"):
        make_method("HNV", {"association": "gnn", "local_max_pos_std": 0.0})
    assert isinstance(make_method("SS", {"association": "gnn", "q": 0.1}), MultiTargetMethod)


# Track ids ------------------------------------------------------------------------------
def plot(t, sensor, seq, p):
    """A noise-free 3D radar plot of the point p from the origin."""
    e, n, u = p
    z = np.array([math.atan2(e, n) % (2 * math.pi), math.atan2(u, math.hypot(e, n)), math.hypot(e, n, u)])
    return Measurement(t, sensor, "az_el_range", z, np.array([1e-3, 1e-3, 10.0]), np.zeros(3), seq)


def _plots(t, p, seq, kinds=("range_az", "azel")):
    """Noise-free plots of the point p at t: a 2D radar at the origin (range, azimuth) and
    an angle sensor at (10, 0, 0) km (azimuth, elevation)."""
    out = []
    if "range_az" in kinds:
        e, n, u = p
        out.append(Measurement(t, "radar", "range_az", np.array([math.atan2(e, n) % (2 * math.pi), math.hypot(e, n, u)]),
                               np.array([1e-3, 10.0]), np.zeros(3), seq))
    if "azel" in kinds:
        e, n, u = p - np.array([10e3, 0.0, 0.0])
        out.append(Measurement(t, "angle", "azel", np.array([math.atan2(e, n) % (2 * math.pi),
                                                              math.atan2(u, math.hypot(e, n))]),
                               np.array([1e-3, 1e-3]), np.array([10e3, 0.0, 0.0]), seq))
    return out


@pytest.mark.parametrize("alone, kept", [("azel", False), ("range_az", True)])
def test_a_confirmed_track_fed_by_an_angle_sensor_alone_scores_misses(alone, kept):
    """SS, one aircraft, both sensors for 6 scans (confirmed), then for 4 scans one
    sensor alone sees it (the other reports something far away; delete_misses = 3).
    The angle sensor's plots fix only a ray: a track they alone keep alive can drift
    along it (fusion.tracking.table.scores_hit), so they score no hit and the track is deleted; a
    2D radar's plots fix the range and keep it."""
    method = make_method("SS", {"association": "gnn", "confirm_m": 3, "confirm_n": 4, "delete_misses": 3})
    v, p0 = np.array([150.0, 0.0, 0.0]), np.array([0.0, 40e3, 5e3])
    out = []
    for k in range(10):
        plots = _plots(float(k), p0 + k * v, k, ("range_az", "azel") if k < 6 else (alone,))
        if k >= 6:  # the other sensor reports something else, far away: the frame has two sensors
            other = {"azel": ("range_az",), "range_az": ("azel",)}[alone]
            plots += _plots(float(k), np.array([-30e3, 20e3, 3e3]), k, other)
        for m in sorted(plots, key=lambda m: m.order_key):
            out += method.advance(m.t - 0.5) + method.process(m)
    out += method.finish()
    assert {e.t for e in out} >= {3.0, 4.0, 5.0}  # confirmed, and held while both sensors saw it
    last = max(e.t for e in out)
    assert (last == 9.0) == kept, last
    if not kept:
        assert last == 7.0  # scans 6, 7 and 8 score no hit: deleted at the third


def test_ids_follow_confirmation_order_and_are_never_reused():
    """A appears at t = 0, B at t = 2; A vanishes after t = 5 and comes back at t = 12
    (after its track was deleted): ids T1 (A), T2 (B), then T3 for A's new track."""
    method = make_method("RADAR3D", {"association": "gnn", "motion": "cv", "q": 1.0, "confirm_m": 2,
                                     "confirm_n": 2, "delete_misses": 3})
    a0, b0 = np.array([5000.0, 8000.0, 2000.0]), np.array([-7000.0, 3000.0, 4000.0])
    va, vb = np.array([100.0, 0.0, 0.0]), np.array([0.0, -100.0, 0.0])
    out = []
    for k in range(20):
        t = float(k)
        plots = []
        if k <= 5 or k >= 12:
            plots.append(a0 + va * t)
        if k >= 2:
            plots.append(b0 + vb * t)
        for seq, p in enumerate(plots):
            out += method.process(plot(t, "r3", 100 * k + seq, p))
    out += method.finish()
    seen = {}
    for e in out:
        truth = "A" if np.linalg.norm(e.x[:3] - (a0 + va * e.t)) < 500 else "B"
        seen.setdefault(e.track, set()).add(truth)
    assert seen == {"T1": {"A"}, "T2": {"B"}, "T3": {"A"}}
    first = {tid: min(e.t for e in out if e.track == tid) for tid in seen}
    assert first == {"T1": 1.0, "T2": 3.0, "T3": 13.0}
    assert max(e.t for e in out if e.track == "T1") == 7.0  # coasts 2 frames, deleted at the 3rd miss


# Three aircraft crossing, with clutter -----------------------------------------------------



def test_three_crossing_aircraft_in_clutter_are_all_held(crossing):
    """A, B and C cross within 30 s (B passes 300 m above A's path, C through both) with
    5 + 3 false alarms per scan and P_D = 0.9. Over 60 Monte Carlo runs (seeds 3, runs
    0–59) SS with GNN had no false track; purity was ≥ 0.994, held fraction 0.86–0.97
    (mean 0.935; 2 of the 61 steps per target are the 3-of-4 confirmation delay), and
    16 breaks in 60 runs (≤ 2 per run, of ~10 000 chances): at a crossing the other
    track may take the radar plots for three frames, and a track fed by an angle sensor
    alone scores misses (fusion.tracking.table.scores_hit) and is restarted (1 break in 60 when a
    hit from any one sensor counted). Runs 0–4 have no break: exactly 3 tracks."""
    held = []
    breaks = 0
    for run in range(5):
        s = score_tracks_run(crossing, "SS", run, c=1000.0)
        assert s.n_tracks == 3 and s.false_tracks == 0, s.summary()
        assert s.purity >= 0.99, s.summary()
        assert s.held >= 0.85, s.summary()
        last = s.assignments[-1]
        assert set(last) == {"A", "B", "C"} and len(set(last.values())) == 3  # all held at the end
        held.append(s.held)
        breaks += s.breaks
    assert breaks <= 1
    assert np.mean(held) >= 0.92


# Metrics on constructed cases ----------------------------------------------------------------
def steps_from(seq):
    return [Step(float(t), truths, tracks) for t, (truths, tracks) in enumerate(seq)]


def test_metrics_closed_forms():
    """Two targets over 5 steps. Track 1 follows X throughout; track 2 follows Y for
    steps 0–1, Y is unheld at step 2, track 3 takes Y at 3–4; track 4 is 5 km from
    everything at steps 1–2. Breaks: Y at step 2 (held → unheld); re-acquisition by
    track 3 is not another break. Chances: X 4, Y 3 (steps 0→1, 1→2, 3→4). Purity: tracks
    1, 2, 3 on one target all their life (5 + 2 + 2 steps), track 4 on none (2 steps):
    9/11. One false track. GOSPA (c = 100, p = 2) at step 2: one miss and one false
    track, each c²/2: √(c²) = 100; plus step 1's false track alone: √(c²/2)."""
    X = lambda t: np.array([100.0 * t, 0.0, 0.0])  # noqa: E731
    Y = lambda t: np.array([0.0, 1000.0 + 100.0 * t, 0.0])  # noqa: E731
    far = np.array([5000.0, 5000.0, 0.0])
    off = np.array([3.0, 4.0, 0.0])  # a 5 m error
    seq = []
    for t in range(5):
        tracks = {"1": X(t) + off}
        if t <= 1:
            tracks["2"] = Y(t)
        if t >= 3:
            tracks["3"] = Y(t)
        if t in (1, 2):
            tracks["4"] = far
        seq.append(({"X": X(t), "Y": Y(t)}, tracks))
    s = score_tracks(steps_from(seq), c=100.0, p=2.0)
    assert (s.breaks, s.break_chances) == (1, 7)
    assert s.held_steps == 9 and s.truth_steps == 10
    assert s.purity == pytest.approx(9 / 11)
    assert (s.false_tracks, s.false_track_steps, s.n_tracks) == (1, 2, 4)
    np.testing.assert_allclose(s.gospa, [5.0, math.sqrt(25 + 5000), math.sqrt(25 + 5000 + 5000), 5.0, 5.0])
    assert s.n_missed == [0, 0, 1, 0, 0] and s.n_false == [0, 1, 1, 0, 0]
    assert s.assignments[2] == {"X": "1"}
    # Hold: X all 5 steps; Y from step 0, 4 of 5. Track 4's 2 steps are the longest
    # ghost; both targets are held at the last step.
    assert sorted(s.hold_fractions) == [0.8, 1.0] and s.worst_hold == 0.8
    assert s.longest_ghost == [2] and s.found_at_end == [1.0]
    # A third target never held holds 0 and is not found at the end.
    Z = np.array([0.0, -9000.0, 0.0])
    seq2 = [({**truths, "Z": Z}, tracks) for truths, tracks in seq]
    s2 = score_tracks(steps_from(seq2), c=100.0, p=2.0)
    assert sorted(s2.hold_fractions) == [0.0, 0.8, 1.0] and s2.found_at_end == [2 / 3]
    merged = type(s).merged([s, s2])
    assert merged.longest_ghost == [2, 2] and merged.worst_hold == 0.0 and merged.found_at_end == [1.0, 2 / 3]
    # A ghost's count restarts when it passes over a target: false 2 + on 1 + false 2 is 2.
    W = np.array([0.0, 0.0, 0.0])
    seq3 = [({"W": W}, {"g": W if t == 2 else far}) for t in range(5)]
    assert score_tracks(steps_from(seq3), c=100.0).longest_ghost == [2]


def test_an_id_swap_is_two_breaks_and_lowers_purity():
    """Tracks a and b swap targets at step 2 of 4: each target changes id once (2
    breaks of 6 chances); each track spends 2 of 4 steps on either target: purity 1/2."""
    P = {"X": np.array([0.0, 0.0, 0.0]), "Y": np.array([1000.0, 0.0, 0.0])}
    seq = [(P, {"a": P["X"], "b": P["Y"]})] * 2 + [(P, {"a": P["Y"], "b": P["X"]})] * 2
    s = score_tracks(steps_from(seq), c=100.0)
    assert (s.breaks, s.break_chances, s.purity, s.false_tracks) == (2, 6, 0.5, 0)
    assert s.mean_gospa == 0.0 and s.held == 1.0


@pytest.mark.slow
def test_many_targets_over_zenoh_equal_in_process(crossing, crossing_run):
    """`zfusion run` on a many-target scenario: the processes' fused tracks, scored as an
    air picture, are the in-process evaluation's, step by step (ids included: breaks and
    purity depend on them)."""
    doc, _, p, _, _ = crossing_run
    assert "gospa" in p.stdout  # the air-picture table is printed
    got = doc["methods"]["SS"]
    ref = tracks_summary([score_tracks_of(crossing, run_method(crossing, "SS"))])
    assert got["series"]["t"] == ref["series"]["t"]
    np.testing.assert_allclose(got["series"]["gospa"], ref["series"]["gospa"], rtol=0, atol=1e-9)
    for key in ("held", "breaks", "purity", "tracks", "false_tracks", "n_updates"):
        assert got[key] == ref[key], key
    assert got["rmse_pos"] is None and got["tracks"] >= 3


@pytest.mark.parametrize("merge_frames", [0, 3])
def test_a_second_track_on_a_target_is_merged_away(crossing, merge_frames):
    """SS + GNN on the crossing scenario; at t = 20 s a confirmed track is duplicated
    (a copy under a new id, as a wrong initiation would make one). The two share the
    target's plots and agree; with ``merge_frames = 3`` the copy is deleted within 3
    frames and the original keeps the target to the end; with 0 the copy lives on
    until its misses delete it (the original wins the plots: it comes first)."""
    import copy

    method = make_method("SS", {**crossing.tracker, "merge_frames": merge_frames})
    out, t_prev, copied = [], None, None
    for m in merged_measurements(crossing, 0):
        if t_prev is not None and m.t > t_prev:
            out += method.advance(t_prev)
            if copied is None and t_prev >= 20.0:
                original = method.tracks[0]
                twin = copy.deepcopy(original)
                twin.id = method.table.ids.next()
                method.table.add(twin)
                copied = (original.id, twin.id, t_prev)
        out += method.process(m)
        t_prev = m.t
    out += method.finish()
    kept, twin_id, t0 = copied
    twin_times = sorted({e.t for e in out if e.track == twin_id})
    if merge_frames:
        assert len(twin_times) <= merge_frames and all(t <= t0 + merge_frames for t in twin_times), twin_times
        s = score_tracks(track_steps(crossing, out, 0), 1000.0)
        i = s.t.index(t0)
        truth = next(k for k, v in s.assignments[i].items() if v == kept)
        assert all(a.get(truth) == kept for a in s.assignments[i:])
    else:
        assert len(twin_times) > 3, twin_times


# Initiation and sequential gating on air-picture's first frames ---------------------------
def _labelled_frames(run: int, frames: int):
    """air-picture's first ``frames`` frames of ``run``, and each plot's aircraft ('' for a
    false alarm) keyed by (sensor, seq)."""
    sc = load_scenario("air-picture")
    origin, plots = {}, []
    for sid in sc.sensors:
        for ev in sensor_events(sc, sid, run=run):
            m = ev.measurement
            if m is not None and m.t < frames - 0.5:
                origin[(m.sensor, m.seq)] = ev.target or ""
                plots.append(m)
    return sc, sorted(plots, key=lambda m: m.order_key), origin


def _run_frames(sc, plots):
    """SS with association over ``plots``; its tracks (confirmed and tentative) after them."""
    method = make_method("SS", method_config(sc.tracker, "SS"))
    for m in plots:
        method.advance(m.t - 0.5)
        method.process(m)
    method.advance(plots[-1].t + 0.5)
    return method


def _nearest_track(method, sc, run, t):
    """Per aircraft, the distance (m) from its true position at t to the nearest track."""
    X = np.array([tr.filter.x[:3] for tr in method.tracks])
    return {tid: float(np.min(np.linalg.norm(X - truth_trajectory(sc, tid, run).position(t)[:3], axis=1)))
            for tid in sc.targets}


@pytest.mark.parametrize("run", [0, 3, 4])
def test_initiation_does_not_pair_one_aircraft_with_its_neighbour(run):
    """air-picture, the first frame: every aircraft seen by an angle sensor and a radar
    starts a track on itself. A ray of one aircraft meets the range sphere of its
    neighbour (2.5 km away) inside the radar's 1° azimuth gate; taken in order of the
    pair's d² alone, such pairs started tracks 1–2 km off the aircraft, which then held
    its plots (runs 0, 3 and 4: E01, E02, N01 without a track for up to 9 s). Ranked by
    support, the pairs the other sensors confirm go first."""
    sc, plots, origin = _labelled_frames(run, 1)
    pairs = Initiator(9, InitPriors(), 0.999)
    own = {tid: [m for m in plots if origin[(m.sensor, m.seq)] == tid] for tid in sc.targets}
    seen = {tid for tid, mine in own.items()  # those a pair of their own plots can start
            if any(pairs.pair_consistency(a, r) for a in mine for r in mine if (a.kind, r.kind) == ("azel", "range_az"))}
    near = _nearest_track(_run_frames(sc, plots), sc, run, 0.0)
    assert len(seen) >= 20
    assert {tid: d for tid, d in near.items() if tid in seen and d > 300.0} == {}


def test_sequential_gating_keeps_a_neighbour_s_radar_plot_out_of_a_new_track():
    """air-picture run 0, frame 1: the tracks born at frame 0 on N10 and N11 know
    nothing of their velocity (σ 300 m/s), so each gated radar2's plots at a prediction
    spread over hundreds of metres, and against those predictions each took its
    neighbour's plot (600 m off in range), was pulled 500–650 m off, found no plot at
    frame 2 and was not confirmed. Gated after the angle sensors' updates, each takes
    its own: both confirmed at frame 2 (t = 2), within 100 m."""
    sc, plots, _ = _labelled_frames(0, 3)
    method = _run_frames(sc, plots)
    confirmed = [tr for tr in method.tracks if tr.logic.status == CONFIRMED]
    X = np.array([tr.filter.x[:3] for tr in confirmed])
    for tid in ("N10", "N11"):
        assert np.min(np.linalg.norm(X - truth_trajectory(sc, tid, 0).position(2.0)[:3], axis=1)) < 100.0
