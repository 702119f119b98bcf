"""Robust initialisation of the recursive DF filters (fusion.df.init, config ``init``),
and the log-domain Gaussian likelihood the IMM uses."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import multivariate_normal, norm

from fusion.df import make
from fusion.df.filters import BearingEKF
from fusion.df.imm import BearingIMM, log_likelihood, transition_matrix
from fusion.df.init import mixture_loglik, ranked_pairs, robust_pair, usable_pairs
from fusion.df.methods import DFConfig
from fusion.df.models import bearing, bearing_measurements, bearing_of, emitter_Q
from fusion.df.noise import contaminated, gaussian
from fusion.df.triangulation import GeometryError, ipu
from fusion.kalman import gaussian_likelihood, gaussian_loglikelihood, update

EMITTER = np.array([15e3, 15e3])
SITES = np.array([[0.0, 0.0], [10e3, 0.0], [20e3, 0.0]])
SIGMA, SIGMA2, P_OUT = 0.0175, 0.25, 0.3
CFG = {"sigma": SIGMA, "imm_sigma2": SIGMA2, "imm_p": P_OUT}


def stream(noise, sites=SITES, emitter=EMITTER):
    sensors = [f"DF{i + 1}" for i in range(len(sites))]
    beta = bearing(emitter, sites) + noise
    return bearing_measurements(1.0 + np.arange(noise.shape[0], dtype=float), sensors, sites, beta, SIGMA)


def run(method, ms, watermarks=None):
    out = []
    for i, m in enumerate(ms):
        out += method.process(m)
        if watermarks is not None:
            t_next = ms[i + 1].t if i + 1 < len(ms) else 1e9
            out += method.advance(watermarks(t_next))
    return out + method.finish()


# -- gaussian_loglikelihood (fusion.kalman) -------------------------------------------------

@pytest.mark.parametrize("dim", [1, 2, 3])
def test_gaussian_loglikelihood_equals_scipy_logpdf(dim):
    rng = np.random.default_rng(dim)
    for scale in (1e-6, 1.0, 1e4):
        A = rng.standard_normal((dim, dim))
        S = scale * (A @ A.T + dim * np.eye(dim))
        for k in (0.0, 1.0, 10.0, 1e3):  # up to ~1000 σ: the density itself is 0.0 there
            nu = k * np.sqrt(scale) * rng.standard_normal(dim)
            ref = multivariate_normal(mean=np.zeros(dim), cov=S).logpdf(nu)
            assert gaussian_loglikelihood(nu, S) == pytest.approx(ref, rel=1e-10, abs=1e-9)


def test_gaussian_loglikelihood_is_finite_where_the_likelihood_underflows():
    nu, S = np.array([0.5]), np.array([[1e-6]])  # 500 σ
    assert gaussian_likelihood(nu, S) == 0.0
    ll = gaussian_loglikelihood(nu, S)
    assert np.isfinite(ll) and ll == pytest.approx(norm.logpdf(0.5, scale=1e-3), rel=1e-12)
    assert gaussian_loglikelihood(np.array([0.1]), np.array([[0.04]])) == pytest.approx(
        np.log(gaussian_likelihood(np.array([0.1]), np.array([[0.04]]))), rel=1e-12)
    for S in (np.diag([1.0, -1.0]), np.array([[0.0]]), np.array([[-1.0]])):
        with pytest.raises(np.linalg.LinAlgError):
            gaussian_loglikelihood(np.ones(len(S)), S)


def test_imm_log_likelihood_uses_the_log_domain_helper():
    res = update(np.zeros(2), np.eye(2), np.array([40.0]), np.array([[1.0, 0.0]]), np.array([[1e-4]]))
    assert gaussian_likelihood(res.nu, res.S) == 0.0
    assert log_likelihood(res) == pytest.approx(norm.logpdf(40.0, scale=np.sqrt(res.S[0, 0])), rel=1e-12)


def test_imm_mode_probabilities_stay_a_distribution_when_every_likelihood_underflows():
    site = np.array([0.0, 0.0])
    P = np.eye(2)
    for form in ("symmetric", "iid"):
        imm = BearingIMM([EMITTER, EMITTER], [P, P], np.zeros((2, 2)), transition_matrix(0.3, form), [0.95, 0.05])
        for _ in range(3):  # 2.5 rad off: NIS ~ 6e10 under model 1 and ~6e4 under model 2
            imm.step(site, bearing(EMITTER, site) + 2.5, (1e-5, 0.01))
            assert np.all(np.isfinite(imm.mu)) and imm.mu.sum() == pytest.approx(1.0)
            assert imm.mu[1] == pytest.approx(1.0)
        assert np.all(np.isfinite(imm.x)) and np.all(np.isfinite(imm.P))


# -- the initialiser (fusion.df.init) ---------------------------------------------------------

def _window(noise):
    """Bearings of the first epochs (rows of ``noise``) as flat (sites, betas, sigmas)."""
    n_ep = noise.shape[0]
    sites = np.tile(SITES, (n_ep, 1))
    betas = (bearing(EMITTER, SITES) + noise).ravel()
    return sites, betas, np.full(betas.shape, SIGMA)


def test_mixture_loglik_is_the_sum_of_log_mixture_densities():
    rng = np.random.default_rng(3)
    sites, betas, sigmas = _window(contaminated(rng, SIGMA, SIGMA2, P_OUT, (4, 3)))
    x = EMITTER + [300.0, -200.0]
    r = betas - bearing(x, sites)
    ref = np.sum(np.log((1 - P_OUT) * norm.pdf(r, scale=SIGMA) + P_OUT * norm.pdf(r, scale=SIGMA2)))
    assert mixture_loglik(x, sites, betas, sigmas, P_OUT, SIGMA2) == pytest.approx(ref, rel=1e-12)
    xs = EMITTER + rng.normal(0, 2e3, (5, 2))
    np.testing.assert_allclose(mixture_loglik(xs, sites, betas, sigmas, P_OUT, SIGMA2),
                               [mixture_loglik(v, sites, betas, sigmas, P_OUT, SIGMA2) for v in xs], rtol=1e-12)
    # far off every bearing: finite (log domain), and residuals are wrapped (β + 2π is β)
    far = np.array([-50e3, -50e3])
    assert np.isfinite(mixture_loglik(far, sites, betas, sigmas, P_OUT, 1e-3))
    assert mixture_loglik(x, sites, betas + 2 * np.pi, sigmas, P_OUT, SIGMA2) == pytest.approx(ref, rel=1e-12)
    for bad in (0.0, 1.0):
        with pytest.raises(ValueError, match="p must be"):
            mixture_loglik(x, sites, betas, sigmas, bad, SIGMA2)


def test_usable_pairs_are_the_ipu_fixes_the_ipu_initialisation_accepts():
    rng = np.random.default_rng(5)
    sites, betas, sigmas = _window(gaussian(rng, SIGMA, (2, 3)))
    sites = np.vstack([sites, [[40e3, 0.0]]])      # a 7th bearing pointing away: diverges from all
    betas = np.append(betas, -np.pi / 2)
    sigmas = np.append(sigmas, SIGMA)
    i, j, x = usable_pairs(sites, betas, sigmas)
    pairs = set(zip(i.tolist(), j.tolist()))
    assert not any(a % 3 == b % 3 and max(a, b) < 6 for a, b in pairs)   # never one site twice
    assert not any(6 in pr for pr in pairs)                               # nor the diverging bearing
    for a, b, xa in zip(i, j, x):
        np.testing.assert_allclose(xa, ipu(sites[a], betas[a], SIGMA, sites[b], betas[b], SIGMA)[0], rtol=1e-9)
    # the conditioning test is the ipu one: EKF with ipu refuses a 0.2° crossing at σ = 1°
    half = 20e3 * np.tan(np.radians(0.1))
    s2, b2 = np.array([[-half, 0.0], [half, 0.0]]), np.array([np.pi / 2 - np.radians(0.1), np.pi / 2 + np.radians(0.1)])
    assert len(usable_pairs(s2, b2, [SIGMA, SIGMA])[0]) == 0
    assert len(usable_pairs(s2, b2, [SIGMA, SIGMA], max_rel=0.0)[0]) == 1
    with pytest.raises(GeometryError):
        robust_pair(s2, b2, [SIGMA, SIGMA], P_OUT, SIGMA2)


def test_robust_pair_avoids_outliers_in_the_first_bearings():
    noise = np.zeros((5, 3))
    noise[0, 0], noise[0, 1] = 0.3, -0.2        # the thesis's ipu pair: both jammed
    noise[2, 2] = 0.25
    sites, betas, sigmas = _window(noise)
    choice = robust_pair(sites, betas, sigmas, P_OUT, SIGMA2)
    assert choice.i not in (0, 1, 8) and choice.j not in (0, 1, 8)
    np.testing.assert_allclose(choice.x, EMITTER, atol=1e-6)
    ranked = ranked_pairs(sites, betas, sigmas, P_OUT, SIGMA2)
    assert (ranked[0].i, ranked[0].j) == (choice.i, choice.j) and len(ranked) == choice.n_candidates
    assert [c.loglik for c in ranked] == sorted((c.loglik for c in ranked), reverse=True)
    jammed = [c for c in ranked if {c.i, c.j} & {0, 1, 8}]
    assert jammed and all(c.loglik < choice.loglik for c in jammed)


def test_robust_pair_picks_a_clean_pair_in_most_jammed_windows():
    # the window's job, over many random 5-epoch windows at p = 0.3: how often the chosen
    # pair holds a harmful bearing (error > 3σ₁; a Laplacian outlier is often smaller, and
    # then harmless), against how often the thesis's first pair does (~40 %). Offline,
    # 4000 windows: 12 % with a 2-epoch window, 3.8 % with 3, 0.4 % with 5, 0 with 10.
    rng = np.random.default_rng(11)
    n, bad_first, bad_robust = 400, 0, 0
    for _ in range(n):
        noise = contaminated(rng, SIGMA, SIGMA2, P_OUT, (5, 3))
        sites, betas, sigmas = _window(noise)
        c = robust_pair(sites, betas, sigmas, P_OUT, SIGMA2)
        harmful = np.abs(noise.ravel()) > 3 * SIGMA
        bad_robust += bool(harmful[c.i] or harmful[c.j])
        bad_first += bool(harmful[0] or harmful[1])
    assert bad_first / n > 0.3
    assert bad_robust / n < 0.02, bad_robust / n


# -- the streaming methods with init = "robust" -----------------------------------------------

def test_config_keys_and_default():
    assert (DFConfig().init, DFConfig().init_epochs) == ("ipu", 5)
    assert DFConfig.from_dict({"init": "robust", "init_epochs": 3}).init == "robust"
    for cfg, key in [({"init": "ransac"}, "init"), ({"init": 1}, "init"), ({"init_epochs": 0}, "init_epochs"),
                     ({"init_epochs": 2.5}, "init_epochs"), ({"init_epochs": True}, "init_epochs")]:
        with pytest.raises(ValueError, match=key):
            make("IMM", cfg)


@pytest.mark.parametrize("name", ["EKF", "MEKF2", "IMM"])
def test_robust_with_one_pair_per_window_is_ipu(name):
    # two stations, one epoch in the window: the only pair is the thesis's first pair
    rng = np.random.default_rng(2)
    ms = stream(gaussian(rng, SIGMA, (10, 2)), sites=SITES[[0, 2]])
    a = run(make(name, {}), ms)
    b = run(make(name, {"init": "robust", "init_epochs": 1}), ms)
    assert len(a) == len(b) == 10
    for ea, eb in zip(a, b):
        np.testing.assert_array_equal(ea.x, eb.x)
        np.testing.assert_array_equal(ea.P, eb.P)
        assert ea.nis == eb.nis and ea.extra == eb.extra


def _bearings(ms):
    return [(*bearing_of(m), SIGMA) for m in ms]


@pytest.mark.parametrize("K", [1, 3, 5])
def test_robust_init_is_the_chosen_pair_then_every_other_bearing_in_order(K):
    rng = np.random.default_rng(40 + K)
    n_ep = 12
    ms = stream(contaminated(rng, SIGMA, SIGMA2, P_OUT, (n_ep, 3)))
    cfg = {**CFG, "init": "robust", "init_epochs": K}
    out = run(make("EKF", cfg), ms)
    assert len(out) == n_ep
    b = _bearings(ms)
    c = DFConfig.from_dict(cfg)
    # by hand: the window's best pair, its ipu, then every other bearing in arrival order
    for k in range(1, n_ep + 1):
        window = b[:3 * min(k, K)]
        choice = robust_pair(np.array([w[0] for w in window]), np.array([w[1] for w in window]),
                             np.full(len(window), SIGMA), P_OUT, SIGMA2)
        x0, P0 = ipu(b[choice.i][0], b[choice.i][1], SIGMA, b[choice.j][0], b[choice.j][1], SIGMA)
        ekf = BearingEKF(x0, P0, emitter_Q(c.q22, c.q11))
        for idx, (site, beta, s) in enumerate(b[:3 * k]):
            if idx not in (choice.i, choice.j):
                ekf.step(site, beta, s)
        np.testing.assert_allclose(out[k - 1].x, ekf.x, rtol=1e-12)
        np.testing.assert_allclose(out[k - 1].P, ekf.P, rtol=1e-9)
        assert out[k - 1].extra["n_bearings"] == 3 * k


def test_provisional_outputs_are_the_same_estimator_on_fewer_epochs():
    rng = np.random.default_rng(9)
    ms = stream(contaminated(rng, SIGMA, SIGMA2, P_OUT, (8, 3)))
    cfg = {**CFG, "init": "robust", "init_epochs": 5, "imm_transition": "iid"}
    full = run(make("IMM", cfg), ms)
    for k in range(1, 6):
        short = run(make("IMM", cfg), ms[:3 * k])
        np.testing.assert_array_equal(short[-1].x, full[k - 1].x)
        np.testing.assert_array_equal(short[-1].P, full[k - 1].P)


@pytest.mark.parametrize("name", ["EKF", "MEKF1", "IMM"])
def test_robust_output_does_not_depend_on_watermarks(name):
    rng = np.random.default_rng(21)
    ms = stream(contaminated(rng, SIGMA, SIGMA2, P_OUT, (8, 3)))
    cfg = {**CFG, "init": "robust", "init_epochs": 3}
    plain = run(make(name, cfg), ms)
    eager = run(make(name, cfg), ms, watermarks=lambda t_next: np.nextafter(t_next, -np.inf))
    lagging = run(make(name, cfg), ms, watermarks=lambda t_next: t_next - rng.uniform(1e-9, 2.5))
    assert len(plain) == 8
    for a, b, c in zip(plain, eager, lagging):
        np.testing.assert_array_equal(a.x, b.x)
        np.testing.assert_array_equal(a.x, c.x)


def test_robust_init_waits_for_a_usable_pair_like_ipu():
    # a single moving observer: the first epoch has no pair, the second has one
    k = np.arange(9)
    path = np.column_stack([130e3 + 30e3 * k, 11e3 + 30e3 * k])
    emitter = np.array([141e3, 141e3])
    ms = bearing_measurements(1.0 + k, ["AC"], path[:, None, :], bearing(emitter, path)[:, None], SIGMA)
    for name in ("EKF", "IMM"):
        out = run(make(name, {"q22": 0.0, "init": "robust", "init_epochs": 4}), ms)
        assert len(out) == 8 and out[0].t == ms[1].t
        np.testing.assert_allclose(out[-1].x, emitter, atol=1e-3)


def test_jammed_first_pair_robust_start_is_near_the_emitter():
    noise = gaussian(np.random.default_rng(6), SIGMA, (10, 3))
    noise[0, 0], noise[0, 1] = 0.2, -0.15          # DF1 and DF2 jammed in the first epoch
    ms = stream(noise)
    ipu_start = run(make("IMM", CFG), ms)[0]
    robust = run(make("IMM", {**CFG, "init": "robust", "init_epochs": 3}), ms)
    assert np.linalg.norm(ipu_start.x - EMITTER) > 2e3
    assert np.linalg.norm(robust[2].x - EMITTER) < 1e3     # once the window is closed
    assert np.linalg.norm(robust[-1].x - EMITTER) < 500.0


def test_window_without_a_pair_stays_open_until_the_first_usable_pair():
    # DF1 alone for 6 epochs (no fix), then DF1 + DF3: with a 3-epoch window the choice is
    # made once, at epoch 7, over all 8 bearings so far, and is final from then on
    rng = np.random.default_rng(12)
    noise = contaminated(rng, SIGMA, SIGMA2, P_OUT, (12, 2))
    ms = stream(noise, sites=SITES[[0, 2]])
    ms = [m for m in ms if m.sensor == "DF1" or m.t > 6.5]
    cfg = {**CFG, "init": "robust", "init_epochs": 3}
    out = run(make("EKF", cfg), ms)
    assert len(out) == 6 and out[0].t == 7.0
    b = _bearings(ms)
    c = DFConfig.from_dict(cfg)
    window = b[:8]
    choice = robust_pair(np.array([w[0] for w in window]), np.array([w[1] for w in window]),
                         np.full(8, SIGMA), P_OUT, SIGMA2)
    assert b[choice.j][0][0] == SITES[2, 0]  # a pair needs DF3
    x0, P0 = ipu(b[choice.i][0], b[choice.i][1], SIGMA, b[choice.j][0], b[choice.j][1], SIGMA)
    ekf = BearingEKF(x0, P0, emitter_Q(c.q22, c.q11))
    xs = []
    for idx, (site, beta, s) in enumerate(b):
        if idx not in (choice.i, choice.j):
            ekf.step(site, beta, s)
        if idx >= 7 and idx % 2 == 1:  # after each DF3 bearing: the end of an epoch
            xs.append(ekf.x.copy())
    np.testing.assert_allclose([e.x for e in out], xs, rtol=1e-12)
