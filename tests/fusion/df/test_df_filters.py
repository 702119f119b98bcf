"""EKFT/EKFS/SKF, the cross-fed MEKF/MKF scheme, the IMM and the bearing smoothers."""

from __future__ import annotations

import numpy as np
import pytest
from filterpy.kalman import ExtendedKalmanFilter, IMMEstimator, KalmanFilter

from fusion.angles import wrap_pi
from fusion.df.filters import (
    MEKF,
    BearingEKF,
    CrossFed,
    SingularLinearisation,
    bearing_step,
    lin_ekfs,
    lin_ekft,
    lin_skf,
)
from fusion.df.imm import IMM, BearingIMM, log_likelihood, transition_matrix
from fusion.df.models import bearing, bearing_measurements
from fusion.df.smoothing import BearingSmoother, CrossFedBearingSmoother
from fusion.kalman import gaussian_likelihood, predict, update

EMITTER = np.array([15e3, 15e3])
SIGMA = 0.0175
Q = np.diag([0.0, 625.0])
P0 = np.array([[4e5, 1e5], [1e5, 9e5]])


@pytest.mark.parametrize("site", [[0.0, 0.0], [20e3, 0.0], [15e3, 0.0], [0.0, 30e3], [15e3, 40e3]])
def test_ekft_row_is_the_bearing_gradient(site):
    site = np.array(site)
    nu, H = lin_ekft(EMITTER, site, bearing(EMITTER, site) + 0.01)
    assert nu == pytest.approx(0.01)
    h = 1e-3
    fd = [(bearing(EMITTER + d, site) - bearing(EMITTER - d, site)) / (2 * h) for d in np.eye(2) * h]
    np.testing.assert_allclose(H, fd, rtol=1e-7)


def test_ekfs_and_skf_are_the_printed_rows():
    site = np.array([0.0, 0.0])
    x = np.array([12e3, 17e3])
    xk, yk = x / 1000.0  # the thesis's km
    u = yk / xk
    _, H = lin_ekfs(x, site, 0.9)
    np.testing.assert_allclose(H * 1000.0, [(-u / xk) / xk, (1.0 / xk) / yk], rtol=1e-12)  # per km, as printed
    _, Hs = lin_skf(x, site, 0.9)
    h = np.arctan2(17e3, 12e3)
    np.testing.assert_allclose(Hs, [0.5 * h / x[0], 0.5 * h / x[1]], rtol=1e-12)
    assert Hs @ x == pytest.approx(h)  # pseudo-linear: H·x̂ = h


def test_singular_linearisations_raise_and_the_filter_falls_back_to_ekft():
    on_x = np.array([15e3, 0.0])  # station on the emitter's x coordinate: Δx = 0
    with pytest.raises(SingularLinearisation, match="Δx"):
        lin_ekfs(EMITTER, on_x, 1.0)
    with pytest.raises(ValueError, match="ŷ_e"):
        lin_skf(np.array([10e3, 0.0]), np.array([0.0, 5e3]), 1.0)
    z = bearing(EMITTER, on_x) + 0.002
    f = BearingEKF(EMITTER, P0, Q, "EKFS")
    res = f.step(on_x, z, SIGMA)
    ref = bearing_step(EMITTER, P0, on_x, z, SIGMA, Q, "EKFT")
    assert f.n_fallbacks == 1
    np.testing.assert_array_equal(res.x, ref.x)


def test_bearing_step_equals_filterpy_ekf_with_angle_residual():
    rng = np.random.default_rng(3)
    sites = np.array([[0.0, 0.0], [20e3, 0.0], [15e3, 30e3]])
    ekf = ExtendedKalmanFilter(dim_x=2, dim_z=1)
    ekf.x, ekf.P, ekf.F, ekf.Q = EMITTER + [800.0, -500.0], P0.copy(), np.eye(2), Q
    x, P = ekf.x.copy(), ekf.P.copy()
    for k in range(12):
        s = sites[k % 3]
        z = bearing(EMITTER, s) + SIGMA * rng.standard_normal()
        res = bearing_step(x, P, s, z, SIGMA, Q, "EKFT")
        x, P = res.x, res.P
        ekf.predict()
        ekf.update(np.array([z]), lambda xx: lin_ekft(xx, s, 0.0)[1][None, :],
                   lambda xx: np.array([bearing(xx, s)]), R=SIGMA ** 2,
                   residual=lambda a, b: wrap_pi(a - b))
        np.testing.assert_allclose(x, ekf.x, rtol=1e-10)
        np.testing.assert_allclose(P, ekf.P, rtol=1e-8)


def test_wrapped_innovation_across_north():
    # predicted compass 359.9°, measured 0.1°: the innovation is 0.2°, not −359.8°
    site = np.array([0.0, 0.0])
    x = np.array([-20e3 * np.tan(np.radians(0.1)), 20e3])   # compass 359.9° from the site
    beta_meas = np.pi / 2 - np.radians(0.1)                  # compass 0.1°, math angle
    nu, _ = lin_ekft(x, site, beta_meas)
    assert nu == pytest.approx(-np.radians(0.2), rel=1e-9)   # math angles turn the other way
    res = bearing_step(x, P0, site, beta_meas, SIGMA, Q)
    assert res.x[0] > x[0] and abs(res.x[0] - x[0]) < 200.0  # moved a little east


