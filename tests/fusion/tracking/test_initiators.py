"""fusion.tracking.initiators: a new 3D track from an angle plot's ray and a 2D radar
plot's range sphere, at the crossing the radar's azimuth confirms."""

from __future__ import annotations

import math

import numpy as np
import pytest

from fusion.init3d import FAR, NEAR, InitPriors
from fusion.methods import make_method
from fusion.tracking.initiators import Initiator, moved
from fusion.types import Measurement


# Initiation at either crossing of a range sphere ------------------------------------------
_RADAR, _ANGLE_OUT, _ANGLE_IN = np.zeros(3), np.array([0.0, 50e3, 0.0]), np.array([0.0, 10e3, 0.0])


def _pair(p, angle_site, rng=None):
    """Noise-free plots of the point p: an angle sensor at ``angle_site`` (az, el) and a
    2D radar at the origin (az, slant range ``rng``, default |p|); σ 1 mrad, 1°, 20 m."""
    e, n, u = p - angle_site
    a = Measurement(0.0, "angle", "azel", np.array([math.atan2(e, n) % (2 * math.pi), math.atan2(u, math.hypot(e, n))]),
                    np.array([1e-3, 1e-3]), angle_site, 0)
    r = Measurement(0.0, "radar", "range_az", np.array([math.atan2(p[0], p[1]) % (2 * math.pi),
                                                         np.linalg.norm(p) if rng is None else rng]),
                    np.array([math.radians(1.0), 20.0]), _RADAR, 0)
    return a, r


def _crossings(a, r):
    """Closed form: the distances t along the ray where |s + t·u − s_r| = r, t > 0."""
    az, el = a.z
    u = np.array([math.cos(el) * math.sin(az), math.cos(el) * math.cos(az), math.sin(el)])
    w = a.site - r.site
    b, c = u @ w, w @ w - r.z[1] ** 2
    disc = b * b - c
    return [] if disc <= 0 else [t for t in (-b - math.sqrt(disc), -b + math.sqrt(disc)) if t > 0]


@pytest.mark.parametrize("site, p, root", [
    (_ANGLE_OUT, np.array([3e3, 30e3, 5e3]), NEAR),   # angle sensor outside the sphere, aircraft at its near crossing
    (_ANGLE_OUT, np.array([1e3, -10e3, 3e3]), FAR),   # outside, the ray goes past the radar: aircraft at the far one
    (_ANGLE_IN, np.array([3e3, 30e3, 5e3]), FAR),     # inside the sphere: the near root is behind the sensor
])
def test_a_pair_starts_at_the_crossing_the_radar_azimuth_confirms(site, p, root):
    """The ray of an angle plot crosses the radar plot's range sphere at
    t± = −b ± √(b² − c) (fusion.init3d); ahead of the sensor are both when it lies
    outside the sphere, only t₊ inside. The pair keeps the crossing(s) whose radar
    azimuth is in the gate, and the track starts there. The old rule took t₊ always: the
    first case started no track."""
    a, r = _pair(p, site)
    ts = _crossings(a, r)
    assert len(ts) == (2 if site is _ANGLE_OUT else 1)
    t_true = float(np.linalg.norm(p - site))
    assert min(abs(t - t_true) for t in ts) < 1e-6 * t_true  # the closed form finds the aircraft
    cands = Initiator(9, InitPriors(), 0.999).pair_consistency(a, r)
    assert [c[0] for c in cands] == [root]
    np.testing.assert_allclose(cands[0][2][:3], p, atol=1e-6 * t_true)
    assert cands[0][1] < 1e-12  # noise-free: the radar azimuth fits exactly
    method = make_method("SS", {"association": "gnn", "confirm_m": 1, "confirm_n": 1})
    out = []
    for m in sorted([a, r], key=lambda m: m.order_key):
        out += method.advance(m.t - 0.5) + method.process(m)
    out += method.finish()
    assert len(out) == 1
    np.testing.assert_allclose(out[0].x[:3], p, atol=1e-6 * t_true)


