"""The many-target tracker on rotating radars (fusion/tracking/sweep.py): management in
time, the screen before gating, gating at each plot's own time, and a rotating scenario
tracked end to end where the frame-by-frame tracker confirms nothing."""

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest
from scipy.stats import multivariate_normal

from fusion.ekf import TrackEKF
from fusion.measurement.kinds import model_of
from fusion.motion import ConstantAcceleration, ConstantVelocity
from fusion.tracking.hypotheses import gate_threshold, mahalanobis2
from fusion.tracking import sweep
from fusion.methods import make_method, method_config
from fusion.tracking.sweep import REVISIT_SLACK_S, Spread, SweepLogic, near, pair_d2, position_row
from fusion.tracking.table import CONFIRMED, DELETED, TENTATIVE, ManagementRule, Track
from fusion.types import Estimate, Measurement
from sensors_sim import load_scenario
from services.evaluation import run_method
from services.scoring import score_tracks_of, truth_function

ROTATING = Path(__file__).parents[1] / "data" / "rotating.toml"
RULE = ManagementRule(confirm_m=3, confirm_n=4, delete_misses=3, max_pos_std=2000.0)


def test_a_tentative_track_lives_one_revisit_from_its_birth_a_confirmed_one_k_without_a_hit():
    """Born at 0 with revisit 4 s: confirmed at its third hit (birth counts) once two
    sensors have seen it, one measuring elevation, and one of them has seen it twice
    (false plots do not repeat); a tentative track dies once 4 s (and
    the slack of a beam's crossing) pass after its birth, however many hits it took (a
    track left waiting gathers false plots), a confirmed one once 3 x 4 = 12 s pass
    without a hit."""
    flat = SweepLogic(RULE, 4.0, 0.0, frozenset({"a"}), elevation=False)
    for t in (1.0, 2.0, 3.0):
        assert flat.record(True, None, t, {"b"}) == TENTATIVE  # two 2D radars: no height
    assert flat.record(True, None, 3.5, {"c"}, elevation=True) == CONFIRMED
    logic = SweepLogic(RULE, 4.0, 0.0, frozenset({"a"}))
    assert logic.record(False, None, 1.9) == TENTATIVE
    assert logic.record(True, None, 1.95, {"a"}) == TENTATIVE and logic.hits == 2
    assert logic.record(True, None, 3.0, {"a"}) == TENTATIVE and logic.hits == 3  # one sensor: clutter's signature
    assert logic.record(True, None, 3.5, {"b"}) == CONFIRMED
    assert logic.record(False, None, 15.5) == CONFIRMED  # 12 s after the last hit: not more
    assert logic.record(False, None, 15.51) == DELETED
    late = 4.0 + REVISIT_SLACK_S
    slow = SweepLogic(RULE, 4.0, 0.0, frozenset({"a"}))
    assert slow.record(True, None, 3.9, {"b"}) == TENTATIVE
    assert slow.record(True, None, late + 0.01, {"c"}) == DELETED  # its third hit came too late
    young = SweepLogic(RULE, 4.0, 10.0, frozenset({"a", "b"}))
    assert young.record(False, None, 10.0 + late) == TENTATIVE
    assert young.record(False, None, 10.0 + late + 0.001) == DELETED
    three = SweepLogic(RULE, 4.0, 0.0, frozenset({"a"}))
    assert three.record(True, None, 1.0, {"b"}) == TENTATIVE
    assert three.record(True, None, 2.0, {"c"}) == TENTATIVE and three.hits == 3  # three sensors once each
    assert three.record(True, None, 3.0, {"b"}) == CONFIRMED  # b's second look
    just = SweepLogic(RULE, 4.0, 0.0, frozenset({"a"}))
    assert just.record(True, None, 2.0, {"b"}) == TENTATIVE
    assert just.record(True, None, late, {"a"}) == CONFIRMED  # a's next turn crossed it a little late
    wide = SweepLogic(RULE, 4.0, 0.0, frozenset({"a"}))
    assert wide.record(True, np.eye(3) * 2000.0**2, 1.0) == DELETED  # σ = 2000 √3 > max_pos_std


