"""fusion.pda: the weighted (PDA) update of each filter — against the moment-matched
mixture of its hypotheses (EKF, UKF; the IMM's over models and associations), its
reductions, and Stone Soup's PDAUpdater (test-only reference) on a linear position model
and on the spherical (azimuth, elevation, range) model."""

from __future__ import annotations

import datetime

import numpy as np
import pytest
from stonesoup.base import Property
from stonesoup.models.measurement.linear import LinearGaussian
from stonesoup.models.measurement.nonlinear import NonLinearGaussianMeasurement
from stonesoup.types.array import CovarianceMatrix, StateVector
from stonesoup.types.detection import Detection, MissedDetection
from stonesoup.types.hypothesis import SingleProbabilityHypothesis
from stonesoup.types.multihypothesis import MultipleHypothesis
from stonesoup.types.prediction import GaussianStatePrediction
from stonesoup.updater.probability import PDAUpdater

from fusion import kalman
from fusion.measurement.models import SphericalModel
from fusion.ekf import ekf_update_weighted
from fusion.motion import make_motion
from fusion.patent import TrackerConfig
from fusion.pda import pda_moments
from fusion.ukf import TrackUKF

T0 = datetime.datetime(2026, 1, 1)


class PositionModel:
    """``z = p + noise`` (``H = [I₃ 0]``): a linear model with the measurement-model interface."""

    angles = np.zeros(3, dtype=bool)

    def __init__(self, std, n_x=9):
        self.n_z, self.n_x = 3, n_x
        self.R = np.diag(np.asarray(std, dtype=float) ** 2)
        self.H = np.eye(3, n_x)

    def h(self, x):
        return self.H @ x

    def jacobian(self, x):
        return self.H

    def innovation_and_jacobian(self, z, x):
        return np.asarray(z, dtype=float) - self.H @ x, self.H


def _prior(rng, n_x=9):
    x = np.r_[rng.normal(size=3) * 2e3 + np.array([3e3, 20e3, 5e3]), rng.normal(size=3) * 100, rng.normal(size=3)]
    A = rng.normal(size=(n_x, n_x))
    P = A @ A.T + np.diag(np.r_[[400.0] * 3, [100.0] * 3, [1.0] * 3])
    return x, P


def _weights(rng, m):
    w = rng.dirichlet(np.ones(m + 1))
    return w[1:], float(w[0])


def _models():
    return [PositionModel([30.0, 30.0, 50.0]),
            SphericalModel(("az", "el", "range"), [100.0, -300.0, 20.0], [2e-3, 2e-3, 25.0], 9)]


def _plots(rng, model, x, m):
    z = model.h(x)
    std = np.sqrt(np.diag(model.R))
    return z + rng.normal(size=(m, model.n_z)) * std * 2.0


@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize("which", [0, 1], ids=["position", "spherical"])
def test_the_weighted_update_is_the_moment_matched_mixture_of_its_hypotheses(seed, which):
    """Mean and covariance of β₀ N(x⁻, P⁻) + Σ βⱼ N(x⁻ + K νⱼ, Pᶜ), each hypothesis the
    filter's own update with one plot (kalman.update), moment-matched
    (kalman.gaussian_mixture): equal to 1e-9."""
    rng = np.random.default_rng(seed)
    model = _models()[which]
    x, P = _prior(rng)
    Z = _plots(rng, model, x, m=1 + seed % 4)
    beta, beta0 = _weights(rng, len(Z))
    got, _ = ekf_update_weighted(model, x, P, Z, beta, beta0)
    singles = [kalman.update(x, P, *model.innovation_and_jacobian(z, x), model.R) for z in Z]
    mean, cov = kalman.gaussian_mixture(np.r_[beta0, beta], np.array([x, *(s.x for s in singles)]),
                                        np.array([P, *(s.P for s in singles)]))
    scale = np.abs(cov).max()
    np.testing.assert_allclose(got.x, mean, rtol=0, atol=1e-9 * np.abs(mean).max())
    np.testing.assert_allclose(got.P, cov, rtol=0, atol=1e-9 * scale)
    assert np.all(np.linalg.eigvalsh(got.P) > 0)


def test_one_sure_plot_is_the_filter_s_update_and_a_sure_miss_the_prediction():
    rng = np.random.default_rng(7)
    model = _models()[1]
    x, P = _prior(rng)
    Z = _plots(rng, model, x, 3)
    own = kalman.update(x, P, *model.innovation_and_jacobian(Z[1], x), model.R)
    sure, _ = ekf_update_weighted(model, x, P, Z, [0.0, 1.0, 0.0], 0.0)
    np.testing.assert_allclose(sure.x, own.x, rtol=1e-12)
    np.testing.assert_allclose(sure.P, own.P, rtol=0, atol=1e-12 * np.abs(P).max())
    miss, _ = ekf_update_weighted(model, x, P, Z, [0.0, 0.0, 0.0], 1.0)
    np.testing.assert_array_equal(miss.x, x)
    np.testing.assert_allclose(miss.P, P, rtol=0, atol=1e-12 * np.abs(P).max())
    with pytest.raises(ValueError, match="sum to 1"):
        ekf_update_weighted(model, x, P, Z, [0.2, 0.2, 0.2], 0.2)