@pytest.mark.parametrize("rng", [10e3, 9e3])
def test_a_ray_that_touches_or_misses_the_sphere_makes_no_pair(rng):
    """A horizontal ray due north from (10, −50, 0) km passes the radar at 10 km: a
    sphere of 10 km it touches (b² = c exactly, where t no longer depends on r: the
    Jacobian is singular), one of 9 km it misses — no candidate either way, and the
    frame's two plots start no pair (each waits: a partner kind is in the frame)."""
    a = Measurement(0.0, "angle", "azel", np.array([0.0, 0.0]), np.array([1e-3, 1e-3]), np.array([10e3, -50e3, 0.0]), 0)
    r = Measurement(0.0, "radar", "range_az", np.array([math.pi / 2, rng]), np.array([math.radians(1.0), 20.0]), _RADAR, 0)
    assert _crossings(a, r) == []
    ini = Initiator(9, InitPriors(), 0.999)
    assert ini.pair_consistency(a, r) == []
    assert [g[:2] for g in ini.groups([a, r])] == []
    inside = Measurement(0.0, "radar", "range_az", np.array([math.pi / 2, 10_001.0]), r.std, _RADAR, 0)
    assert len(_crossings(a, inside)) == 2  # 1 m larger: crossings 141 m either side of the tangent point, both in the gate
    assert {c[0] for c in ini.pair_consistency(a, inside)} == {NEAR, FAR}
    assert len(ini.groups([a, inside])) == 1  # one track from the pair, not two


# Pairs across frames (the sweep tracker's pair_window_s) -------------------------------------
def _plot(kind, sensor, site, p, t, std, seq=0):
    """A noise-free plot of the point ``p`` at time ``t``: ``range_az`` (az, slant range)
    or ``azel`` (az, el) from ``site``."""
    e, n, u = p - site
    az = math.atan2(e, n) % (2 * math.pi)
    z = [az, float(np.linalg.norm(p - site))] if kind == "range_az" else [az, math.atan2(u, math.hypot(e, n))]
    return Measurement(t, sensor, kind, np.array(z), np.array(std, dtype=float), site, seq)


def test_a_moved_radar_plot_carries_the_targets_motion_as_its_error():
    """A 2D radar plot moved by Δt (fusion.tracking.initiators.moved): the target went
    v·Δt with v ~ N(0, σ_v² I₃), which adds (σ_v Δt)² to the range's variance and
    (σ_v Δt / r)² to the azimuth's. Against a Monte Carlo of that motion (200,000 draws,
    the true range and azimuth of p + v·Δt): the spreads within 1 %; and the plot is the
    same plot, at the new time."""
    p, site, dt, vel_std = np.array([20e3, 25e3, 3e3]), np.array([1e3, -2e3, 50.0]), 1.2, 140.0
    r = _plot("range_az", "radar", site, p, 10.0, [math.radians(0.15), 60.0], seq=7)
    m = moved(r, 10.0 - dt, vel_std)
    assert (m.t, m.sensor, m.kind, m.seq, m.moved_from) == (10.0 - dt, "radar", "range_az", 7, r)
    np.testing.assert_array_equal(m.z, r.z)
    step = vel_std * dt
    np.testing.assert_allclose(m.std ** 2, r.std ** 2 + [(step / r.z[1]) ** 2, step ** 2], rtol=1e-12)
    d = p - site + np.random.default_rng(1).normal(0.0, step, (200_000, 3))
    az = np.arctan2(d[:, 0], d[:, 1]) - r.z[0]
    rng = np.linalg.norm(d, axis=1) - r.z[1]
    assert np.std(rng) == pytest.approx(step, rel=0.01)
    # the slant range stands for the ground range a 2D radar does not know: cos(el) off
    el = math.asin((p - site)[2] / r.z[1])
    assert np.std(az) * math.cos(el) == pytest.approx(step / r.z[1], rel=0.01)