def _track(rng, t0, motion=None, correlated=False):
    motion = motion or ConstantAcceleration(q=0.5)
    x = np.zeros(9)
    x[:3] = rng.uniform([-60e3, -60e3, 1e3], [60e3, 60e3, 12e3])
    x[3:5] = rng.normal(0.0, 150.0, 2)
    x[6:8] = rng.normal(0.0, 3.0, 2)
    sd = rng.choice([30.0, 300.0, 3000.0])
    P = np.diag(np.r_[[sd**2] * 3, [(sd / 3) ** 2] * 3, [4.0] * 3])
    if correlated:  # position with velocity and acceleration (any covariance: not what the screen assumes)
        A = rng.normal(0.0, 0.3, (9, 9))
        P = (np.eye(9) + A) @ P @ (np.eye(9) + A).T
    n_x = motion.n_x
    f = TrackEKF(motion, x[:n_x], P[:n_x, :n_x], t0)
    return Track(f, Estimate(t0, x[:n_x], P[:n_x, :n_x], "SS", "centre"))


def _plots(rng, kind, tracks, site, t0, n, made):
    """``n`` plots of one sensor at ``site`` over 0.3 s from ``t0``, the first ``made`` of
    them at the predicted positions of the first tracks, the others anywhere."""
    a = math.radians(0.2)
    std = {"range_az": np.array([a, 100.0]), "az_el_range": np.array([a, a, 100.0]), "azel": np.radians([0.05, 0.05])}[kind]
    plots = []
    for j in range(n):
        t = t0 + 0.3 * j / n
        src = tracks[j] if j < made else None
        p = src.filter.predicted(t)[0][:3] if src else rng.uniform([-80e3, -80e3, 0], [80e3, 80e3, 15e3])
        d = p - site
        z = {"range_az": [math.atan2(d[0], d[1]) % (2 * math.pi), np.linalg.norm(d)],
             "az_el_range": [math.atan2(d[0], d[1]) % (2 * math.pi), math.atan2(d[2], math.hypot(d[0], d[1])),
                             np.linalg.norm(d)],
             "azel": [math.atan2(d[0], d[1]) % (2 * math.pi), math.atan2(d[2], math.hypot(d[0], d[1]))]}[kind]
        z = np.array(z) + rng.normal(0.0, std)
        plots.append(Measurement(t, "s1", kind, z, std, site, seq=j))
    return plots


@pytest.mark.parametrize("kind", ["range_az", "az_el_range", "azel"])
def test_the_screen_keeps_every_pair_in_the_gate(kind):
    """Random tracks (σ 30 m to 3 km) and plots of one sensor in a 0.3 s sector, some
    made by the tracks: every pair with ``d²`` (at the plot's time) inside twice the
    tracker's 3-dof gate (``P_G = 0.999``: 16.3, so 32.6 < 6²) is kept, and the screen
    drops most of the others."""
    rng = np.random.default_rng(7)
    site = np.array([5e3, -3e3, 0.0])
    tracks = [_track(rng, 10.0 - rng.uniform(0, 5)) for _ in range(80)]
    plots = _plots(rng, kind, tracks, site, 10.0, 60, 30)
    keep = near(tracks, plots[0].t, plots)
    model = model_of(plots[0], 9)
    wide = 2 * gate_threshold(3, 0.999)
    inside = 0
    for r, tr in enumerate(tracks):
        for j, m in enumerate(plots):
            d2 = mahalanobis2(model, *tr.filter.predicted(m.t), m.z)[0]
            if d2 <= wide:
                inside += 1
                assert keep[r, j], (r, j, d2)
    assert inside >= 30 and keep.mean() < 0.5