def test_the_spread_term_is_what_widens_the_covariance():
    """Two plots either side of the prediction, equal weights: ν̄ = 0, so the mean does
    not move, and P⁺ − (β₀P⁻ + (1 − β₀)Pᶜ) is K Σβνν K ᵀ, positive semi-definite and
    not zero; pda_moments without it (one plot at ν̄) is narrower."""
    model = PositionModel([10.0, 10.0, 10.0])
    x, P = np.zeros(9), np.eye(9) * 100.0
    Z = np.array([[50.0, 0.0, 0.0], [-50.0, 0.0, 0.0]])
    got, _ = ekf_update_weighted(model, x, P, Z, [0.4, 0.4], 0.2)
    np.testing.assert_allclose(got.nu, 0.0, atol=1e-12)
    np.testing.assert_allclose(got.x, x, atol=1e-12)
    base = 0.2 * P + 0.8 * kalman.update(x, P, np.zeros(3), model.H, model.R).P
    extra = np.linalg.eigvalsh(got.P - base)
    assert extra.min() > -1e-9 and extra.max() > 100.0
    _, narrower, _ = pda_moments(x, P, got.K, base, np.zeros((1, 3)), [0.8], 0.2)
    assert np.trace(narrower) < np.trace(got.P) - 100.0


# Stone Soup's PDAUpdater ---------------------------------------------------------------------
class _Spherical(NonLinearGaussianMeasurement):
    """zfusion's spherical model as a Stone Soup measurement model (the same h and its
    analytic Jacobian), so that the two updaters linearise alike."""

    model: object = Property(doc="a fusion.measurement.models.SphericalModel")

    @property
    def ndim_meas(self) -> int:
        return self.model.n_z

    def function(self, state, noise=False, **kwargs):
        return StateVector(self.model.h(np.asarray(state.state_vector, dtype=float).ravel()))

    def jacobian(self, state, **kwargs):
        return self.model.jacobian(np.asarray(state.state_vector, dtype=float).ravel())


def _stone_soup(model, x, P, Z, beta, beta0):
    if isinstance(model, PositionModel):
        ss_model = LinearGaussian(ndim_state=9, mapping=(0, 1, 2), noise_covar=CovarianceMatrix(model.R))
    else:
        ss_model = _Spherical(ndim_state=9, mapping=tuple(range(9)), noise_covar=CovarianceMatrix(model.R), model=model)
    updater = PDAUpdater(ss_model)
    prediction = GaussianStatePrediction(StateVector(x), CovarianceMatrix(P), timestamp=T0)
    zhat = updater.predict_measurement(prediction, measurement_model=ss_model)
    hyps = [SingleProbabilityHypothesis(prediction, MissedDetection(timestamp=T0), beta0)]
    for z, b in zip(Z, beta):
        det = Detection(StateVector(z), timestamp=T0, measurement_model=ss_model)
        hyps.append(SingleProbabilityHypothesis(prediction, det, b, measurement_prediction=zhat))
    post = updater.update(MultipleHypothesis(hyps, normalise=False))
    return np.asarray(post.state_vector, dtype=float).ravel(), np.asarray(post.covar, dtype=float)


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("which", [0, 1], ids=["position", "spherical"])
def test_the_weighted_update_is_stone_soup_s_pda_update(seed, which):
    """The same prediction, plots and weights through Stone Soup's PDAUpdater (its EKF,
    P − KSKᵀ) and ours (Joseph form): the posterior to 1e-9."""
    rng = np.random.default_rng(100 + seed)
    model = _models()[which]
    x, P = _prior(rng)
    Z = _plots(rng, model, x, m=2 + seed % 3)
    beta, beta0 = _weights(rng, len(Z))
    got, _ = ekf_update_weighted(model, x, P, Z, beta, beta0)
    x_ss, P_ss = _stone_soup(model, x, P, Z, beta, beta0)
    np.testing.assert_allclose(got.x, x_ss, rtol=0, atol=1e-9 * np.abs(x_ss).max())
    np.testing.assert_allclose(got.P, P_ss, rtol=0, atol=1e-9 * np.abs(P_ss).max())


# The UKF's and the IMM's weighted updates ---------------------------------------------------
def _ukf(x, P):
    return TrackUKF(make_motion("ca", 1.0), x, P, 0.0)


