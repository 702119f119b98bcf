"""The [traffic] generator of air-picture-live: deterministic per seed, bounded, Poisson
births at the stated rate, every aircraft crossing the box edge to edge in coverage;
and a short live run whose picture holds >= 3 confirmed tracks."""

from __future__ import annotations

import dataclasses
import json
import math
import subprocess
import time

import numpy as np
import pytest
from scipy import stats

from sensors_sim import load_scenario, sensor_events, truth_events
from sensors_sim.geometry import in_coverage
from sensors_sim.traffic import Traffic, longest_life

from conftest import zfusion

SC = load_scenario("air-picture-live")


def _aircraft(traffic: Traffic, times) -> dict:
    seen = {}
    for t in times:
        for a in traffic.alive(float(t)):
            seen.setdefault(a.id, a)
    return seen


def test_deterministic_per_seed_and_replayable():
    times = np.arange(0.0, 900.0, 1.0)
    a = _aircraft(Traffic(SC.traffic, 1), times)
    b = _aircraft(Traffic(SC.traffic, 1), times)
    assert a.keys() == b.keys() and all(np.array_equal(a[k].p0, b[k].p0) and a[k].t0 == b[k].t0 for k in a)
    c = _aircraft(Traffic(SC.traffic, 2), times)
    assert {(k, v.t0) for k, v in a.items()} != {(k, v.t0) for k, v in c.items()}
    cursor = Traffic(SC.traffic, 1)
    first = [x.id for x in cursor.alive(500.0)]
    cursor.alive(800.0)
    assert [x.id for x in cursor.alive(500.0)] == first  # an earlier time replays


def test_alive_count_bounded_and_cap_counted():
    spec = dataclasses.replace(SC.traffic, rate=30 / 60.0, max_alive=5)
    traffic = Traffic(spec, 3)
    counts = [len(traffic.alive(float(t))) for t in range(0, 3000, 2)]
    assert max(counts) == 5 and traffic.dropped > 0
    # the stationary mean alive at t = 0 already (the process starts at -L_max)
    full = Traffic(SC.traffic, 4)
    assert len(full.alive(0.0)) >= 5


def test_birth_rate_matches_poisson():
    """Births per 10-minute window over 2,000 hours: counts Poisson(λ·600) — mean by a
    z test, dispersion by the χ² index-of-dispersion test (both at 1e-3)."""
    spec = dataclasses.replace(SC.traffic, max_alive=10**6)
    traffic = Traffic(spec, 7)
    window, n_windows = 600.0, 12_000
    start = -longest_life(spec)
    counts = []
    traffic.alive(0.0)
    previous = traffic.births
    for k in range(1, n_windows + 1):
        traffic.alive(k * window - 1e-9)
        counts.append(traffic.births - previous)
        previous = traffic.births
    counts = np.array(counts)
    mu = spec.rate * window
    z = (counts.mean() - mu) / math.sqrt(mu / n_windows)
    assert abs(z) < 3.3, (counts.mean(), mu)
    d = ((counts - counts.mean()) ** 2).sum() / counts.mean()  # ~ χ²(n - 1) for Poisson counts
    lo, hi = stats.chi2.ppf([5e-4, 1 - 5e-4], n_windows - 1)
    assert lo < d < hi
    assert start < 0


def test_each_aircraft_enters_and_leaves_the_box_in_coverage():
    x0, x1, y0, y1 = SC.traffic.box
    for a in _aircraft(Traffic(SC.traffic, 1), np.arange(0.0, 1200.0, 1.0)).values():
        start, end = a.position(a.t0), a.position(a.t1)
        on_edge = lambda p: min(abs(p[0] - x0), abs(p[0] - x1), abs(p[1] - y0), abs(p[1] - y1)) < 1e-6
        assert on_edge(start) and on_edge(end)
        assert np.linalg.norm(end[:2] - start[:2]) > 0.99 * min(x1 - x0, y1 - y0)  # the far edge
        assert SC.traffic.alt[0] <= start[2] <= SC.traffic.alt[1]
        for tau in np.linspace(a.t0, a.t1, 7):
            for s in SC.sensors.values():
                assert in_coverage(s, a.position(tau) - s.site.position(tau)), (a.id, s.id)


