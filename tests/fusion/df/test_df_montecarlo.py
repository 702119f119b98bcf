"""Issue-4 acceptance: Monte Carlo on the thesis scenarios (100 runs × 40 epochs).

thesis-fixed-c1: the EKF with a static-emitter model must come within 20 % of the
Cramér–Rao bound. jammed-df: the IMM's RMS position error must be at least 30 % lower
than the plain EKF's. The noise is drawn once, vectorised, from a seeded Generator.

The jamming comparison is run with both filters initialised alike (config ``init``):

* ``ipu`` (the theses'): the first pair holds an outlier in half the runs, and a few
  such runs diverge (tens to hundreds of km) and decide the RMS of *either* filter; the
  IMM then beats the EKF on RMS for some seeds and not others, while its median miss is
  5–7 times smaller for every seed. Only the median is asserted for ``ipu``.
* ``robust`` (:mod:`fusion.df.init`, window of ``init_epochs = 5``): the acceptance.

The tests use one seed; ``python tests/fusion/df/test_df_montecarlo.py --seeds 1-10`` prints the
per-seed table (both outlier laws) that shows the conclusions do not hang on it.
"""

from __future__ import annotations

import numpy as np
import pytest

from fusion.df import make
from fusion.df.crb import crb_rmse, crb_rmse_series
from fusion.df.models import THESIS_Q22, bearing, bearing_measurements
from fusion.df.noise import contaminated, gaussian
from fusion.metrics import chi2_bounds, nees, rmse

EMITTER = np.array([15e3, 15e3])
SIGMA = 0.0175
RUNS, EPOCHS = 100, 40


def final_estimates(name, config, sites, noise):
    """Run ``name`` on every run's stream; return the final estimates' x and P."""
    sensors = [f"DF{i + 1}" for i in range(len(sites))]
    beta = bearing(EMITTER, sites)
    epochs = noise.shape[1]
    xs, Ps = [], []
    for r in range(noise.shape[0]):
        ms = bearing_measurements(1.0 + np.arange(epochs), sensors, sites, beta + noise[r], SIGMA)
        m = make(name, config)
        out = [e for b in ms for e in m.process(b)] + m.finish()
        assert len(out) == epochs
        xs.append(out[-1].x)
        Ps.append(out[-1].P)
    return np.array(xs), np.array(Ps)


@pytest.fixture(scope="module")
def c1():
    sites = np.array([[0.0, 0.0], [20e3, 0.0]])
    noise = gaussian(np.random.default_rng(1), SIGMA, (RUNS, EPOCHS, 2))
    return sites, noise


def test_crb_series_accumulates_the_bearings(c1):
    sites, _ = c1
    series = crb_rmse_series(EMITTER, [(sites, SIGMA)] * EPOCHS)
    assert series[-1] == pytest.approx(crb_rmse(EMITTER, np.repeat(sites, EPOCHS, axis=0), SIGMA))
    np.testing.assert_allclose(series * np.sqrt(np.arange(1, EPOCHS + 1)), series[0], rtol=1e-12)  # ∝ 1/√k


def test_ekf_static_model_reaches_the_crb_on_thesis_fixed_c1(c1):
    sites, noise = c1
    x, P = final_estimates("EKF", {"q22": 0.0}, sites, noise)
    bound = crb_rmse(EMITTER, np.repeat(sites, EPOCHS, axis=0), SIGMA)
    ratio = rmse(x - EMITTER) / bound
    assert 0.8 <= ratio <= 1.2, ratio
    # and its covariance is consistent: ANEES within the 99 % two-sided χ² interval
    lo, hi = chi2_bounds(2, RUNS, 0.99)
    assert lo <= np.mean(nees(x - EMITTER, P)) <= hi


@pytest.mark.parametrize("name", ["EKF", "IMM", "MEKF3"])
def test_default_model_keeps_converging_on_a_stationary_emitter(c1, name):
    """No q22 given (a site, or a scenario that does not set it): after 400 epochs the
    final fix is within 1.5x the CRB of all 800 bearings. The theses' random-walk q22,
    which their scenarios set, stalls where the bound has gone on shrinking."""
    sites, _ = c1
    noise = gaussian(np.random.default_rng(4), SIGMA, (20, 400, 2))
    bound = crb_rmse(EMITTER, np.repeat(sites, 400, axis=0), SIGMA)  # 22 m
    x, _ = final_estimates(name, {}, sites, noise)
    assert rmse(x - EMITTER) <= 1.5 * bound, (name, rmse(x - EMITTER), bound)
    if name == "EKF":
        stalled, _ = final_estimates(name, {"q22": THESIS_Q22}, sites, noise)
        assert rmse(stalled - EMITTER) > 3 * bound, rmse(stalled - EMITTER)