def test_a_radar_plot_pairs_with_an_angle_plot_of_an_earlier_frame_within_the_window():
    """An aircraft flying away from the radar at 150 m/s: an angle plot at 0 s, a 2D radar plot at 0.5 s, in two
    frames. Within the frame alone (window 0) they start no pair; with a window of
    1.5 s one pair starts, at the angle plot's time, the radar plot moved there, its
    state's position close to the aircraft's at 0 s in its own covariance (d² < 3); a
    pair that took the radar plot as it is, 75 m further in range, is 3.7σ off (d² 14).
    Two earlier plots never pair with each other, nor a plot outside the window."""
    p0 = np.array([3e3, 30e3, 5e3])
    vel = 150.0 * p0 / np.linalg.norm(p0)
    a = _plot("azel", "angle", _ANGLE_IN, p0, 0.0, [1e-3, 1e-3])
    r = _plot("range_az", "radar", _RADAR, p0 + 0.5 * vel, 0.5, [math.radians(0.2), 20.0], seq=1)
    ini = Initiator(9, InitPriors(vel_std=140.0), 0.999)
    pairs = lambda groups: [g for g in groups if len(g[0]) == 2]  # noqa: E731 (the lone radar plot's is dropped later)
    assert pairs(ini.groups_across([r], [a], 0.0)[0]) == []
    assert pairs(ini.groups_across([r], [a], 0.4)[0]) == []
    groups, moved_from = ini.groups_across([r], [a], 1.5)
    assert len(groups) == 1
    (first, more, x, P), = groups
    assert more == [] and first[0] is a and first[1].t == 0.0 and moved_from == {id(first[1]): r}
    d2 = float((x[:3] - p0) @ np.linalg.solve(P[:3, :3], x[:3] - p0))
    assert ini.groups_across([], [a, r], 1.5) == ([], {})
    unmoved, = pairs(ini.groups([a, r]))
    d2_unmoved = float((unmoved[2][:3] - p0) @ np.linalg.solve(unmoved[3][:3, :3], unmoved[2][:3] - p0))
    assert d2_unmoved > 9.0 > 3.0 > d2  # taken as it is, the radar plot puts the pair 3.7σ off


def test_a_pair_within_the_frame_goes_before_a_pair_across_frames_of_the_same_support():
    """An angle plot and two 2D radar plots of one radar that fit its ray: one in the
    frame, 1σ off in azimuth, one of an earlier frame, moved (its wider σ makes its
    azimuth's d² the smaller). Each pair gathers nothing (one radar): the same support;
    the pair within the frame starts the track, and the earlier plot is left."""
    p = np.array([3e3, 30e3, 5e3])
    std = [math.radians(0.2), 20.0]
    a = _plot("azel", "angle", _ANGLE_IN, p, 2.0, [1e-3, 1e-3])
    now = _plot("range_az", "radar", _RADAR, p, 2.0, std, seq=2)
    now = Measurement(now.t, now.sensor, now.kind, now.z + [std[0], 0.0], now.std, now.site, now.seq)
    before = _plot("range_az", "radar", _RADAR, p, 1.0, std, seq=1)
    ini = Initiator(9, InitPriors(vel_std=140.0), 0.999)
    d2_now = ini.pair_consistency(a, now)[0][1]
    d2_before = ini.pair_consistency(a, moved(before, a.t, 140.0))[0][1]
    assert d2_before < d2_now  # the premise: by d² alone the earlier plot would win
    groups, _ = ini.groups_across([a, now], [before], 1.5)
    assert [g[0] for g in groups] == [[a, now]]


