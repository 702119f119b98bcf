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