@pytest.mark.parametrize("kind", ["range_az", "az_el_range", "azel"])
@pytest.mark.parametrize("north", [False, True])
def test_the_azimuth_index_keeps_the_pairs_all_against_all_keeps(kind, north, monkeypatch):
    """The screen's pairs found through the plots' sorted azimuths are those it keeps
    trying every track against every plot, also for plots on both sides of north (the
    wrap of azimuth), tracks wider than the whole turn and a track over the site."""
    rng = np.random.default_rng(5)
    site = np.array([5e3, -3e3, 0.0])
    tracks = [_track(rng, 10.0 - rng.uniform(0, 5)) for _ in range(150)]
    if north:  # every track and plot within 20 km of the line north of the site
        for tr in tracks:
            tr.filter.x = tr.filter.x.copy()
            tr.filter.x[0] = site[0] + rng.uniform(-20e3, 20e3)
            tr.filter.x[1] = site[1] + abs(tr.filter.x[1])
    tracks[1].filter.P = np.diag([3e5**2] * 3 + [100.0**2] * 3 + [4.0] * 3)  # σ 300 km: the whole turn
    over = tracks[2].filter
    over.x = over.x.copy()
    over.x[:2] = site[:2]
    over.x[3:] = 0.0
    plots = _plots(rng, kind, tracks, site, 10.0, 60, 40)
    if north:
        assert any(p.z[0] < 0.3 for p in plots) and any(p.z[0] > 2 * math.pi - 0.3 for p in plots)
    keep = near(tracks, plots[0].t, plots)
    monkeypatch.setattr(sweep, "_by_azimuth", lambda az, w, Z: tuple(a.ravel() for a in np.indices((len(az), len(Z)))))
    every = near(tracks, plots[0].t, plots)
    np.testing.assert_array_equal(keep, every)
    assert keep[:, :40].diagonal().all() and keep[1].all() and keep.mean() < 0.5


@pytest.mark.parametrize("motion", [ConstantAcceleration(q=0.5), ConstantVelocity(q=2.0),
                                    ConstantAcceleration(q=0.3, noise="discrete"), ConstantVelocity(q=1.0, noise="discrete")],
                         ids=repr)
def test_the_closed_form_prediction_row_is_the_motion_models(motion):
    """:func:`position_row`'s ``f`` and ``q₀₀`` for many intervals at once are the first
    row of the model's ``F₁(dt)`` and ``Q₁(dt)[0, 0]``, interval by interval."""
    dt = np.r_[0.0, np.random.default_rng(3).uniform(0.0, 15.0, 40)]
    f, q00 = position_row(motion, dt)
    for i, d in enumerate(dt):
        np.testing.assert_allclose(f[i], motion.F_axis(d)[0], rtol=1e-14, atol=0)
        np.testing.assert_allclose(q00[i], motion.Q_axis(d)[0, 0], rtol=1e-13, atol=0)


@pytest.mark.parametrize("motion", [ConstantAcceleration(q=0.5), ConstantVelocity(q=2.0, noise="discrete"),
                                    ConstantAcceleration(q=0.5, q_up=0.02)], ids=repr)
@pytest.mark.parametrize("kind", ["range_az", "az_el_range", "azel"])
def test_the_stacked_costs_are_the_per_pair_ones(kind, motion):
    """Random correlated tracks (σ 30 m to 3 km, 0 to 5 s old) against plots of one sensor,
    some of them the tracks': the ``d²`` of every pair in one stack
    (:func:`pair_d2`) is each track predicted to its plot's time by its filter and
    scored by :func:`mahalanobis2`, pair by pair, to 1e-10; a track over the site (its
    azimuth undefined) costs ``inf`` and leaves the other pairs as they were."""
    rng = np.random.default_rng(11)
    site = np.array([5e3, -3e3, 0.0])
    tracks = [_track(rng, 10.0 - rng.uniform(0, 5), motion, correlated=True) for _ in range(60)]
    tracks[0].filter.t = 10.0  # a pair at dt = 0 (the plot at the filter's time)
    over = tracks[-1].filter
    over.x = over.x.copy()
    over.x[:2] = site[:2]
    over.x[3:] = 0.0  # over the site until the plots' time
    plots = _plots(rng, kind, tracks, site, 10.0, 40, 20)
    model = model_of(plots[0], motion.n_x)
    spread = Spread.of(tracks)
    assert spread.linear.all()
    rows, cols = np.meshgrid(np.arange(len(tracks)), np.arange(len(plots)), indexing="ij")
    rows, cols = rows.ravel(), cols.ravel()
    d2 = pair_d2(tracks, spread, rows, plots, cols, model)
    ref = np.array([mahalanobis2(model, *tracks[r].filter.predicted(plots[c].t), plots[c].z)[0]
                    for r, c in zip(rows, cols)])
    assert np.isinf(ref[rows == len(tracks) - 1]).all()
    finite = np.isfinite(ref)
    np.testing.assert_array_equal(np.isfinite(d2), finite)
    np.testing.assert_allclose(d2[finite], ref[finite], rtol=1e-10, atol=0)
    assert (d2 < gate_threshold(model.n_z, 0.999)).sum() >= 20  # the tracks' own plots
    clean = rows != len(tracks) - 1  # without the track over the site: all in the stack
    np.testing.assert_allclose(pair_d2(tracks, spread, rows[clean], plots, cols[clean], model), ref[clean],
                               rtol=1e-10, atol=0)