@pytest.mark.parametrize("seed", range(4))
def test_the_ukf_s_weighted_update_is_the_mixture_of_its_own_updates(seed):
    """The UKF on the spherical model: β₀ N(x⁻, P⁻) + Σ βⱼ (its update with plot j alone),
    moment-matched, to 1e-9; its innovations are those its updates use."""
    rng = np.random.default_rng(200 + seed)
    model = _models()[1]
    x, P = _prior(rng)
    Z = _plots(rng, model, x, m=1 + seed)
    beta, beta0 = _weights(rng, len(Z))
    singles = [_ukf(x, P) for _ in Z]
    results = [f.update(model, z) for f, z in zip(singles, Z)]
    nus, S = _ukf(x, P).innovations(model, Z)
    np.testing.assert_allclose(nus, [r.nu for r in results], rtol=0, atol=1e-12)
    np.testing.assert_allclose(S, results[0].S, rtol=1e-12)
    mean, cov = kalman.gaussian_mixture(np.r_[beta0, beta], np.array([x, *(f.x for f in singles)]),
                                        np.array([P, *(f.P for f in singles)]))
    f = _ukf(x, P)
    f.update_weighted(model, Z, beta, beta0)
    np.testing.assert_allclose(f.x, mean, rtol=0, atol=1e-9 * np.abs(mean).max())
    np.testing.assert_allclose(f.P, cov, rtol=0, atol=1e-9 * np.abs(cov).max())


def _imm(x, P):
    cfg = TrackerConfig.from_dict({"motion": "imm"})
    f = cfg.new_filter(cfg.motion_model())(x, P, 0.0)
    f.predict(1.0)  # mixed: the models' predictions differ, c̄ is not μ₀
    return f


@pytest.mark.parametrize("seed", range(4))
def test_the_imm_s_weighted_update_is_the_joint_posterior_over_models_and_associations(seed):
    """IMM (cv, ct, ca; EKFs), the spherical model. Brute force over every (model j,
    association i) hypothesis: weight c̄ⱼ β₀ for "none" (model j's prediction), c̄ⱼ βᵢ
    Nᵢⱼ / N̄ᵢ for plot i (model j's EKF update with it alone), N̄ᵢ = Σⱼ c̄ⱼ Nᵢⱼ. The mode
    probabilities are each model's total weight (1e-12) and the track's Gaussian the
    moment-matched mixture of all of them (1e-9)."""
    rng = np.random.default_rng(300 + seed)
    model = _models()[1]
    x, P = _prior(rng)
    imm = _imm(x, P)
    Z = _plots(rng, model, imm.x, m=1 + seed)
    beta, beta0 = _weights(rng, len(Z))
    cbar = imm.mu.copy()
    weights, means, covs = [], [], []
    for j, fj in enumerate(imm.filters):
        N = np.array([np.exp(kalman.gaussian_loglikelihood(nu, S)) for nu, S in
                      [(model.innovation_and_jacobian(z, fj.x)[0], fj.innovations(model, Z)[1]) for z in Z]])
        weights.append(cbar[j] * beta0), means.append(fj.x), covs.append(fj.P)
        for i, z in enumerate(Z):
            Nbar = sum(cbar[k] * np.exp(kalman.gaussian_loglikelihood(*_one(model, fk, z))) for k, fk in enumerate(imm.filters))
            one = kalman.update(fj.x, fj.P, *model.innovation_and_jacobian(z, fj.x), model.R)
            weights.append(cbar[j] * beta[i] * N[i] / Nbar), means.append(one.x), covs.append(one.P)
    weights = np.array(weights)
    mean, cov = kalman.gaussian_mixture(weights / weights.sum(), np.array(means), np.array(covs))
    mu = weights.reshape(len(imm.filters), len(Z) + 1).sum(axis=1)
    imm.update_weighted(model, Z, beta, beta0)
    assert weights.sum() == pytest.approx(1.0, abs=1e-12)
    np.testing.assert_allclose(imm.mu, mu, rtol=0, atol=1e-12)
    np.testing.assert_allclose(imm.x, mean, rtol=0, atol=1e-9 * np.abs(mean).max())
    np.testing.assert_allclose(imm.P, cov, rtol=0, atol=1e-9 * np.abs(cov).max())


def _one(model, f, z):
    nu, H = model.innovation_and_jacobian(z, f.x)
    return nu, H @ f.P @ H.T + model.R


def test_the_imm_s_weighted_update_reduces_to_its_update_and_to_nothing():
    """One sure plot: the IMM's own update (μ, x, P); a sure miss: nothing changes."""
    rng = np.random.default_rng(9)
    model = _models()[1]
    x, P = _prior(rng)
    a, b, c = _imm(x, P), _imm(x, P), _imm(x, P)
    z = _plots(rng, model, a.x, 1)
    a.update(model, z[0])
    b.update_weighted(model, z, [1.0], 0.0)
    np.testing.assert_allclose(b.mu, a.mu, rtol=0, atol=1e-12)
    np.testing.assert_allclose(b.x, a.x, rtol=0, atol=1e-9 * np.abs(a.x).max())
    np.testing.assert_allclose(b.P, a.P, rtol=0, atol=1e-9 * np.abs(a.P).max())
    mu, x0, P0 = c.mu.copy(), c.x.copy(), c.P.copy()
    c.update_weighted(model, z, [0.0], 1.0)
    np.testing.assert_allclose(c.mu, mu, rtol=0, atol=1e-15)
    np.testing.assert_allclose(c.x, x0, rtol=0, atol=1e-9 * np.abs(x0).max())
    np.testing.assert_allclose(c.P, P0, rtol=0, atol=1e-9 * np.abs(P0).max())
