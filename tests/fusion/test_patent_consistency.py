"""Consistency (NEES) of the patent methods over 200 Monte Carlo runs of ``patent-3d``.
The diagnosis, with the numbers behind every choice here, is in
docs/consistency.md; in short:

The criterion — "over 200 runs, each method in its consistent configuration has
its average NEES inside the two-sided 95 % χ² bounds at ≥ 90 % of the time steps after
the first five scans" — is not a pass/fail test. Each run's error persists from scan to
scan, so the 26 per-scan averages are strongly correlated (lag-one correlation 0.75) and
the number of scans outside the band varies widely from one 200-run batch to the next:
an *exactly* consistent linear Kalman filter with this very geometry fails the criterion
in ≈ 18 % of batches (:func:`test_literal_criterion_fails_for_an_exactly_consistent_filter`).
More runs do not help: the band narrows as fast as the noise. So the criterion's fraction
is reported (in assertion messages and the doc), and what it is meant to establish is
tested with statistics whose false-alarm probability for a consistent filter is ≈ 0.1 %:

* *level*: the mean over runs of each run's NEES averaged over scans 5…30 (independent
  across runs) lies within 4 standard errors of the dimension — for the whole state and
  for position, velocity and acceleration separately (3 dof each), so that a low block
  cannot hide a high one;
* *shape*: the run-averaged NEES lies inside the two-sided 99.9 % χ² band at ≥ 90 % of
  the scans after the first five (an exactly consistent filter passes in 99.9 % of
  batches; catches transients the level averages out).

Consistent configuration. The truth of ``patent-3d`` is a realisation of the trackers'
model (CA, white-noise jerk with the trackers' q, discretised exactly) from a *fixed*
initial state (:func:`test_truth_is_a_realisation_of_the_trackers_model`). A prior over a
fixed quantity is consistent only if it no longer weighs; the default velocity and
acceleration priors (200 m/s, 10 m/s², zero mean) still do at scan 5 — six scans
measure acceleration only to a few m/s² — and make every method conservative there
(expected NEES 8.56 instead of 9, :func:`test_default_priors_still_weigh_at_scan_five`).
``ENVELOPE`` (1 km/s, 100 m/s² ≈ 10 g per axis: a bound on the flight envelope, not a
description of this target) weighs 0.006 in NEES at scan 5. The scenario files give each
method its consistent configuration in ``[tracker.methods.*]`` tables, and the tests run
the methods with those (:func:`test_the_scenarios_run_each_method_in_its_consistent_configuration`).

Methods:

* LCDD, HNDD, SS, PHHNV and DDHNV with the ``info`` or ``bar-shalom-campo`` rule
  observe the whole state: consistent with ``ENVELOPE``. (PHHNV/info = DDHNV/info = SS
  and DDHNV/bsc = PHHNV/bsc exactly, tests/fusion/test_patent_methods.py; run here: LCDD, HNDD,
  SS, PHHNV/bsc.)
* HNV: its 2D-radar local EKF never observes altitude and its angle-sensor local EKF
  never observes range, so each carries its prior along that direction into the fusion.
  With ``ENVELOPE`` horizontally and a physical vertical prior (20 m/s, 1 m/s²) its
  horizontal subspace is consistent; its vertical is conservative (the truth's fixed
  climb of 5 m/s and −0.05 m/s² is not drawn from that prior) and never overconfident.
* RADAR3D (1°, 20 m): with a non-informative prior its EKF is overconfident for ~20
  scans (the accurate range's curvature across a cross-range spread of hundreds of
  metres, see the doc); with its default prior it is conservative while that prior
  weighs, and consistent from the scan at which the prior's expected NEES deficit falls
  below 0.1 (scan 20, computed here, not chosen).
* RADAR2D, ANGLE: a single 2D radar never observes elevation, an angle sensor never
  observes range; their full-state NEES is governed by the prior and by the EKF's
  spurious information along the unobservable direction (docs/consistency.md). No
  consistency claim is made or tested for them.

Robustness: runs with the scenario's own seed (1); verified offline for scenario seeds
0–13: every test passes for each of the 14. ``ZF_MC_SEED=<n>`` reruns with another seed.
Runtime: 22 s on two cores at load ≈ 2, up to ≈ 40 s when they are shared more heavily.
"""