def _method(scenario, **keys):
    return dataclasses.replace(scenario, tracker={**scenario.tracker, "association": "gnn", **keys})


def test_a_rotating_scenario_with_clutter_is_tracked_sweep_by_sweep():
    """tests/data/rotating.toml (one aircraft, two rotating radars, an angle sensor) with
    20 false plots a turn on each radar: frame by frame (each plot its own frame: any
    one clutter plot scores a hit or a miss for every track) the aircraft is held at
    under a tenth of the steps; in sweeps of 0.25 s one track holds it from its third
    look on (held after initiation >= 0.9), no false track, no break, within 300 m of
    it at every estimate."""
    sc = load_scenario(str(ROTATING))
    sc = dataclasses.replace(sc, sensors={i: dataclasses.replace(s, clutter_rate=20.0) if i != "angle" else s
                                          for i, s in sc.sensors.items()})
    framed = _method(sc)
    assert score_tracks_of(framed, run_method(framed, "SS")).held < 0.1
    swept = _method(sc, revisit_s=6.0, pair_tol=0.25)
    out = run_method(swept, "SS")
    assert {e.track for e in out} == {"T1"}
    score = score_tracks_of(swept, out)
    assert score.held_after_init >= 0.9 and score.false_tracks == 0 and score.breaks == 0, score
    truth = truth_function(sc)
    err = [np.linalg.norm(e.x[:3] - truth(0, "T1", e.t)[:3]) for e in out]
    assert max(err) < 300.0, max(err)


def test_a_lone_2d_radar_plot_starts_no_track_a_3d_radar_or_angle_plot_does():
    """A frame's lone 2D radar plot (its height open by kilometres) leaves the table
    empty; a lone 3D radar plot, or a lone angle plot, starts one tentative track; a
    2D radar plot paired with an angle plot on the same aircraft starts one track from
    both."""
    sc = load_scenario(str(ROTATING))
    method = make_method("SS", method_config(_method(sc, revisit_s=6.0, pair_tol=0.25).tracker, "SS"))
    tracker = method.tracker
    aircraft = np.array([20000.0, 5000.0, 4000.0])

    def plot(kind, site, t, seq):
        d = aircraft - np.asarray(site, float)
        az, el, r = math.atan2(d[0], d[1]) % (2 * math.pi), math.atan2(d[2], math.hypot(d[0], d[1])), np.linalg.norm(d)
        z, std = {"range_az": ([az, r], [math.radians(1.0), 20.0]),
                  "az_el_range": ([az, el, r], [math.radians(0.3), math.radians(0.3), 100.0]),
                  "azel": ([az, el], [math.radians(0.05)] * 2)}[kind]
        return Measurement(t, kind, kind, np.array(z), np.array(std), tuple(site), seq=seq)

    assert tracker.frame([plot("range_az", (0.0, 0.0, 0.0), 1.0, 0)]) == [] and not tracker.table.tracks
    tracker.frame([plot("az_el_range", (30000.0, 0.0, 0.0), 2.0, 1)])
    assert len(tracker.table.tracks) == 1
    tracker.table.tracks.clear()
    tracker.frame([plot("azel", (15000.0, -5000.0, 0.0), 3.0, 2)])
    assert len(tracker.table.tracks) == 1
    tracker.table.tracks.clear()
    pair = [plot("range_az", (0.0, 0.0, 0.0), 4.0, 3), plot("azel", (15000.0, -5000.0, 0.0), 4.1, 4)]
    tracker.frame(pair)
    assert len(tracker.table.tracks) == 1
    assert tracker.table.tracks[0].logic.sensors == {"range_az", "azel"}