def test_cross_fed_hands_states_and_covariances_over():
    calls = []

    def f(tag):
        def step(x, P, z):
            calls.append((tag, x.copy(), P.copy()))
            return update(x, P, np.array([z - x[0]]), np.array([[1.0]]), np.array([[1.0]]))._replace(
                x=x + (1.0 if tag == "A1" else 2.0), P=P * (0.5 if tag == "A1" else 0.25))
        return step

    x0, p0 = np.array([0.0]), np.array([[4.0]])
    cf = CrossFed(f("A1"), f("A2"), x0, p0, "swap")
    out = cf.step(0.0)
    assert out.x[0] == 1.0 and out.P[0, 0] == 2.0      # reported: A1's output
    cf.step(0.0)
    (_, xa1, pa1), (_, xa2, pa2) = calls[2], calls[3]
    assert xa1[0] == 2.0 and pa1[0, 0] == 1.0           # A1's prior = A2's output
    assert xa2[0] == 1.0 and pa2[0, 0] == 2.0           # A2's prior = A1's output
    calls.clear()
    cp = CrossFed(f("A1"), f("A2"), x0, p0, "printed")
    cp.step(0.0)
    cp.step(0.0)
    assert calls[3][1][0] == 1.0 and calls[3][2][0, 0] == 4.0  # printed: A2's covariance stays P₀


def test_mekf3_is_exactly_the_ekf_and_mekf1_is_not():
    rng = np.random.default_rng(1)
    sites = np.array([[0.0, 0.0], [20e3, 0.0]])
    x0 = EMITTER + [300.0, -600.0]
    ekf, m3, m1 = BearingEKF(x0, P0, Q), MEKF(3, x0, P0, Q), MEKF(1, x0, P0, Q)
    for k in range(20):
        s = sites[k % 2]
        z = bearing(EMITTER, s) + SIGMA * rng.standard_normal()
        ekf.step(s, z, SIGMA), m3.step(s, z, SIGMA), m1.step(s, z, SIGMA)
    np.testing.assert_array_equal(m3.x, ekf.x)
    np.testing.assert_array_equal(m3.P, ekf.P)
    assert np.linalg.norm(m1.x - ekf.x) > 1.0


def test_transition_matrices():
    np.testing.assert_allclose(transition_matrix(0.3), [[0.7, 0.3], [0.3, 0.7]])
    np.testing.assert_allclose(transition_matrix(0.3, "iid"), [[0.7, 0.3], [0.7, 0.3]])
    for bad in (0.0, 1.0, -0.1):
        with pytest.raises(ValueError, match="p must be"):
            transition_matrix(bad)
    with pytest.raises(ValueError, match="transition form"):
        transition_matrix(0.2, "markov")


def test_log_likelihood_is_the_log_of_the_shared_gaussian_likelihood():
    res = update(np.zeros(2), np.eye(2), np.array([0.7]), np.array([[1.0, 0.5]]), np.array([[0.3]]))
    assert log_likelihood(res) == pytest.approx(np.log(gaussian_likelihood(res.nu, res.S)), rel=1e-12)


@pytest.mark.parametrize("form", ["symmetric", "iid"])
def test_imm_equals_filterpy_imm_on_linear_models(form):
    rng = np.random.default_rng(7)
    Pi = transition_matrix(0.2, form)
    R = [0.5 ** 2, 3.0 ** 2]
    x0, p0 = np.array([1.0, -2.0]), np.diag([10.0, 20.0])
    Qs = np.diag([0.01, 0.02])
    fps = []
    for r in R:
        kf = KalmanFilter(dim_x=2, dim_z=1)
        kf.x, kf.P, kf.F, kf.Q, kf.R = x0.copy(), p0.copy(), np.eye(2), Qs, np.array([[r]])
        fps.append(kf)
    ref = IMMEstimator(fps, np.array([0.9, 0.1]), Pi)
    imm = IMM([x0, x0], [p0, p0], Pi, [0.9, 0.1])
    for k in range(15):
        H = np.array([[np.cos(0.4 * k), np.sin(0.4 * k)]])
        z = float((H @ [3.0, 1.0])[0]) + (0.5 if rng.random() < 0.8 else 3.0) * rng.standard_normal()
        for kf in fps:
            kf.H = H

        def step(r):
            def f(x, P):
                xp, Pp = predict(x, P, np.eye(2), Qs)
                return update(xp, Pp, np.array([z]) - H @ xp, H, np.array([[r]]))
            return f

        imm.step([step(r) for r in R])
        ref.predict()
        ref.update(np.array([z]))
        np.testing.assert_allclose(imm.mu, ref.mu, rtol=1e-9)
        np.testing.assert_allclose(imm.x, ref.x, rtol=1e-9)
        np.testing.assert_allclose(imm.P, ref.P, rtol=1e-8)