def test_sensors_and_truth_see_the_same_population():
    sc = dataclasses.replace(SC, duration=20.0)
    truth = {(s.t, s.target) for s in truth_events(sc)}
    plots = {(e.t, e.target) for e in sensor_events(sc, "radar1") if not e.clutter}
    assert plots == truth and len({tg for _, tg in truth}) >= 8


@pytest.mark.slow
def test_live_run_picture_has_confirmed_tracks(tmp_path, deployment):
    """During `zfusion run --scenario air-picture-live --live`, `zfusion picture` from
    another process, dialling the endpoint the run printed (``--listen``), returns >= 3
    confirmed tracks (a fused track is only reported once confirmed)."""
    from services.launcher import free_port

    hub = f"tcp/127.0.0.1:{free_port()}"
    run = zfusion("run", "--scenario", "air-picture-live", "--live", "--for", "15", "--deployment", deployment,
                  "--listen", hub, "--json", str(tmp_path / "run.json"), "--rrd", str(tmp_path / "run.rrd"),
                  stdout=subprocess.DEVNULL, stderr=(tmp_path / "run.err").open("w"))
    best = []
    try:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and run.poll() is None and len(best) < 3:
            time.sleep(2)
            q = zfusion("picture", "--deployment", deployment, "--timeout", "5", "--connect", hub,
                        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
            out, _ = q.communicate(timeout=60)
            if q.returncode == 0:
                tracks = json.loads(out)["tracks"]
                best = tracks if len(tracks) > len(best) else best
    finally:
        run.wait(timeout=180)
    err = (tmp_path / "run.err").read_text()
    assert run.returncode == 0, err[-3000:]
    # the run says where to find it before anything else
    assert f"session at {hub} (zfusion picture --connect {hub} --deployment {deployment})" in err.splitlines()[0]
    assert len(best) >= 3, best
    assert all(np.all(np.isfinite(t["x"])) for t in best)
    summary = json.loads((tmp_path / "run.json").read_text())
    assert summary["epoch_utc"] > 1e9
    ss = summary["methods"]["SS"]  # scored over the ~15 s played, not the scenario's 600 s
    assert 10 <= ss["steps"] <= 25 and ss["held"] > 0.5, ss


# --- manoeuvres: waypoints with fly-by turns, level changes --------------------------

MANOEUVRES = dataclasses.replace(
    SC.traffic, rate=6.0 / 60.0, box=(-150e3, 150e3, -120e3, 120e3), waypoints=2, waypoint_offset=30e3,
    turn_rate=(math.radians(1.0), math.radians(3.0)), level_changes=2, climb_rate=(5.0, 15.0), max_alive=200)


def _population(spec, seed=5, times=np.arange(0.0, 4000.0, 50.0)):
    cursor = Traffic(spec, seed)
    return cursor, _aircraft(cursor, times)


def test_straight_level_crossings_are_the_first_versions():
    """Without manoeuvre keys an aircraft is the straight line of the first version: from
    its entry ``p0`` at its speed to the far edge, level, ``t1 = t0 + L/v``."""
    for a in _aircraft(Traffic(SC.traffic, 1), np.arange(0.0, 900.0, 5.0)).values():
        t = a.t0 + 17.0
        x = a.state(t)
        v = x[3:6]
        np.testing.assert_array_equal(x[:3], a.p0 + v * (t - a.t0))
        assert v[2] == 0.0 and not x[6:].any()
        assert a.t1 - a.t0 == pytest.approx(np.linalg.norm(a.position(a.t1) - a.p0) / np.linalg.norm(v), rel=1e-12)


def test_manoeuvring_aircraft_fly_their_kinematics():
    """Velocity and acceleration are the derivatives of the position (central differences
    over the whole life, across every leg and level change), the ground speed is
    constant, turn rates and vertical rates are those drawn (or a capped turn's), every
    aircraft turns and changes level, enters on an edge and leaves at the far one."""
    spec = MANOEUVRES
    _, aircraft = _population(spec)
    assert len(aircraft) > 50
    x0, x1, y0, y1 = spec.box
    on_edge = lambda p: min(abs(p[0] - x0), abs(p[0] - x1), abs(p[1] - y0), abs(p[1] - y1)) < 1e-6  # noqa: E731
    turned = climbed = 0
    for a in list(aircraft.values())[:60]:
        assert on_edge(a.position(a.t0)) and on_edge(a.position(a.t1))
        assert np.linalg.norm(a.position(a.t1)[:2] - a.p0[:2]) > 0.99 * min(x1 - x0, y1 - y0)
        ts = np.linspace(a.t0 + 1.0, a.t1 - 1.0, 2000)
        h = 1e-3
        X, Xp, Xm = a.states(ts), a.states(ts + h), a.states(ts - h)
        # no level change or turn starts or ends in between: the derivatives jump there
        smooth = (np.abs(Xp[:, 3:6] - Xm[:, 3:6]).max(axis=1) < 1.0) & (np.abs(Xp[:, 6:] - Xm[:, 6:]).max(axis=1) < 0.1)
        np.testing.assert_allclose((Xp[smooth, :3] - Xm[smooth, :3]) / (2 * h), X[smooth, 3:6], atol=1e-4)
        np.testing.assert_allclose((Xp[smooth, 3:5] - Xm[smooth, 3:5]) / (2 * h), X[smooth, 6:8], atol=1e-4)
        assert smooth.mean() > 0.99
        speed = np.hypot(X[:, 3], X[:, 4])
        np.testing.assert_allclose(speed, speed[0], rtol=1e-12)
        assert spec.speed[0] <= speed[0] <= spec.speed[1]
        rate = np.abs(X[:, 6] * X[:, 4] - X[:, 7] * X[:, 3]) / speed**2  # |ω| = |v × a| / v²
        turning = rate > 0
        turned += bool(turning.any())
        assert np.all(rate[turning] >= spec.turn_rate[0] - 1e-12)
        vz = np.abs(X[:, 5])
        climbed += bool((vz > 0).any())
        assert np.all((vz == 0) | ((vz >= spec.climb_rate[0] - 1e-9) & (vz <= spec.climb_rate[1] + 1e-9)))
        assert np.all((X[:, 2] >= spec.alt[0] - 1e-6) & (X[:, 2] <= spec.alt[1] + 1e-6))
    assert turned == climbed == 60


def test_a_manoeuvring_population_is_a_function_of_seed_and_run():
    """The fleet (arrays, all at once) and each aircraft alone give the same states; a
    second cursor, and a replay after a later time, the same population; another run
    another one; the life bound holds."""
    cursor, a = _population(MANOEUVRES)
    _, b = _population(MANOEUVRES)
    assert a.keys() == b.keys()
    for k in a:
        np.testing.assert_array_equal(a[k].state(a[k].t0 + 100.0), b[k].state(b[k].t0 + 100.0))
        assert a[k].t1 - a[k].t0 <= longest_life(MANOEUVRES)
    fleet = cursor.fleet(3950.0)
    X = fleet.states(3960.0)
    for i, ident in enumerate(fleet.ids):
        np.testing.assert_array_equal(X[i], a[ident].state(3960.0))
    assert [x.id for x in cursor.alive(1000.0)] == [x.id for x in Traffic(MANOEUVRES, 5).alive(1000.0)]
    other = Traffic(MANOEUVRES, 5, run=1).alive(1000.0)
    assert {x.id: x.t0 for x in other} != {x.id: x.t0 for x in cursor.alive(1000.0)}
