"""OSPA/GOSPA against Stone Soup, the evaluation's aggregation against direct
computations, and the noise Fisher information against closed forms and Monte Carlo."""

from __future__ import annotations

import datetime
import itertools

import numpy as np
import pytest
from scipy import stats

from fusion.crb3d import effective_std, noise_fisher_information
from fusion.kalman import predict, update
from fusion.metrics import anees_series, chi2_bounds, gospa, median_point_distance, ospa
from fusion.types import Estimate
from services.summary import aggregate, method_summary

# OSPA / GOSPA ---------------------------------------------------------------------------


def _stonesoup(X, Y, c, p):
    from stonesoup.metricgenerator.ospametric import GOSPAMetric, OSPAMetric
    from stonesoup.types.state import State

    t = datetime.datetime(2020, 1, 1)
    xs = [State(np.asarray(x, float).reshape(-1, 1), timestamp=t) for x in X]
    ys = [State(np.asarray(y, float).reshape(-1, 1), timestamp=t) for y in Y]
    d_ospa = OSPAMetric(p=p, c=c).compute_OSPA_distance(xs, ys).value
    g = GOSPAMetric(p=p, c=c).compute_gospa_metric(xs, ys)[0].value
    return d_ospa, g


def _ospa_brute(X, Y, c, p):
    """OSPA by enumerating every assignment (the definition, for small sets)."""
    X, Y = (X, Y) if len(X) <= len(Y) else (Y, X)
    m, n = len(X), len(Y)
    best = min(sum(min(np.linalg.norm(X[i] - Y[j]), c) ** p for i, j in enumerate(perm))
               for perm in itertools.permutations(range(n), m))
    return ((best + c**p * (n - m)) / n) ** (1 / p)


CASES = [(50.0, 1.0), (20.0, 2.0), (100.0, 2.0), (10.0, 3.0), (30.0, 1.5), (5.0, 2.0)]


@pytest.mark.parametrize("seed", range(len(CASES)))
def test_ospa_and_gospa_equal_the_definition_and_stone_soup(seed):
    rng = np.random.default_rng(seed)
    c, p = CASES[seed]
    m, n = rng.integers(1, 6, size=2)
    X = rng.uniform(0, 60, size=(m, 2))
    Y = rng.uniform(0, 60, size=(n, 2))
    d_ospa, g = _stonesoup(X, Y, c, p)
    assert ospa(X, Y, c, p) == pytest.approx(_ospa_brute(X, Y, c, p), rel=1e-12)
    if p == 1.0:
        # Stone Soup 1.9 assigns on d rather than d^p, the same thing only for p = 1
        assert ospa(X, Y, c, p) == pytest.approx(d_ospa, rel=1e-12)
    else:
        assert ospa(X, Y, c, p) <= d_ospa + 1e-12  # the exact minimum is never above it
    mine = gospa(X, Y, c, p)
    assert mine.distance == pytest.approx(g["distance"], rel=1e-12, abs=1e-12)
    assert mine.localisation == pytest.approx(g["localisation"], rel=1e-12, abs=1e-9)
    assert mine.missed == pytest.approx(g["missed"], rel=1e-12, abs=1e-12)
    assert mine.false == pytest.approx(g["false"], rel=1e-12, abs=1e-12)


def test_ospa_gospa_closed_forms():
    X = np.array([[0.0, 0.0], [10.0, 0.0]])
    assert ospa(X, X, 5.0) == 0.0 and gospa(X, X, 5.0).distance == 0.0
    assert ospa([], [], 5.0) == 0.0
    assert ospa(X, [], 5.0) == 5.0  # all unmatched: the cut-off
    # one missed target out of two: ((0 + c^p)/2)^(1/p)
    assert ospa(X[:1], X, 4.0, 2.0) == pytest.approx(np.sqrt(16.0 / 2.0))
    # GOSPA (alpha = 2): a miss costs c^p/2; a pair further than c is a miss plus a false track
    g = gospa([[100.0, 0.0]], [[0.0, 0.0]], c=4.0, p=2.0)
    assert (g.n_missed, g.n_false) == (1, 1) and g.distance == pytest.approx(4.0)
    g = gospa([[3.0, 4.0]], [[0.0, 0.0]], c=10.0, p=1.0)
    assert (g.distance, g.localisation, g.n_missed) == (pytest.approx(5.0), pytest.approx(5.0), 0)
    with pytest.raises(ValueError):
        ospa(X, X, c=0.0)