def test_the_track_score_is_the_sum_of_its_plots_log_likelihood_ratios_confirmed_at_wald_threshold():
    """With a score, a track's llr is its birth's plus each kept hit's (a miss adds
    nothing), and it is confirmed at the first hit that takes the sum to ln(1/α), once a
    plot measuring elevation has hit it and two sensors have (one angle sensor's plots do
    not fix a range) and a plot measuring range has, besides the one it started from (a
    ray's pairing with a range sphere is a coincidence in one dimension that the angle
    sensor's next plots on the ray do not test); a plot's term is ln(P_D N(ν; 0, S) / λ)."""
    threshold = math.log(1.0 / sweep.FALSE_CONFIRM_PROB)
    assert sweep.confirm_threshold() == pytest.approx(threshold)
    terms = [0.25 * threshold, 0.5 * threshold, -0.1 * threshold, 0.4 * threshold]
    logic = SweepLogic(RULE, 4.0, 0.0, frozenset({"a", "b"}), llr=0.1 * threshold, ranged=True)
    total = 0.1 * threshold
    for k, (t, term) in enumerate(zip((0.5, 1.0, 1.5, 2.0), terms)):
        assert logic.record(False, None, t - 0.1, score=99.0) == TENTATIVE  # a miss: not counted
        status = logic.record(True, None, t, {"a"}, elevation=True, score=term)
        total += term
        assert logic.llr == pytest.approx(total)
        assert status == (CONFIRMED if k == 3 else TENTATIVE)  # 0.85, 0.75 below; 1.15 above
    flat = SweepLogic(RULE, 4.0, 0.0, frozenset({"a"}), elevation=False, llr=0.0, ranged=True)
    assert flat.record(True, None, 1.0, {"b"}, score=2 * threshold) == TENTATIVE  # no height yet
    assert flat.record(True, None, 2.0, {"c"}, elevation=True, score=0.0) == CONFIRMED
    alone = SweepLogic(RULE, 4.0, 0.0, frozenset({"a"}), llr=0.0, ranged=True)
    assert alone.record(True, None, 1.0, {"a"}, elevation=True, score=2 * threshold) == TENTATIVE
    assert alone.record(True, None, 2.0, {"b"}, score=0.0) == CONFIRMED
    ray = SweepLogic(RULE, 4.0, 0.0, frozenset({"radar", "eo"}), llr=0.0)  # a 2D radar plot and an angle plot paired
    assert ray.record(True, None, 1.0, {"eo"}, elevation=True, score=2 * threshold) == TENTATIVE  # on the same ray
    assert ray.record(True, None, 2.0, {"eo"}, elevation=True, score=2 * threshold) == TENTATIVE
    assert ray.record(True, None, 3.0, {"radar"}, score=0.0, ranged=True) == CONFIRMED  # its range seen again
    nu, S, lam = np.array([0.01, -30.0]), np.array([[1e-4, 0.1], [0.1, 900.0]]), 1e-5
    log_lik = multivariate_normal(np.zeros(2), S).logpdf(nu)
    assert sweep.plot_score(log_lik, math.log(lam)) == pytest.approx(
        math.log(sweep.P_DETECT * math.exp(log_lik) / lam))