from __future__ import annotations

import os

import numpy as np
import pytest
from scipy.stats import chi2

from sim3d import LinearAnalogue, centre_track, run_method, scenario_runs  # noqa: E402

from fusion.methods import method_config  # noqa: E402
from fusion.motion import make_motion  # noqa: E402
from fusion.methods import make_method as make  # noqa: E402
from fusion.patent import TrackerConfig  # noqa: E402
from sensors_sim import load_scenario  # noqa: E402

N_RUNS = 200
FIRST = 5  # "after the first five scans": scans 5 … 30 are scored
SEED = int(os.environ.get("ZF_MC_SEED", "1"))  # 1: the scenario file's own seed
LEVEL_SE = 4.0  # level test: |mean − dof| < 4 standard errors
SHAPE_P, SHAPE_FRACTION = 0.999, 0.9  # shape test: ≥ 90 % of the scans inside the 99.9 % band

ENVELOPE = {"init_vel_std": 1e3, "init_vel_std_up": 1e3, "init_acc_std": 1e2, "init_acc_std_up": 1e2}
VERTICAL = {"init_vel_std_up": 20.0, "init_acc_std_up": 1.0}  # physical, for trackers blind to altitude
BSC = {"fusion_rule": "bar-shalom-campo"}
POS, VEL, ACC = [0, 1, 2], [3, 4, 5], [6, 7, 8]
HORIZONTAL, VERTICAL_AXIS = [0, 1, 3, 4, 6, 7], [2, 5, 8]

# key: (method, tracker overrides, scenario). Overrides None: the method's configuration
# in the scenario file ([tracker] with its [tracker.methods.<M>] table), which is what
# `zfusion run` and `zfusion eval` use; otherwise the common [tracker] keys + overrides.
CONFIGS = {
    "LCDD": ("LCDD", None, "patent-3d"),
    "HNDD": ("HNDD", None, "patent-3d"),
    "SS": ("SS", None, "patent-3d"),
    "PHHNV/bsc": ("PHHNV", {**BSC, **ENVELOPE}, "patent-3d"),
    "HNV/bsc": ("HNV", None, "patent-3d"),
    "RADAR3D": ("RADAR3D", None, "patent-3d-radar3d"),
    "RADAR3D/default": ("RADAR3D", {}, "patent-3d-radar3d"),
    "RADAR3D/envelope": ("RADAR3D", ENVELOPE, "patent-3d-radar3d"),
    "SS/default": ("SS", {}, "patent-3d"),
    "SS/envelope×10": ("SS", {k: 10 * v for k, v in ENVELOPE.items()}, "patent-3d"),
    "PHHNV/naive": ("PHHNV", {"fusion_rule": "naive", **ENVELOPE}, "patent-3d"),
    "PHHNV/ci": ("PHHNV", {"fusion_rule": "ci", **ENVELOPE}, "patent-3d"),
}
CONSISTENT = ["LCDD", "HNDD", "SS", "PHHNV/bsc", "RADAR3D"]


# Statistics -------------------------------------------------------------------------------
def band(p: float, dof: int, n_runs: int = N_RUNS) -> np.ndarray:
    """Two-sided ``p`` χ² bounds of the average of ``n_runs`` NEES values of ``dof`` dof."""
    return chi2.ppf([(1 - p) / 2, (1 + p) / 2], dof * n_runs) / n_runs


def block_nees(truth, x, P, idx=None) -> np.ndarray:
    """NEES ``(runs, scans)`` of the components ``idx`` (marginal covariance block)."""
    idx = np.arange(x.shape[-1]) if idx is None else np.asarray(idx)
    e = (x - truth)[..., idx]
    Pb = P[..., idx[:, None], idx[None, :]]
    return np.einsum("...i,...i->...", e, np.linalg.solve(Pb, e[..., None])[..., 0])


def level_z(n: np.ndarray, dof: int, first: int = FIRST) -> float:
    """(mean − dof) / standard error of the per-run time averages over scans ≥ ``first``."""
    per_run = n[:, first:].mean(axis=1)
    return float((per_run.mean() - dof) / (per_run.std(ddof=1) / np.sqrt(len(per_run))))