# The evaluation's aggregation --------------------------------------------------------


def _linear_kf_runs(runs=60, steps=25, seed=11, scale=1.0):
    """A 2-state constant-velocity KF on linear-Gaussian position measurements, one run at a
    time, returned as Estimates (covariance scaled by ``scale``) and the truths."""
    rng = np.random.default_rng(seed)
    F = np.array([[1.0, 1.0], [0.0, 1.0]])
    Q = 0.05 * np.array([[1 / 3, 1 / 2], [1 / 2, 1.0]])
    H, R = np.array([[1.0, 0.0]]), np.array([[4.0]])
    P0 = np.diag([25.0, 4.0])
    all_est, all_truth = [], []
    for _ in range(runs):
        xt = rng.multivariate_normal([0.0, 1.0], P0)
        x, P = np.array([0.0, 1.0]), P0
        est, truth = [], []
        for k in range(1, steps + 1):
            xt = F @ xt + rng.multivariate_normal([0, 0], Q)
            z = H @ xt + 2.0 * rng.standard_normal(1)
            x, P = predict(x, P, F, Q)
            res = update(x, P, z - H @ x, H, R)
            x, P = res.x, res.P
            est.append(Estimate(float(k), x, scale * P, "KF", nis=res.nis, nis_dof=1))
            truth.append(xt.copy())
        all_est.append(est)
        all_truth.append(np.array(truth))
    return all_est, np.array(all_truth)


def test_aggregate_nees_of_a_linear_kf_is_its_dimension_and_rmse_is_direct():
    runs, truths = _linear_kf_runs()
    truth = lambda r, track, t: truths[r][int(round(t)) - 1]  # noqa: E731
    s = method_summary(runs, truth)
    # NEES: every estimate's eᵀP⁻¹e, recomputed here independently
    e = np.array([[est.x - truths[r][k] for k, est in enumerate(run)] for r, run in enumerate(runs)])
    P = np.array([[est.P for est in run] for run in runs])
    nees = np.einsum("rki,rkij,rkj->rk", e, np.linalg.inv(P), e)
    assert s["anees"] == pytest.approx(nees.mean(), rel=1e-10)
    assert s["series"]["anees"] == pytest.approx(nees.mean(axis=0).tolist(), rel=1e-10)
    # overall: N·T·ANEES ~ χ²(N·T·2) if the (weakly time-correlated) terms were independent
    lo, hi = chi2_bounds(2, e.shape[0] * e.shape[1], 0.99)
    assert lo <= s["anees"] <= hi
    # per step: most of the 60-run averages inside their 95 % interval
    avg, (lo, hi) = anees_series(nees, 2)
    assert np.mean((avg >= lo) & (avg <= hi)) >= 0.8
    assert s["anees_bounds"] == pytest.approx([lo, hi])
    # ANIS per dof ≈ 1 for the same filter
    assert 0.85 < s["anis_per_dof"] < 1.15
    # RMSE: 2-state "fix" (position block = both components, as for an emitter [px py])
    assert s["rmse_pos"] == pytest.approx(np.sqrt(np.mean(np.sum(e**2, axis=-1))), rel=1e-12)
    assert s["series"]["rmse_pos"] == pytest.approx(np.sqrt(np.mean(np.sum(e**2, axis=-1), axis=0)).tolist())
    assert s["final"]["rmse_pos"] == pytest.approx(np.sqrt(np.mean(np.sum(e[:, -1] ** 2, axis=-1))))
    # CEP of the final "fixes": the median miss; the thesis's statistic: the median point
    final = e[:, -1, :]
    assert s["cep50"] == pytest.approx(np.median(np.hypot(final[:, 0], final[:, 1])))
    assert s["median_point_distance"] == pytest.approx(float(np.hypot(*np.median(final, axis=0))))
    assert s["median_point_distance"] == pytest.approx(median_point_distance(final, [0.0, 0.0]))