def test_the_clutter_density_is_the_left_plots_over_the_swept_measurement_volume():
    """A radar turning at ω = 2π/8 s: over T seconds its n plots no track took, uniform in
    range up to R, give λ = n / (T ω R) per rad·m; a staring angle sensor's, n over its
    scans, a turn of azimuth and its elevation span each."""
    rng = np.random.default_rng(3)
    omega, R, clutter = 2 * math.pi / 8.0, 90e3, sweep.ClutterDensity()
    n = 0
    for frame in range(160):  # 40 s in frames of 0.25 s
        t0 = frame * 0.25
        ts = np.sort(rng.uniform(t0, t0 + 0.25, 6))
        scan = [Measurement(t, "r", "range_az", np.array([(omega * t) % (2 * math.pi), r]), np.array([0.003, 100.0]),
                            np.zeros(3)) for t, r in zip(ts, rng.uniform(0.0, R, 6))]
        scan[-1] = dataclasses.replace(scan[-1], z=np.array([scan[-1].z[0], R]))  # the farthest plot at R
        clutter.see(scan, scan[:4])
        n += 4
    seen = clutter.seen["r"]
    expected = n / ((seen.t1 - seen.t0) * omega * R)
    assert 39.5 < seen.t1 - seen.t0 <= 40.0
    assert math.exp(clutter.log_density(scan[0])) == pytest.approx(expected, rel=1e-9)
    staring = sweep.ClutterDensity()
    for k in range(10):
        scan = [Measurement(float(k), "eo", "azel", np.array([a % (2 * math.pi), e]), np.array([1e-3, 1e-3]), np.zeros(3))
                for a, e in ((0.1, 0.05), (2.0, 0.45), (-1.0, 0.25))]
        staring.see(scan, scan[:2])
    assert math.exp(staring.log_density(scan[0])) == pytest.approx(20 / (10 * 2 * math.pi * 0.4))


def test_the_false_plot_density_counts_no_plot_in_a_gate_nor_one_that_started_a_confirmed_track(monkeypatch):
    """The false-plot density's count (module docstring, 6.): a plot no track took but
    inside a track's gate (a target's, which a neighbour's track took) is not counted; a
    plot counted when it started a track is uncounted when that track is confirmed (it
    was a target's); a plot far from every track is counted."""
    sc = load_scenario(str(ROTATING))
    tracker = make_method("SS", method_config(_method(sc, revisit_s=6.0, pair_tol=0.25).tracker, "SS")).tracker
    monkeypatch.setattr(sweep, "confirm_threshold", lambda: -math.inf)  # confirmed once two sensors, one with height
    aircraft = np.array([20000.0, 5000.0, 4000.0])

    def plot(sensor, site, t, seq, off=(0.0, 0.0, 0.0)):
        d = aircraft + np.asarray(off) - np.asarray(site, float)
        z = [math.atan2(d[0], d[1]) % (2 * math.pi), math.atan2(d[2], math.hypot(d[0], d[1])), np.linalg.norm(d)]
        return Measurement(t, sensor, "az_el_range", np.array(z), np.array([math.radians(0.3), math.radians(0.3), 100.0]),
                           tuple(site), seq=seq)

    a, b = (30000.0, 0.0, 0.0), (0.0, -20000.0, 0.0)
    tracker.frame([plot("a", a, 1.0, 0)])
    assert len(tracker.table.tracks) == 1 and not tracker.table.tracks[0].confirmed
    assert tracker.clutter.seen["a"].left == 1  # far from every track when it came
    tracker.frame([plot("b", b, 1.5, 1), plot("b", b, 1.5, 2, off=(150.0, 0.0, 0.0)),
                   plot("b", b, 1.5, 3, off=(-60000.0, 10000.0, 0.0))])
    assert tracker.table.tracks[0].confirmed
    assert tracker.clutter.seen["b"].left == 1  # the far plot: not the one in the track's gate
    assert tracker.clutter.seen["a"].left == 0  # it started the track now confirmed