def in_band(n: np.ndarray, dof: int, p: float, first: int = FIRST) -> float:
    """Fraction of the scans ≥ ``first`` whose run-averaged NEES is inside the ``p`` band."""
    lo, hi = band(p, dof, n.shape[0])
    a = n[:, first:].mean(axis=0)
    return float(np.mean((a >= lo) & (a <= hi)))


def report(n: np.ndarray, dof: int, first: int = FIRST) -> str:
    a = n[:, first:].mean(axis=0)
    return (
        f"level z {level_z(n, dof, first):+.2f}; criterion (95 % band) {in_band(n, dof, 0.95, first):.0%}, "
        f"99.9 % band {in_band(n, dof, SHAPE_P, first):.0%} of scans ≥ {first}; ANEES {np.round(a, 2).tolist()}"
    )


def assert_consistent(n: np.ndarray, dof: int, what: str, first: int = FIRST) -> None:
    assert abs(level_z(n, dof, first)) < LEVEL_SE, f"{what}: {report(n, dof, first)}"
    assert in_band(n, dof, SHAPE_P, first) >= SHAPE_FRACTION, f"{what}: {report(n, dof, first)}"


# Monte Carlo runs (shared: each configuration runs once over the 200 runs) ---------------
class MonteCarlo:
    def __init__(self, seed: int):
        self.seed = seed
        self._runs: dict[str, object] = {}
        self._tracks: dict[str, tuple] = {}

    def runs(self, scenario: str):
        if scenario not in self._runs:
            self._runs[scenario] = scenario_runs(scenario, N_RUNS, self.seed)
        return self._runs[scenario]

    def __getitem__(self, key: str):
        """``(truth, x, P)`` of configuration ``key``, each ``(runs, scans, …)``."""
        if key not in self._tracks:
            name, overrides, scenario = CONFIGS[key]
            sim = self.runs(scenario)
            table = load_scenario(scenario).tracker
            cfg = method_config(table, name) if overrides is None else method_config(table, None, overrides)
            tracks = [centre_track(run_method(make(name, cfg), meas)) for meas in sim.measurements]
            assert all(np.array_equal(t[0], sim.times) for t in tracks)  # one estimate per scan
            self._tracks[key] = (sim.truth, np.array([t[1] for t in tracks]), np.array([t[2] for t in tracks]))
        return self._tracks[key]

    def nees(self, key: str, idx=None) -> np.ndarray:
        return block_nees(*self[key], idx)


@pytest.fixture(scope="module")
def mc():
    return MonteCarlo(SEED)


# The data and the priors -------------------------------------------------------------------
@pytest.mark.slow
def test_truth_is_a_realisation_of_the_trackers_model(mc):
    # Whitened one-scan increments of the truth, w = L⁻¹(x_{k+1} − F x_k) with LLᵀ = Q(1 s)
    # of the trackers' model: 200 × 30 × 9 values that must be i.i.d. N(0, 1).
    sim = mc.runs("patent-3d")
    cfg = TrackerConfig.from_dict(method_config(load_scenario("patent-3d").tracker, None))
    motion = make_motion(cfg.motion, cfg.q, cfg.process_noise)
    F, Q = motion.F(1.0), motion.Q(1.0)
    assert np.allclose(np.diff(sim.times), 1.0)
    d = sim.truth[:, 1:] - sim.truth[:, :-1] @ F.T
    w = np.linalg.solve(np.linalg.cholesky(Q), d.reshape(-1, 9).T).T
    n = w.shape[0]
    assert np.all(np.abs(w.mean(axis=0)) < 4.0 / np.sqrt(n)), w.mean(axis=0)
    C = np.cov(w.T)
    assert np.all(np.abs(C - np.eye(9)) < 4.0 * np.sqrt(2.0 / n)), np.round(C, 3)
    # … from one fixed initial state (no prior describes it: see the module docstring).
    assert np.ptp(sim.truth[:, 0], axis=0).max() == 0.0