# The batched screens: they drop only what the one-pair path would -----------------------
def _dense_frame(rng, n_angle=60, n_radar=120, radar_az_std_deg=1.0, n_aircraft=12):
    """One frame as air-picture-dense's: two angle sensors (0.05°) and two 2D radars (az σ
    ``radar_az_std_deg``, 20 m), each with the noisy plots of ``n_aircraft`` aircraft and
    false plots uniform in its measurement space."""
    sites = {"angle1": np.array([50e3, 0.0, 0.0]), "angle2": np.array([0.0, 55e3, 0.0]),
             "radar1": np.zeros(3), "radar2": np.array([50e3, 55e3, 0.0])}
    plots, seq = [], 0
    std = {"azel": np.radians([0.05, 0.05]), "range_az": np.array([math.radians(radar_az_std_deg), 20.0])}
    for p in np.column_stack([rng.uniform(10e3, 45e3, (n_aircraft, 2)), rng.uniform(3e3, 8e3, n_aircraft)]):
        for s, site in sites.items():
            e, n, u = p - site
            kind = "azel" if s.startswith("angle") else "range_az"
            z = (np.array([math.atan2(e, n) % (2 * math.pi), math.atan2(u, math.hypot(e, n))]) if kind == "azel" else
                 np.array([math.atan2(e, n) % (2 * math.pi), float(np.linalg.norm(p - site))]))
            seq += 1
            plots.append(Measurement(0.0, s, kind, z + std[kind] * rng.standard_normal(2), std[kind], site, seq))
    for s in ("angle1", "angle2"):
        for _ in range(n_angle):
            seq += 1
            plots.append(Measurement(0.0, s, "azel", np.array([rng.uniform(0, 2 * math.pi), rng.uniform(0.0, 0.5)]),
                                     np.radians([0.05, 0.05]), sites[s], seq))
    for s in ("radar1", "radar2"):
        for _ in range(n_radar):
            seq += 1
            plots.append(Measurement(0.0, s, "range_az", np.array([rng.uniform(0, 2 * math.pi), rng.uniform(2e3, 80e3)]),
                                     np.array([math.radians(radar_az_std_deg), 20.0]), sites[s], seq))
    return plots


@pytest.mark.parametrize("radar_az_std_deg", [1.0, 0.02])  # the angle plot's direction, or the radar's
def test_the_crossing_screen_keeps_every_pair_in_the_gate(radar_az_std_deg):
    """``_near_spheres`` with the gate drops a (radar plot, crossing) only where
    :meth:`Initiator.pair_consistency` finds it outside the χ²(1) gate: over a dense
    frame of random rays and spheres, both give the same candidate pairs (where the
    radar measures azimuth better than the angle sensor the direction is the radar's and
    the screen does not apply)."""
    from fusion.tracking import initiators

    rng = np.random.default_rng(7)
    ini = Initiator(9, InitPriors(range=35e3, range_std=20e3, el=0.3, el_std=0.3), 0.999)
    plots = _dense_frame(rng, n_angle=15, n_radar=60, radar_az_std_deg=radar_az_std_deg)
    angles = [m for m in plots if m.kind == "azel"]
    gate, k = ini._gate(1), initiators._PAIR_PREFILTER * math.sqrt(ini._gate(1))
    kept = dropped = 0
    for a in angles:
        radars = [m for m in plots if m.kind == "range_az"]
        wide = {id(r): roots for r, roots in initiators._near_spheres(a, radars, k)}
        tight = {id(r): roots for r, roots in initiators._near_spheres(a, radars, k, gate)}
        for r in radars:
            full = [c[0] for c in ini.pair_consistency(a, r, wide.get(id(r), ()))]
            assert [c[0] for c in ini.pair_consistency(a, r, tight.get(id(r), ()))] == full
            kept += len(full)
            dropped += len(wide.get(id(r), ())) - len(tight.get(id(r), ()))
    assert kept > 30  # the frame is dense enough to have pairs in the gate
    assert (dropped > 500) == (radar_az_std_deg == 1.0)  # and the screen does its work where it applies


def test_groups_are_the_same_with_and_without_the_screens(monkeypatch):
    """The initiation groups of a dense frame (pairs, gathered plots, states) are those of
    the one-pair path: the crossing screen and the gathering screen switched off give
    the very same groups."""
    from fusion.tracking import initiators

    rng = np.random.default_rng(11)
    plots = _dense_frame(rng, n_angle=40, n_radar=150)
    ini = Initiator(9, InitPriors(range=35e3, range_std=20e3, el=0.3, el_std=0.3), 0.999)
    screened = ini.groups(plots)
    near = initiators._near_spheres
    monkeypatch.setattr(initiators, "_near_spheres", lambda a, radars, k, gate=math.inf: near(a, radars, k))
    monkeypatch.setattr(initiators._BySensor, "screen", lambda self, cands, gate: [[None] * len(self.groups)] * len(cands))
    plain = ini.groups(plots)
    assert len(screened) > 10 and any(g[1] for g in screened)  # pairs, some of which gathered plots
    assert len(screened) == len(plain)
    for (f1, m1, x1, P1), (f2, m2, x2, P2) in zip(screened, plain):
        assert [m.seq for m in f1] == [m.seq for m in f2] and [m.seq for m in m1] == [m.seq for m in m2]
        assert np.array_equal(x1, x2) and np.array_equal(P1, P2)