def test_a_radar_that_never_crosses_an_aircraft_in_an_angle_sensors_sweep_pairs_across_sweeps():
    """An aircraft flying away from a 2D radar turning in 10 s, crossed at 0.5 s past
    every look of an angle sensor (3 s), in frames each with another radar's plot (so a
    lone angle plot waits for a partner, as in a dense picture): within sweeps of 0.25 s
    its plots never pair and no track starts in 60 s; with ``pair_window_s`` = 1.5 the
    radar plot pairs with the angle plot of 0.5 s before, the track starts then and is
    confirmed at the radar's next look, within 300 m of the aircraft from there on. The
    kept plots are those of the last 1.5 s."""
    sc = load_scenario(str(ROTATING))
    vel = 150.0 * np.array([0.6, 0.8, 0.0])
    start = np.array([12e3, 16e3, 4e3])
    radar, eo, other = np.zeros(3), np.array([10e3, 5e3, 0.0]), np.array([-60e3, 0.0, 0.0])

    def plot(kind, sensor, site, t, seq, p=None):
        d = (start + vel * t if p is None else p) - site
        az, r = math.atan2(d[0], d[1]) % (2 * math.pi), float(np.linalg.norm(d))
        z, std = {"range_az": ([az, r], [math.radians(0.2), 60.0]),
                  "azel": ([az, math.asin(d[2] / r)], [math.radians(0.05)] * 2)}[kind]
        return Measurement(t, sensor, kind, np.array(z), np.array(std), tuple(site), seq=seq)

    frames = []
    for k in range(20):  # the angle sensor's looks at 3k s, the radar's at 0.5 + 10j s
        t = 3.0 * k
        far = plot("range_az", "other", other, t + 0.1, k, p=np.array([-90e3, 40e3, 8e3]))
        frames.append([plot("azel", "eo", eo, t, k), far])
        if k % 10 in (0, 3, 6):
            frames.append([plot("range_az", "radar", radar, 10.0 * ((k + 1) // 3) + 0.5, k)])
    frames.sort(key=lambda f: f[0].t)
    assert not any({m.kind for m in f} == {"azel", "range_az"} and "radar" in {m.sensor for m in f} for f in frames)

    def run(window):
        method = make_method("SS", method_config(_method(sc, revisit_s=10.0, pair_tol=0.25,
                                                         pair_window_s=window).tracker, "SS"))
        out = [(tr, tr.last) for f in frames for tr in method.tracker.frame(f)]  # each track's estimate then
        return method.tracker, out

    tracker, out = run(0.0)
    assert out == [] and not [tr for tr in tracker.table.tracks if "radar" in tr.logic.sensors]
    tracker, out = run(1.5)
    ours = [tr for tr in tracker.table.tracks if tr.logic.sensors == {"radar", "eo"}]
    assert len(ours) == 1 and ours[0].confirmed and ours[0].logic.born == 0.0
    assert out and all(tr is ours[0] for tr, _ in out)
    reported = [e for _, e in out]
    assert reported[0].t == pytest.approx(10.5)  # confirmed at the radar's next look
    err = [np.linalg.norm(e.x[:3] - (start + vel * e.t)) for e in reported]
    assert max(err) < 300.0, err
    assert tracker.earlier and all(frames[-1][-1].t - m.t <= 1.5 for m in tracker.earlier)


def test_a_position_reporter_heard_twice_confirms_a_track_alone():
    """A track that two looks of one position reporter (ADS-B: the aircraft's own
    report) have hit is confirmed on its score without a second sensor; two looks of one
    radar are not (clutter's signature)."""
    threshold = math.log(1.0 / sweep.FALSE_CONFIRM_PROB)
    heard = SweepLogic(RULE, 10.0, 0.0, frozenset({"adsb"}), llr=0.0, reporters=frozenset({"adsb"}))
    assert heard.record(True, None, 5.0, {"adsb"}, elevation=True, score=2 * threshold, ranged=True,
                        reporters={"adsb"}) == CONFIRMED
    radar = SweepLogic(RULE, 10.0, 0.0, frozenset({"r3d"}), llr=0.0)
    assert radar.record(True, None, 5.0, {"r3d"}, elevation=True, score=2 * threshold, ranged=True) == TENTATIVE
    two = SweepLogic(RULE, 10.0, 0.0, frozenset({"adsb"}), llr=0.0, reporters=frozenset({"adsb"}))
    assert two.record(True, None, 5.0, {"adsb2"}, elevation=True, score=2 * threshold, ranged=True,
                      reporters={"adsb2"}) == CONFIRMED  # two sensors, as before


@pytest.mark.parametrize("keys, says", [
    ({"pair_window_s": -1.0, "revisit_s": 10.0}, "'pair_window_s' must be >= 0"),
    ({"pair_window_s": 1.5}, "it needs 'revisit_s'"),
])
def test_a_pair_window_needs_sweeps_and_a_length(keys, says):
    from fusion.tracking.config import AssociationConfig
    with pytest.raises(ValueError, match=says):
        AssociationConfig.split({"association": "gnn", **keys})