JAM_SITES = np.array([[0.0, 0.0], [10e3, 0.0], [20e3, 0.0]])
JAM = {"q22": THESIS_Q22, "sigma": SIGMA, "imm_sigma2": 0.25, "imm_p": 0.3}   # the jammed-df [tracker] table
#: the filters compared: label -> (method, extra config)
JAM_FILTERS = {
    "EKF-ipu": ("EKF", {"init": "ipu"}),
    "EKF-robust": ("EKF", {"init": "robust"}),
    "IMM-sym-ipu": ("IMM", {"init": "ipu", "imm_transition": "symmetric"}),
    "IMM-iid-ipu": ("IMM", {"init": "ipu", "imm_transition": "iid"}),
    "IMM-sym-robust": ("IMM", {"init": "robust", "imm_transition": "symmetric"}),
    "IMM-iid-robust": ("IMM", {"init": "robust", "imm_transition": "iid"}),
}


def jammed_noise(seed: int, law: str) -> np.ndarray:
    return contaminated(np.random.default_rng(seed), SIGMA, 0.25, 0.3, (RUNS, EPOCHS, 3), law=law)


def jammed_misses(noise, labels=tuple(JAM_FILTERS)) -> dict[str, np.ndarray]:
    """Final position errors (runs × 2, m) of the filters ``labels`` on ``noise``."""
    out = {}
    for label in labels:
        name, extra = JAM_FILTERS[label]
        out[label] = final_estimates(name, {**JAM, **extra}, JAM_SITES, noise)[0] - EMITTER
    return out


def _criteria(misses: dict[str, np.ndarray]) -> dict[str, tuple[float, float]]:
    """Each check as ``name -> (IMM value, EKF value)``; a check passes when the IMM's
    value is at most 0.7 times the EKF's. RMS of the final miss with the robust start
    (against the EKF started either way); median miss with either start."""
    rms = {k: rmse(v) for k, v in misses.items()}
    med = {k: float(np.median(np.hypot(*v.T))) for k, v in misses.items()}
    out = {}
    for form in ("sym", "iid"):
        for ekf in ("EKF-robust", "EKF-ipu"):
            if ekf in rms:
                out[f"RMS IMM-{form}-robust vs {ekf}"] = (rms[f"IMM-{form}-robust"], rms[ekf])
        for init in ("ipu", "robust"):
            if f"IMM-{form}-{init}" in med and f"EKF-{init}" in med:
                out[f"median IMM-{form}-{init} vs EKF-{init}"] = (med[f"IMM-{form}-{init}"], med[f"EKF-{init}"])
    return out


def _assert_criteria(misses):
    checks = _criteria(misses)
    failed = {k: v for k, v in checks.items() if not v[0] <= 0.7 * v[1]}
    assert not failed, failed


# One test per outlier law computes everything it asserts, so that no Monte Carlo is run
# twice when the tests are spread over several workers.
def test_imm_rms_at_least_30_percent_below_ekf_under_laplacian_jamming():
    # The acceptance, with both filters started by the robust initialiser (the fair
    # comparison), and also against the EKF as the theses start it; plus the typical run
    # (median miss), however both are started: the IMM discounts the outliers the EKF
    # swallows. Offline, seeds 1-10: RMS ratio 0.13-0.18 (both forms, both laws).
    _assert_criteria(jammed_misses(jammed_noise(1, "laplacian")))


def test_imm_rms_at_least_30_percent_below_ekf_under_uniform_jamming():
    _assert_criteria(jammed_misses(jammed_noise(1, "uniform"), ("EKF-robust", "IMM-sym-robust", "IMM-iid-robust")))


def _seeds(text: str) -> list[int]:
    out = []
    for part in text.split(","):
        a, _, b = part.partition("-")
        out += list(range(int(a), int(b or a) + 1))
    return out


def main(argv=None) -> None:
    """Per-seed RMS table of the jamming comparison (the offline check of the tests)."""
    import argparse

    ap = argparse.ArgumentParser(description=main.__doc__)
    ap.add_argument("--seeds", default="1-10", help="e.g. 1-10 or 1,4,7")
    ap.add_argument("--laws", nargs="+", default=["laplacian", "uniform"])
    args = ap.parse_args(argv)
    labels = list(JAM_FILTERS)
    print(f"RMS of the final miss (m), {RUNS} runs x {EPOCHS} epochs, p = 0.3, sigma2 = 0.25 rad")
    print(f"{'law':10s}{'seed':>5s}" + "".join(f"{k:>15s}" for k in labels))
    passes: dict[str, list[bool]] = {}
    for law in args.laws:
        for seed in _seeds(args.seeds):
            misses = jammed_misses(jammed_noise(seed, law))
            print(f"{law:10s}{seed:5d}" + "".join(f"{rmse(misses[k]):15.0f}" for k in labels), flush=True)
            checks = _criteria(misses)
            for form in ("sym", "iid"):  # and the thesis's start for both filters
                checks[f"RMS IMM-{form}-ipu vs EKF-ipu"] = (rmse(misses[f"IMM-{form}-ipu"]), rmse(misses["EKF-ipu"]))
            for k, (imm, ekf) in checks.items():
                passes.setdefault(f"{law:10s} {k}", []).append(imm <= 0.7 * ekf)
    print("\nIMM <= 0.7 x EKF, seeds passing:")
    for k, v in passes.items():
        print(f"  {k:50s} {sum(v)}/{len(v)}")


if __name__ == "__main__":
    main()