def test_aggregate_catches_an_overconfident_covariance():
    runs, truths = _linear_kf_runs(scale=0.5)
    s = method_summary(runs, lambda r, track, t: truths[r][int(round(t)) - 1])
    lo, hi = s["anees_bounds"]
    assert s["anees"] > hi


def test_aggregate_3d_blocks_and_second_half():
    rng = np.random.default_rng(4)
    runs, truths = [], []
    for r in range(5):
        est, tru = [], []
        for k in range(11):
            xt = rng.normal(size=9)
            x = xt + rng.normal(size=9) * np.repeat([3.0, 2.0, 1.0], 3)
            est.append(Estimate(float(k), x, np.eye(9), "X"))
            tru.append(xt)
        runs.append(est)
        truths.append(tru)
    s = method_summary(runs, lambda r, track, t: truths[r][int(t)])
    e = np.array([[est.x - truths[r][k] for k, est in enumerate(run)] for r, run in enumerate(runs)])
    for key, sl in (("rmse_pos", slice(0, 3)), ("rmse_vel", slice(3, 6)), ("rmse_acc", slice(6, 9))):
        assert s[key] == pytest.approx(np.sqrt(np.mean(np.sum(e[..., sl] ** 2, axis=-1))))
        assert s["second_half"][key] == pytest.approx(np.sqrt(np.mean(np.sum(e[:, 5:, sl] ** 2, axis=-1))))
    assert s["second_half"]["from_t"] == 5.0
    assert s["cep50"] is None and s["median_point_distance"] is None
    assert s["nees_dof"] == 9 and s["anees"] == pytest.approx(np.mean(np.sum(e**2, axis=-1)))
    assert aggregate([])["rmse_pos"] is None


# Fisher information of the jamming mixtures --------------------------------------------


def test_noise_fisher_information_closed_forms():
    assert noise_fisher_information(0.02).info == pytest.approx(1 / 0.02**2)
    b = 0.25 / np.sqrt(2)
    assert noise_fisher_information(0.0175, 1.0, 0.25, "laplacian").info == pytest.approx(1 / b**2)
    # p -> 0 is continuous
    assert noise_fisher_information(0.0175, 1e-9, 0.25, "laplacian").info == pytest.approx(1 / 0.0175**2, rel=1e-6)
    assert effective_std(0.0175) == pytest.approx(0.0175)


@pytest.mark.parametrize("law", ["laplacian", "uniform"])
@pytest.mark.parametrize("p", [0.1, 0.5])
def test_noise_fisher_information_by_monte_carlo(law, p):
    """E[(∂ log f/∂v)²] by sampling the mixture, with the density built from scipy.stats
    and a central-difference score (an implementation independent of fusion.crb3d)."""
    s1, s2 = 0.0175, 0.25
    out = stats.laplace(scale=s2 / np.sqrt(2)) if law == "laplacian" else stats.uniform(-np.sqrt(3) * s2, 2 * np.sqrt(3) * s2)
    rng = np.random.default_rng(1)
    n = 400_000
    is_out = rng.random(n) < p
    v = np.where(is_out, out.rvs(size=n, random_state=rng), s1 * rng.standard_normal(n))

    def logf(x):
        return np.log((1 - p) * stats.norm.pdf(x, scale=s1) + p * out.pdf(x))

    h = 1e-7
    score = (logf(v + h) - logf(v - h)) / (2 * h)
    mc = np.mean(score**2)
    info = noise_fisher_information(s1, p, s2, law)
    assert info.info == pytest.approx(mc, rel=0.02)
    assert info.regular == (law == "laplacian")
    # I ≥ 1/Var for any density (equality only for a Gaussian)
    assert info.info > 1.0 / np.var(v)
