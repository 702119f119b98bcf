"""SS and HNV with a cooperative position report beside the patent's 2D radar and angle
sensor (tests/data/patent-3d-adsb.toml: patent-3d plus an ``adsb`` sensor reporting
between the radar's scans): consistent over 100 Monte Carlo runs, by the statistics of
tests/fusion/test_patent_consistency.py — the level of the per-run time-averaged NEES
within 4 standard errors of the dimension, and the run-averaged NEES inside the two-sided
99.9 % χ² band at ≥ 90 % of the steps after the first five seconds. SS stacks a position
report in the scan it falls in (here alone, between scans); HNV runs a local tracker on
the position reports and fuses it with the radar's and the angle sensor's.

Verified offline for scenario seeds 1–4 (full state: SS level z within ±1.0, HNV within
±1.7; 96–100 % of the steps in band)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import chi2

from sim3d import centre_track, run_method, scenario_runs  # noqa: E402

from conftest import DATA  # noqa: E402
from fusion.methods import make_method, method_config  # noqa: E402
from sensors_sim import load_scenario  # noqa: E402

SCENARIO = str(DATA / "patent-3d-adsb.toml")
N_RUNS = 100
FIRST_S = 5.0


@pytest.fixture(scope="module")
def runs():
    return scenario_runs(SCENARIO, N_RUNS)


def _nees(runs, method: str) -> np.ndarray:
    table = load_scenario(SCENARIO).tracker
    tracks = [centre_track(run_method(make_method(method, method_config(table, method)), m))
              for m in runs.measurements]
    t = tracks[0][0]
    assert all(np.array_equal(tr[0], t) for tr in tracks)
    idx = np.searchsorted(runs.times, t)
    assert np.array_equal(runs.times[idx], t)  # every estimate at a measurement time
    e = np.array([tr[1] for tr in tracks]) - runs.truth[:, idx]
    P = np.array([tr[2] for tr in tracks])
    return np.einsum("...i,...i->...", e, np.linalg.solve(P, e[..., None])[..., 0])[:, t >= FIRST_S]


@pytest.mark.slow
@pytest.mark.parametrize("method", ["SS", "HNV"])
def test_a_method_fed_position_reports_is_consistent(runs, method):
    n = _nees(runs, method)
    dof = 9
    per_run = n.mean(axis=1)
    z = (per_run.mean() - dof) / (per_run.std(ddof=1) / np.sqrt(N_RUNS))
    lo, hi = chi2.ppf([0.0005, 0.9995], dof * N_RUNS) / N_RUNS
    a = n.mean(axis=0)
    inside = np.mean((a >= lo) & (a <= hi))
    assert abs(z) < 4.0 and inside >= 0.9, f"{method}: level z {z:+.2f}, {inside:.0%} in band, ANEES {np.round(a, 2)}"
    assert n.shape[1] >= 50  # the position reports' steps are scored too (two estimates per second)