def test_the_crossing_screen_computes_the_one_pair_d2():
    """The crossing screen's ``d²`` is :meth:`Initiator.pair_consistency`'s to 1e-6: for
    every pair in the gate, a gate just under its ``d²`` drops the crossing and one just
    over keeps it."""
    from fusion.tracking import initiators

    rng = np.random.default_rng(5)
    ini = Initiator(9, InitPriors(range=35e3, range_std=20e3, el=0.3, el_std=0.3), 0.999)
    plots = _dense_frame(rng, n_angle=20, n_radar=60)
    radars = [m for m in plots if m.kind == "range_az"]
    k = initiators._PAIR_PREFILTER * math.sqrt(ini._gate(1))
    checked = 0
    for a in (m for m in plots if m.kind == "azel"):
        for r in radars:
            for root, d2, _, _ in ini.pair_consistency(a, r):
                if d2 < 1e-3:
                    continue
                roots = lambda g: next((rs for _, rs in initiators._near_spheres(a, [r], k, g)), ())  # noqa: E731
                assert root not in roots(d2 * (1.0 - 1e-5)) and root in roots(d2 * (1.0 + 1e-5)), (a, r, root, d2)
                checked += 1
    assert checked > 30


def test_the_gathering_screen_keeps_exactly_the_plots_in_the_gate():
    """``_BySensor.screen`` names, per candidate pair and sensor, the plots whose
    one-pair ``d²`` (:func:`mahalanobis2`) is inside the χ² gate of the sensor's ``n_z``:
    plots placed at ``d²`` from 0.2 to 2 gates of each pair's state, in random
    directions, are named exactly when under the gate."""
    from fusion.measurement.kinds import model_of
    from fusion.tracking.hypotheses import mahalanobis2
    from fusion.tracking.initiators import _BySensor

    rng = np.random.default_rng(9)
    ini = Initiator(9, InitPriors(range=35e3, range_std=20e3, el=0.3, el_std=0.3), 0.999)
    frame = _dense_frame(rng, n_angle=0, n_radar=0, n_aircraft=8)
    a_plots = [m for m in frame if m.sensor == "angle1"]
    r_plots = [m for m in frame if m.sensor == "radar1"]
    candidates = [(a, r, *c) for a, r in zip(a_plots, r_plots) for c in ini.pair_consistency(a, r)]
    assert len(candidates) >= 6
    others = []
    for sensor, tmpl in (("angle2", next(m for m in frame if m.sensor == "angle2")),
                         ("radar2", next(m for m in frame if m.sensor == "radar2"))):
        model = model_of(tmpl, 9)
        G = ini._gate(model.n_z)
        for _, _, _, _, x, P in candidates:
            H = model.jacobian(x)
            L = np.linalg.cholesky(H @ P @ H.T + model.R)
            for f in (0.2, 0.6, 0.95, 1.05, 1.4, 2.0):
                v = rng.standard_normal(model.n_z)
                z = model.h(x) + L @ (v / np.linalg.norm(v) * math.sqrt(f * G))
                others.append(Measurement(0.0, sensor, tmpl.kind, z, tmpl.std, tmpl.site, len(others) + 1000))
    sensors = _BySensor(others)
    near = sensors.screen(candidates, ini._gate)
    for (_, _, _, _, x, P), named in zip(candidates, near):
        for g, (plots, Z, _) in enumerate(sensors.groups):
            d2 = mahalanobis2(model_of(plots[0], 9), x, P, Z)
            assert named[g] == set(np.flatnonzero(d2 <= ini._gate(model_of(plots[0], 9).n_z)).tolist())