def test_bearing_imm_with_identical_models_is_the_ekf():
    rng = np.random.default_rng(2)
    sites = np.array([[0.0, 0.0], [10e3, 0.0], [20e3, 0.0]])
    x0 = EMITTER + [500.0, 400.0]
    Pi = transition_matrix(0.3)
    imm = BearingIMM([x0, x0], [P0, P0], Q, Pi, [0.95, 0.05])
    ekf = BearingEKF(x0, P0, Q)
    for k in range(12):
        s = sites[k % 3]
        z = bearing(EMITTER, s) + SIGMA * rng.standard_normal()
        mu_prev = imm.mu.copy()
        imm.step(s, z, (SIGMA, SIGMA))
        ekf.step(s, z, SIGMA)
        np.testing.assert_allclose(imm.mu, mu_prev @ Pi, rtol=1e-12)  # equal likelihoods: μ = c̄
    np.testing.assert_allclose(imm.x, ekf.x, rtol=1e-12)
    np.testing.assert_allclose(imm.P, ekf.P, rtol=1e-9)


def test_imm_flags_an_outlier_and_survives_underflow():
    site = np.array([0.0, 0.0])
    x0, tight = EMITTER.copy(), np.eye(2)
    imm = BearingIMM([x0, x0], [tight, tight], np.zeros((2, 2)), transition_matrix(0.1, "iid"), [0.9, 0.1])
    imm.step(site, bearing(EMITTER, site), (SIGMA, 0.25))
    assert imm.mu[0] > 0.9
    z = bearing(EMITTER, site) + 1.5
    for s in (1e-4, 0.01):  # NIS ~ 2e8 and ~2e4: exp(-NIS/2) is 0.0 for both models
        res = bearing_step(imm.x, imm.P, site, z, s, np.zeros((2, 2)))
        assert gaussian_likelihood(res.nu, res.S) == 0.0
    imm.step(site, z, (1e-4, 0.01))
    assert np.all(np.isfinite(imm.mu)) and imm.mu[1] > 0.99


def _bearings(sensor, betas, site=(0.0, 0.0), sigma=SIGMA):
    return bearing_measurements(np.arange(len(betas), dtype=float), [sensor],
                                np.array([site]), np.asarray(betas)[:, None], sigma)


def test_smoother_with_zero_q_is_the_wrapped_running_mean():
    betas = np.pi / 2 - np.radians([359.9, 0.1, 0.3, 359.7])  # compass azimuths around north
    sm = BearingSmoother(q=0.0)
    outs = [sm.update(m) for m in _bearings("DF1", wrap_pi(betas))]
    assert np.degrees(wrap_pi(outs[-1].z[0])) == pytest.approx(0.0, abs=1e-9)
    assert np.degrees(wrap_pi(outs[2].z[0])) == pytest.approx(0.1, abs=1e-9)
    np.testing.assert_allclose([o.std[0] for o in outs], SIGMA / np.sqrt(np.arange(1, 5)), rtol=1e-12)
    assert outs[-1].sensor == "DF1" and outs[-1].kind == "bearing"


def test_smoother_with_q_equals_filterpy_scalar_kf():
    rng = np.random.default_rng(4)
    q = 1e-6
    betas = 0.8 + np.cumsum(np.sqrt(q) * rng.standard_normal(30)) + SIGMA * rng.standard_normal(30)
    sm = BearingSmoother(q=q)
    outs = [sm.update(m) for m in _bearings("DF1", betas)]
    kf = KalmanFilter(dim_x=1, dim_z=1)
    kf.x, kf.P, kf.F, kf.H, kf.Q, kf.R = np.array([betas[0]]), np.array([[SIGMA ** 2]]), np.eye(1), np.eye(1), \
        np.array([[q]]), np.array([[SIGMA ** 2]])
    for k in range(1, 30):
        kf.predict()
        kf.update(np.array([betas[k]]))
        assert np.pi / 2 - outs[k].z[0] == pytest.approx(kf.x[0], abs=1e-12)
        assert outs[k].std[0] == pytest.approx(np.sqrt(kf.P[0, 0]), rel=1e-10)


def test_mkf_smoother_swap_is_the_kf_and_printed_is_not():
    rng = np.random.default_rng(5)
    ms = _bearings("DF1", 0.8 + SIGMA * rng.standard_normal(20))
    kf, mkf, pr = BearingSmoother(1e-7), CrossFedBearingSmoother(1e-7), CrossFedBearingSmoother(1e-7, handoff="printed")
    a = [kf.update(m) for m in ms]
    b = [mkf.update(m) for m in ms]
    c = [pr.update(m) for m in ms]
    np.testing.assert_array_equal([o.z for o in a], [o.z for o in b])
    assert c[-1].std[0] > 2 * a[-1].std[0]


def test_smoother_refuses_a_moving_station_and_another_sensor():
    sm = BearingSmoother()
    sm.update(_bearings("DF1", [0.5])[0])
    with pytest.raises(ValueError, match="moved"):
        sm.update(_bearings("DF1", [0.5], site=(100.0, 0.0))[0])
    with pytest.raises(ValueError, match="DF2"):
        sm.update(_bearings("DF2", [0.5])[0])