def test_default_priors_still_weigh_at_scan_five():
    # Linear-Gaussian analogue of SS (exact; no Monte Carlo): expected NEES deficit
    # 9 − E[NEES] caused by the zero-mean prior about the truth's fixed velocity and
    # acceleration.
    default = LinearAnalogue.of_scenario("patent-3d").prior_deficit()
    envelope = LinearAnalogue.of_scenario("patent-3d", ENVELOPE).prior_deficit()
    per_scan_se = np.sqrt(2 * 9 / N_RUNS)  # ≈ 0.3: standard error of one scan's 200-run ANEES
    assert default[FIRST] > per_scan_se  # 0.44: conservative at scan 5, noticeably
    assert envelope[FIRST:].max() < 0.01  # 0.006: gone by scan 5
    assert np.all(default[FIRST:] >= envelope[FIRST:] - 1e-9)


@pytest.mark.slow
def test_the_prior_deficit_is_what_the_filters_show(mc):
    # Same measurements, two priors: the paired difference of run-averaged NEES at scans
    # 5–7 is the prior's deficit (analogue: 0.44, 0.22, 0.13 minus ~0.01), nearly free
    # of Monte Carlo noise.
    expected = (LinearAnalogue.of_scenario("patent-3d").prior_deficit() - LinearAnalogue.of_scenario("patent-3d", ENVELOPE).prior_deficit())[FIRST : FIRST + 3]
    diff = (mc.nees("SS") - mc.nees("SS/default")).mean(axis=0)[FIRST : FIRST + 3]
    assert np.all(np.abs(diff - expected) < 0.5 * expected + 0.05), (diff, expected)


@pytest.mark.slow
def test_envelope_prior_is_non_informative(mc):
    # Ten times broader changes nothing after scan 5: the prior no longer weighs.
    diff = (mc.nees("SS/envelope×10") - mc.nees("SS")).mean(axis=0)[FIRST:]
    assert np.abs(diff).max() < 0.05, np.round(diff, 3)


def test_the_scenarios_run_each_method_in_its_consistent_configuration():
    # What `zfusion run` / `zfusion eval` use is what the tests below establish: the
    # [tracker.methods.*] tables of the patent-3d scenarios carry these configurations.
    table = load_scenario("patent-3d").tracker
    for name in ("LCDD", "HNDD", "SS", "PHHNV", "DDHNV"):
        assert ENVELOPE.items() <= method_config(table, name).items(), name
    assert {**BSC, **ENVELOPE, **VERTICAL}.items() <= method_config(table, "HNV").items()
    assert {**ENVELOPE, "ekf_iterations": 5}.items() <= method_config(table, "RADAR3D").items()
    for name in ("RADAR2D", "ANGLE"):  # a broad prior along an unobservable direction hurts them
        assert method_config(table, name) == method_config(table, None), name


def test_literal_criterion_fails_for_an_exactly_consistent_filter():
    # 400 batches of 200 runs of the linear-Gaussian analogue of SS started from its own
    # prior: exactly consistent by construction (80 000 runs, vectorised).
    batches = 400
    analogue = LinearAnalogue.of_scenario("patent-3d", ENVELOPE)
    n = analogue.nees(batches * N_RUNS, np.random.default_rng(20240503)).reshape(batches, N_RUNS, -1)
    anees = n.mean(axis=1)
    assert np.abs(anees[:, FIRST:].mean() - 9.0) < 0.03
    lo, hi = band(0.95, 9)
    criterion = ((anees[:, FIRST:] >= lo) & (anees[:, FIRST:] <= hi)).mean(axis=1) >= 0.9
    assert 0.72 < criterion.mean() < 0.9  # ≈ 0.82: fails about one batch in five
    lag1 = np.mean([np.corrcoef(anees[:, k], anees[:, k + 1])[0, 1] for k in range(FIRST, anees.shape[1] - 1)])
    assert lag1 > 0.6  # ≈ 0.75
    # The tests here, shape (≥ 90 % inside the 99.9 % band) and level (|z| < 4), each
    # fail about one batch in a thousand.
    assert sum(in_band(b, 9, SHAPE_P) < SHAPE_FRACTION for b in n) <= 3
    z = np.array([level_z(b, 9) for b in n])
    assert np.sum(np.abs(z) >= LEVEL_SE) <= 2 and abs(z.std() - 1.0) < 0.12


# Consistent configurations -----------------------------------------------------------------
@pytest.mark.slow
@pytest.mark.parametrize("key", CONSISTENT)
def test_consistent_methods(key, mc):
    assert_consistent(mc.nees(key), 9, key)
    for name, idx in (("position", POS), ("velocity", VEL), ("acceleration", ACC)):
        n = mc.nees(key, idx)
        assert abs(level_z(n, 3)) < LEVEL_SE, f"{key} {name}: {report(n, 3)}"


@pytest.mark.slow
def test_hnv_horizontal_consistent_vertical_conservative(mc):
    # HNV's local trackers are each blind along one direction (radar: altitude; angle
    # sensor: range) and carry their priors along it into the fusion.
    assert_consistent(mc.nees("HNV/bsc", HORIZONTAL), 6, "HNV horizontal")
    vertical = mc.nees("HNV/bsc", VERTICAL_AXIS)
    assert level_z(vertical, 3) < LEVEL_SE, report(vertical, 3)  # never overconfident …
    # … and conservative while the vertical prior weighs (≈ 2.45 at scans 5–9; 3 later).
    assert vertical[:, FIRST : FIRST + 5].mean() < 3.0, report(vertical, 3)
    full = mc.nees("HNV/bsc")
    assert level_z(full, 9) < LEVEL_SE, report(full, 9)
    rmse = {k: np.sqrt(np.mean(np.sum((mc[k][1] - mc[k][0])[..., :3] ** 2, -1))) for k in ("HNV/bsc", "SS")}
    assert rmse["HNV/bsc"] < 1.1 * rmse["SS"], rmse


@pytest.mark.slow
def test_radar3d_conservative_while_its_prior_weighs_then_consistent(mc):
    # First scan from which the default prior's expected deficit is below 0.1 (a third of
    # one scan's standard error): 20 on patent-3d-radar3d.
    deficit = LinearAnalogue.of_scenario("patent-3d-radar3d").prior_deficit()
    settled = int(np.argmax(deficit < 0.1))
    assert 15 <= settled <= 25, settled
    n = mc.nees("RADAR3D/default")
    assert_consistent(n, 9, f"RADAR3D from scan {settled}", first=settled)
    assert n[:, FIRST:settled].mean() < 9.0, report(n, 9)  # conservative before
    assert level_z(n, 9) < LEVEL_SE, report(n, 9)  # and never overconfident


@pytest.mark.slow
def test_radar3d_single_ekf_is_overconfident_with_a_non_informative_prior_iterated_is_not(mc):
    # With the envelope prior a single linearisation of the accurate range across the
    # broad cross-range spread is overconfident over scans 5-10 (docs/consistency.md §4);
    # relinearising (the scenario's ekf_iterations = 5, tested consistent above) is not.
    # The shape statistic fails a consistent filter in 0.1 % of batches.
    single, iterated = mc.nees("RADAR3D/envelope"), mc.nees("RADAR3D")
    assert in_band(single, 9, SHAPE_P) < SHAPE_FRACTION, report(single, 9)
    assert single[:, FIRST : FIRST + 6].mean() > 9.5, report(single, 9)  # on the high side: overconfident
    assert in_band(iterated, 9, SHAPE_P) >= SHAPE_FRACTION, report(iterated, 9)


# Inconsistent fusion rules, for contrast ----------------------------------------------------
@pytest.mark.slow
def test_naive_feedback_fusion_is_overconfident_ci_conservative(mc):
    hi = band(SHAPE_P, 9)[1]
    naive = mc.nees("PHHNV/naive").mean(axis=0)[FIRST:]
    assert np.mean(naive > hi) > 0.9, np.round(naive, 2)  # counts the shared prior twice
    lo = band(0.95, 9)[0]
    ci = mc.nees("PHHNV/ci").mean(axis=0)[FIRST:]
    assert np.all(ci < lo), np.round(ci, 2)  # CI does not know the tracks share their prior
