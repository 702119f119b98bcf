"""Motion models, 3D measurement models, the EKF step and the initialiser, against
independent references: van Loan's matrix exponential, FilterPy's Q helpers,
pymap3d's ENU↔AER, central finite differences, and Stone Soup's EKF."""

from __future__ import annotations

import numpy as np
import pymap3d
import pytest
from filterpy.common import Q_continuous_white_noise, Q_discrete_white_noise
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.linalg import expm
from scipy.optimize import brentq

from fusion.init3d import FAR, NEAR, InitPriors, initial_state, spherical_to_position
from fusion.motion import ConstantAcceleration, ConstantTurn, ConstantVelocity, PaddedConstantVelocity, make_motion
from fusion.ekf import TrackEKF
from fusion.measurement.kinds import KINDS, model_for, model_of
from fusion.measurement.models import SphericalModel
from fusion.types import Measurement

DEG = np.pi / 180.0
MODELS = [ConstantVelocity, ConstantAcceleration]


def _continuous_A(order: int) -> np.ndarray:
    """Continuous-time dynamics of the derivative-major 3D state, built element by element."""
    n = 3 * order
    A = np.zeros((n, n))
    for d in range(order - 1):
        for ax in range(3):
            A[3 * d + ax, 3 * (d + 1) + ax] = 1.0
    return A


# Motion -------------------------------------------------------------------------------
@pytest.mark.parametrize("q_up", [None, 0.02])
@pytest.mark.parametrize("cls", MODELS)
@pytest.mark.parametrize("dt", [0.1, 1.0, 2.7])
def test_continuous_F_Q_equal_van_loan(cls, dt, q_up):
    """Van Loan's F and Q of white noise on the highest derivative, of PSD diag(q, q,
    q_up) over (east, north, up) with ``q_up`` (its definition), else q I₃."""
    q = 0.37
    m = cls(q, q_up=q_up)
    A = _continuous_A(m.order)
    n = m.n_x
    L = np.zeros((n, 3))
    L[-3:, :] = np.eye(3)  # white noise drives the highest derivative
    psd = np.diag([q, q, q if q_up is None else q_up])
    M = np.block([[-A, L @ psd @ L.T], [np.zeros((n, n)), A.T]]) * dt
    E = expm(M)
    F_ref = E[n:, n:].T
    Q_ref = F_ref @ E[:n, n:]
    np.testing.assert_allclose(m.F(dt), F_ref, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(m.Q(dt), Q_ref, rtol=1e-9, atol=1e-12 * np.abs(Q_ref).max())


@pytest.mark.parametrize("cls", MODELS)
def test_Q_forms_equal_filterpy(cls):
    dt, q = 1.3, 0.05
    dim = cls.order
    cont = Q_continuous_white_noise(dim, dt, spectral_density=q, block_size=3, order_by_dim=False)
    disc = Q_discrete_white_noise(dim, dt, var=q, block_size=3, order_by_dim=False)
    np.testing.assert_allclose(cls(q).Q(dt), cont, rtol=1e-12)
    np.testing.assert_allclose(cls(q, "discrete").Q(dt), disc, rtol=1e-12)


@settings(max_examples=40, deadline=None)
@given(a=st.floats(0.0, 5.0), b=st.floats(0.0, 5.0), cls=st.sampled_from(MODELS))
def test_continuous_model_is_a_semigroup(a, b, cls):
    # Predicting over a then b equals predicting over a + b (the discretisation is exact).
    m = cls(0.2)
    np.testing.assert_allclose(m.F(a + b), m.F(b) @ m.F(a), rtol=1e-12, atol=1e-12)
    Q2 = m.F(b) @ m.Q(a) @ m.F(b).T + m.Q(b)
    np.testing.assert_allclose(m.Q(a + b), Q2, rtol=1e-9, atol=1e-12 * (1 + np.abs(Q2).max()))


@pytest.mark.parametrize("q_up", [None, 0.05])
@pytest.mark.parametrize("noise", ["continuous", "discrete"])
@pytest.mark.parametrize("cls", MODELS)
def test_sample_draws_from_F_and_Q(cls, noise, q_up):
    rng = np.random.default_rng(7)
    m = cls(0.8, noise, q_up)
    x0 = np.arange(m.n_x, dtype=float)
    dt, N = 1.7, 100_000
    x1 = m.sample(np.tile(x0, (N, 1)), dt, rng)
    w = x1 - m.F(dt) @ x0
    Q = m.Q(dt)
    sd = np.sqrt(np.diag(Q))
    np.testing.assert_allclose(w.mean(0) / sd, 0.0, atol=5 / np.sqrt(N))
    corr_err = (np.cov(w.T) - Q) / np.outer(sd, sd)
    assert np.abs(corr_err).max() < 6 * np.sqrt(2.0 / N)
    # One state in, one state out, with the same law.
    assert m.sample(x0, dt, rng).shape == (m.n_x,)


def test_sample_at_zero_dt_is_deterministic():
    m = ConstantAcceleration(1.0)
    x = np.arange(9.0)
    np.testing.assert_array_equal(m.sample(x, 0.0, np.random.default_rng(0)), x)


def test_motion_rejects_bad_input():
    with pytest.raises(ValueError, match="q"):
        ConstantAcceleration(-1.0)
    with pytest.raises(ValueError, match="noise"):
        ConstantAcceleration(1.0, "pink")
    with pytest.raises(ValueError, match="dt"):
        ConstantAcceleration(1.0).Q(-0.5)
    with pytest.raises(ValueError, match="dt"):
        ConstantVelocity(1.0).F(float("nan"))
    with pytest.raises(ValueError, match="6 components"):
        ConstantVelocity(1.0).sample(np.zeros(9), 1.0, np.random.default_rng(0))
    with pytest.raises(ValueError, match="motion model"):
        make_motion("singer", 1.0)


# Measurement geometry --------------------------------------------------------------------
def _random_geometry(rng, n):
    """Targets at all azimuths, elevations ±80°, ranges 100 m – 100 km, random sites."""
    az = rng.uniform(0, 2 * np.pi, n)
    el = rng.uniform(-80, 80, n) * DEG
    r = 10 ** rng.uniform(2, 5, n)
    site = rng.uniform(-5e3, 5e3, (n, 3))
    d = r[:, None] * np.column_stack([np.cos(el) * np.sin(az), np.cos(el) * np.cos(az), np.sin(el)])
    x = np.concatenate([site + d, rng.normal(0, 100, (n, 6))], axis=1)
    return x, site, az, el, r


SENSORS = [
    ("range_az", (1.0 * DEG, 20.0)),
    ("azel", (0.05 * DEG, 0.05 * DEG)),
    ("az_el_range", (1.0 * DEG, 1.0 * DEG, 20.0)),
]


def test_h_matches_pymap3d_enu2aer():
    rng = np.random.default_rng(1)
    x, site, *_ = _random_geometry(rng, 300)
    for k in range(len(x)):
        az, el, rng_ = pymap3d.enu2aer(*(x[k, :3] - site[k]), deg=False)
        ref = {"az": az, "el": el, "range": rng_}
        for kind, std in SENSORS:
            z = model_for(kind, site[k], std).h(x[k])
            np.testing.assert_allclose(z, [ref[c] for c in KINDS[kind].names], rtol=1e-12, atol=1e-9)
            assert 0.0 <= z[0] < 2 * np.pi


def test_h_is_vectorised_over_states():
    rng = np.random.default_rng(2)
    x, *_ = _random_geometry(rng, 50)
    m = model_for("az_el_range", np.zeros(3), (0.01, 0.01, 5.0))
    np.testing.assert_allclose(m.h(x.reshape(5, 10, 9)).reshape(50, 3), np.array([m.h(xi) for xi in x]), rtol=1e-15)


@pytest.mark.parametrize("n_x", [6, 9])
def test_jacobians_match_central_differences(n_x):
    rng = np.random.default_rng(3)
    x, site, *_ = _random_geometry(rng, 400)
    for k in range(len(x)):
        xk = x[k, :n_x]
        for kind, std in SENSORS:
            m = model_for(kind, site[k], std, n_x)
            H = m.jacobian(xk)
            assert H.shape == (m.n_z, n_x)
            step = 1e-5 * np.linalg.norm(xk[:3] - site[k])
            Hfd = np.zeros_like(H)
            for j in range(n_x):
                e = np.zeros(n_x)
                e[j] = step
                dz = m.h(xk + e) - m.h(xk - e)
                dz[m.angles] = (dz[m.angles] + np.pi) % (2 * np.pi) - np.pi  # az may cross north
                Hfd[:, j] = dz / (2 * step)
            scale = np.linalg.norm(H, axis=1, keepdims=True)
            np.testing.assert_allclose(H, Hfd, rtol=0, atol=1e-6 * scale.max())
            assert np.all(np.abs(H - Hfd) <= 1e-6 * scale)


def test_composite_model_rows_come_from_their_own_sites():
    rng = np.random.default_rng(4)
    x, *_ = _random_geometry(rng, 1)
    a, r = model_for("azel", [100.0, 0, 0], (1e-3, 1e-3)), model_for("range_az", [0, -300.0, 5.0], (0.02, 15.0))
    ss = SphericalModel.stack([a, r])
    np.testing.assert_array_equal(ss.h(x[0]), np.concatenate([a.h(x[0]), r.h(x[0])]))
    np.testing.assert_array_equal(ss.jacobian(x[0]), np.vstack([a.jacobian(x[0]), r.jacobian(x[0])]))
    np.testing.assert_array_equal(ss.R, np.diag(np.concatenate([a.std, r.std]) ** 2))
    np.testing.assert_array_equal(ss.angles, [True, True, True, False])
    lcdd = SphericalModel.stack([a, r]).select([0, 1, 3])
    assert lcdd.components == ("az", "el", "range")
    np.testing.assert_array_equal(lcdd.h(x[0]), ss.h(x[0])[[0, 1, 3]])


def test_singular_geometry_is_a_clear_error():
    above = np.array([10.0, 20.0, 5000.0, 0, 0, 0])
    with pytest.raises(ValueError, match="straight above"):
        model_for("azel", [10.0, 20.0, 0.0], (1e-3, 1e-3), 6).jacobian(above)
    with pytest.raises(ValueError, match="straight above"):
        model_for("range_az", [10.0, 20.0, 0.0], (1e-2, 10.0), 6).h(above)
    with pytest.raises(ValueError, match="zero range"):
        SphericalModel(["range"], [10.0, 20.0, 5000.0], [1.0], 6).jacobian(above)
    # Range alone is fine straight above.
    assert SphericalModel(["range"], [10.0, 20.0, 0.0], [1.0], 6).h(above)[0] == pytest.approx(5000.0)


def test_innovation_wraps_azimuth_across_north():
    m = model_for("azel", np.zeros(3), (1e-3, 1e-3), 6)
    x = np.array([-1.0, 1000.0, 10.0, 0, 0, 0])  # just west of north: az ≈ 2π − 0.001
    nu = m.innovation(np.array([0.001, m.h(x)[1]]), x)
    assert nu[0] == pytest.approx(0.001 + 0.001, abs=1e-6)


def test_model_of_builds_the_sensor_model():
    site = np.array([1.0, 2.0, 3.0])
    m = Measurement(0.0, "r1", "range_az", np.array([0.3, 5000.0]), np.array([0.01, 7.0]), site)
    model = model_of(m, 6)
    assert model.components == ("az", "range") and model.n_x == 6
    np.testing.assert_array_equal(model.site, site)
    np.testing.assert_array_equal(model.R, np.diag([0.01**2, 49.0]))
    assert model_of(Measurement(0.0, "a", "azel", m.z, m.std, site)).components == ("az", "el")
    with pytest.raises(ValueError, match="bearing"):
        model_of(Measurement(0.0, "df", "bearing", np.array([0.3]), np.array([0.01]), site))
    with pytest.raises(ValueError, match="r1"):
        model_of(Measurement(0.0, "r1", "range_az", np.array([0.3]), np.array([0.01, 7.0]), site))
    with pytest.raises(ValueError, match="correlations"):
        model_of(Measurement(0.0, "r1", "range_az", m.z, m.std, site, corr=np.eye(2)))
    with pytest.raises(ValueError, match="std"):
        model_for("range_az", site, (0.01, -1.0))


# EKF step vs Stone Soup ------------------------------------------------------------------
def _stonesoup_ekf(model, motion, x, P, dt, z):
    """Stone Soup's ExtendedKalmanPredictor/Updater on the same models.

    Stone Soup orders the state per axis ([x vx ax y vy ay z vz az]) and has no
    slant-range 2D radar, so our measurement model is wrapped (function and Jacobian
    only, permuted); the transition model, prediction and Kalman update are Stone Soup's.
    """
    from datetime import datetime, timedelta

    from stonesoup.base import Property
    from stonesoup.models.measurement.nonlinear import NonLinearGaussianMeasurement
    from stonesoup.models.transition.linear import (
        CombinedLinearGaussianTransitionModel,
        ConstantAcceleration as SSConstantAcceleration,
    )
    from stonesoup.predictor.kalman import ExtendedKalmanPredictor
    from stonesoup.types.detection import Detection
    from stonesoup.types.hypothesis import SingleHypothesis
    from stonesoup.types.state import GaussianState
    from stonesoup.updater.kalman import ExtendedKalmanUpdater

    n = 9
    perm = np.array([3 * (i % 3) + i // 3 for i in range(n)])  # ours[i] = stonesoup[perm[i]]

    class Wrapped(NonLinearGaussianMeasurement):
        ours: object = Property(doc="a fusion.measurement model")

        @property
        def ndim_meas(self):
            return self.ours.n_z

        def function(self, state, noise=False, **kwargs):
            return self.ours.h(np.asarray(state.state_vector, float)[perm, 0]).reshape(-1, 1)

        def jacobian(self, state, **kwargs):
            H = np.zeros((self.ours.n_z, n))
            H[:, perm] = self.ours.jacobian(np.asarray(state.state_vector, float)[perm, 0])
            return H

    t0 = datetime(2024, 1, 1)
    tm = CombinedLinearGaussianTransitionModel([SSConstantAcceleration(noise_diff_coeff=motion.q)] * 3)
    inv = np.argsort(perm)
    prior = GaussianState(x[inv].reshape(-1, 1), P[np.ix_(inv, inv)], timestamp=t0)
    pred = ExtendedKalmanPredictor(tm).predict(prior, timestamp=t0 + timedelta(seconds=dt))
    mm = Wrapped(ndim_state=n, mapping=tuple(range(n)), noise_covar=model.R, ours=model)
    det = Detection(z.reshape(-1, 1), timestamp=pred.timestamp, measurement_model=mm)
    post = ExtendedKalmanUpdater(mm).update(SingleHypothesis(pred, det))
    un = lambda v: np.asarray(v, float)[perm][:, perm] if np.ndim(v) == 2 and v.shape[1] == n else np.asarray(v, float)[perm, 0]
    return un(pred.state_vector), un(pred.covar), un(post.state_vector), un(post.covar)


@pytest.mark.parametrize(
    "model",
    [
        model_for("range_az", [50.0, -20.0, 3.0], (1.0 * DEG, 20.0)),
        model_for("azel", [0.0, 0.0, 0.0], (0.05 * DEG, 0.05 * DEG)),
        model_for("az_el_range", [-300.0, 100.0, 10.0], (0.5 * DEG, 0.7 * DEG, 15.0)),
        SphericalModel.stack([model_for("azel", np.zeros(3), (0.05 * DEG, 0.05 * DEG)), model_for("range_az", np.zeros(3), (1.0 * DEG, 20.0))]),
    ],
    ids=["radar2d", "angle", "radar3d", "stacked"],
)
def test_ekf_step_matches_stonesoup(model):
    rng = np.random.default_rng(5)
    motion = ConstantAcceleration(0.01)
    x = np.array([6000.0, 8000.0, 2000.0, -120.0, -60.0, 5.0, 0.5, 1.0, -0.05])
    A = rng.normal(size=(9, 9))
    P = A @ A.T + np.diag([400.0, 400, 400, 100, 100, 100, 1, 1, 1])
    dt = 1.3
    truth = x + rng.multivariate_normal(np.zeros(9), P)
    z = model.h(motion.F(dt) @ truth) + rng.normal(size=model.n_z) * model.std
    ekf = TrackEKF(motion, x, P, 10.0)
    ekf.predict(10.0 + dt)
    xp, Pp = ekf.x.copy(), ekf.P.copy()
    res = ekf.update(model, z)
    sx_p, sP_p, sx, sP = _stonesoup_ekf(model, motion, x, P, dt, z)
    np.testing.assert_allclose(xp, sx_p, rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(Pp, sP_p, rtol=1e-9, atol=1e-9 * np.abs(Pp).max())
    sd = np.sqrt(np.diag(sP))
    np.testing.assert_allclose((ekf.x - sx) / sd, 0.0, atol=1e-9)
    np.testing.assert_allclose((ekf.P - sP) / np.outer(sd, sd), 0.0, atol=1e-9)
    assert res.nis == pytest.approx(float(res.nu @ np.linalg.solve(res.S, res.nu)), rel=1e-12)


def test_ekf_refuses_to_predict_backwards():
    ekf = TrackEKF(ConstantVelocity(1.0), np.zeros(6), np.eye(6), 5.0)
    with pytest.raises(ValueError, match="backwards"):
        ekf.predict(4.0)


# Initialisation ------------------------------------------------------------------------
def _meas(kind, z, std, site=(0.0, 0.0, 0.0), sensor=None, t=0.0):
    return Measurement(t, sensor or kind, kind, np.array(z, float), np.array(std, float), np.array(site, float))


def _fd_jacobian(f, p, step):
    J = np.zeros((3, 3))
    for j in range(3):
        e = np.zeros(3)
        e[j] = step[j]
        J[:, j] = (np.asarray(f(*(p + e))) - np.asarray(f(*(p - e)))) / (2 * step[j])
    return J


def test_init_uses_angle_sensor_angles_and_radar_range():
    az_i, el_i, az_r, r_r = 0.6435, 0.1974, 0.66, 10_198.0
    s_ang, s_r = (0.05 * DEG, 0.05 * DEG), (1.0 * DEG, 20.0)
    scan = [_meas("azel", [az_i, el_i], s_ang), _meas("range_az", [az_r, r_r], s_r)]
    pr = InitPriors(vel_std=150.0, vel_std_up=30.0, acc_std=4.0, acc_std_up=0.5)
    x, P = initial_state(scan, 9, pr)
    aer2enu = lambda a, e, r: pymap3d.aer2enu(a, e, r, deg=False)
    np.testing.assert_allclose(x[:3], aer2enu(az_i, el_i, r_r), rtol=1e-12)
    np.testing.assert_array_equal(x[3:], 0.0)
    J = _fd_jacobian(aer2enu, np.array([az_i, el_i, r_r]), [1e-7, 1e-7, 1e-3])
    P_ref = J @ np.diag([s_ang[0] ** 2, s_ang[1] ** 2, s_r[1] ** 2]) @ J.T
    np.testing.assert_allclose(P[:3, :3], P_ref, rtol=1e-6, atol=1e-9 * np.abs(P_ref).max())
    np.testing.assert_allclose(np.diag(P)[3:], [150.0**2] * 2 + [30.0**2] + [16.0] * 2 + [0.25])
    assert np.all(P[:3, 3:] == 0.0) and np.all(np.linalg.eigvalsh(P) > 0)
    x6, P6 = initial_state(scan, 6, pr)
    np.testing.assert_array_equal(x6, x[:6])
    np.testing.assert_array_equal(P6, P[:6, :6])


def test_init_with_separated_sites_intersects_the_ray_with_the_range_sphere():
    s_a, s_r = np.array([0.0, 0.0, 0.0]), np.array([3000.0, -1000.0, 50.0])
    az, el, r = 0.7, 0.15, 9000.0
    u = lambda a, e: np.array([np.cos(e) * np.sin(a), np.cos(e) * np.cos(a), np.sin(e)])

    def reference(a, e, rr):  # brentq on the far intersection
        t = brentq(lambda t: np.linalg.norm(s_a + t * u(a, e) - s_r) - rr, 0.0, 1e6)
        return s_a + t * u(a, e)

    scan = [_meas("azel", [az, el], (1e-3, 2e-3), s_a), _meas("range_az", [1.0, r], (0.02, 25.0), s_r)]
    x, P = initial_state(scan, 9)
    np.testing.assert_allclose(x[:3], reference(az, el, r), rtol=1e-10)
    assert np.linalg.norm(x[:3] - s_r) == pytest.approx(r, rel=1e-12)
    J = _fd_jacobian(reference, np.array([az, el, r]), [1e-7, 1e-7, 1e-3])
    np.testing.assert_allclose(P[:3, :3], J @ np.diag([1e-6, 4e-6, 625.0]) @ J.T, rtol=1e-5)
    # A range sphere the ray misses is not used: the prior range applies instead.
    far = [scan[0], _meas("range_az", [1.0, 100.0], (0.02, 25.0), [1e5, 1e5, 0.0])]
    xf, _ = initial_state(far, 9, InitPriors(range=7000.0))
    assert np.linalg.norm(xf[:3]) == pytest.approx(7000.0)


def test_ray_sphere_near_root_and_its_jacobian():
    """A sensor outside the range sphere: its ray crosses it twice ahead; NEAR is the
    first crossing (brentq between the sensor and the ray's closest approach), FAR the
    second, and J = ∂p/∂(az, el, r) of each is the finite difference of that root."""
    s_a, s_r = np.array([0.0, 50e3, 0.0]), np.zeros(3)
    az, el, r = 3.0, 0.12, 30e3
    u = lambda a, e: np.array([np.cos(e) * np.sin(a), np.cos(e) * np.cos(a), np.sin(e)])
    for root in (NEAR, FAR):
        def reference(a, e, rr):
            t_mid = -u(a, e) @ (s_a - s_r)  # closest approach to the radar, inside the sphere
            lo, hi = (0.0, t_mid) if root == NEAR else (t_mid, 1e6)
            return s_a + brentq(lambda t: np.linalg.norm(s_a + t * u(a, e) - s_r) - rr, lo, hi) * u(a, e)

        p, J = spherical_to_position(s_a, az, el, r, s_r, root)
        np.testing.assert_allclose(p, reference(az, el, r), rtol=1e-10)
        np.testing.assert_allclose(J, _fd_jacobian(reference, np.array([az, el, r]), [1e-7, 1e-7, 1e-3]), rtol=1e-5, atol=1e-4)
        x, _ = initial_state([_meas("azel", [az, el], (1e-3, 1e-3), s_a), _meas("range_az", [az, r], (0.02, 20.0), s_r)],
                             9, root=root)
        np.testing.assert_array_equal(x[:3], p)
    assert spherical_to_position(np.zeros(3), az, el, 5e3, [0.0, 1e3, 0.0], NEAR) is None  # inside: t₋ is behind


def test_init_takes_missing_components_from_the_priors():
    pr = InitPriors(range=12_000.0, range_std=3000.0, el=0.2, el_std=0.05)
    x, P = initial_state([_meas("azel", [1.0, 0.3], (1e-3, 1e-3))], 9, pr)
    np.testing.assert_allclose(x[:3], pymap3d.aer2enu(1.0, 0.3, 12_000.0, deg=False), rtol=1e-12)
    u = x[:3] / np.linalg.norm(x[:3])
    assert u @ P[:3, :3] @ u == pytest.approx(3000.0**2, rel=1e-3)  # along the ray: the prior range
    x, P = initial_state([_meas("range_az", [1.0, 8000.0], (0.02, 20.0))], 9, pr)
    np.testing.assert_allclose(x[:3], pymap3d.aer2enu(1.0, 0.2, 8000.0, deg=False), rtol=1e-12)
    # The best (smallest-σ) source of each component wins.
    scan = [_meas("azel", [1.0, 0.3], (1e-2, 1e-2), sensor="a1"), _meas("azel", [1.1, 0.2], (1e-3, 1e-3), sensor="a2")]
    x, _ = initial_state(scan, 9, pr)
    np.testing.assert_allclose(x[:3], pymap3d.aer2enu(1.1, 0.2, 12_000.0, deg=False), rtol=1e-12)


def test_init_position_covariance_is_consistent():
    rng = np.random.default_rng(6)
    p_true = np.array([6000.0, 8000.0, 2000.0])
    az, el, r = pymap3d.enu2aer(*p_true, deg=False)
    s_ang, s_r = np.array([0.05, 0.05]) * DEG, np.array([1.0 * DEG, 20.0])
    N = 2000
    nees = np.empty(N)
    for k in range(N):
        za = np.array([az, el]) + rng.normal(size=2) * s_ang
        zr = np.array([az, r]) + rng.normal(size=2) * s_r
        x, P = initial_state([_meas("azel", za, s_ang), _meas("range_az", zr, s_r)], 6)
        e = x[:3] - p_true
        nees[k] = e @ np.linalg.solve(P[:3, :3], e)
    assert abs(nees.mean() - 3.0) < 4 * np.sqrt(6.0 / N)


def test_init_rejects_what_it_cannot_use():
    with pytest.raises(ValueError, match="empty"):
        initial_state([], 9)
    with pytest.raises(ValueError, match="bearing"):
        initial_state([_meas("bearing", [1.0], [0.01])], 9)
    with pytest.raises(ValueError, match="6 .CV. or 9"):
        initial_state([_meas("azel", [1.0, 0.1], [0.01, 0.01])], 4)
    with pytest.raises(ValueError, match="el"):
        InitPriors(el=2.0)


def test_spherical_to_position_jacobian_colocated():
    p, J = spherical_to_position([1.0, 2.0, 3.0], 4.0, -0.3, 5000.0)
    f = lambda a, e, r: np.array([1.0, 2.0, 3.0]) + np.array(pymap3d.aer2enu(a, e, r, deg=False))
    np.testing.assert_allclose(p, f(4.0, -0.3, 5000.0), rtol=1e-12)
    np.testing.assert_allclose(J, _fd_jacobian(f, np.array([4.0, -0.3, 5000.0]), [1e-7, 1e-7, 1e-3]), rtol=1e-6, atol=1e-6)


def test_iterated_update_is_the_map_estimate_and_one_iteration_is_the_ekf():
    """The iterated update converges to the minimiser of the MAP cost
    |x − x̄|²_P̄⁻¹ + |z − h(x)|²_R⁻¹ (scipy's least squares as the independent reference);
    with one iteration it is the EKF; ν, S and NIS stay those of the prediction."""
    from scipy.optimize import least_squares

    from fusion.ekf import ekf_update, iterated_ekf_update

    rng = np.random.default_rng(7)
    m = model_for("az_el_range", np.zeros(3), (np.radians(1.0), np.radians(1.0), 20.0))  # fine range, coarse angles
    truth = np.r_[6000.0, 8000.0, 2000.0, np.zeros(6)]
    P = np.diag([1000.0**2] * 3 + [100.0**2] * 3 + [10.0**2] * 3)  # a broad cross-range spread
    x_bar = truth + np.linalg.cholesky(P) @ rng.standard_normal(9)
    z = m.h(truth) + np.array([0.3, -0.2, 0.5]) * m.std
    L_p, L_r = np.linalg.cholesky(np.linalg.inv(P)), 1.0 / m.std

    def residual(x):
        nu = m.innovation(z, x)
        return np.r_[L_p.T @ (x - x_bar), nu * L_r]

    ref = least_squares(residual, x_bar, xtol=1e-15, ftol=1e-15, gtol=1e-15).x
    one = ekf_update(m, x_bar, P, z)
    it, _ = iterated_ekf_update(m, x_bar, P, z, iterations=1)
    np.testing.assert_array_equal(it.x, one.x)
    it, _ = iterated_ekf_update(m, x_bar, P, z, iterations=20)
    np.testing.assert_allclose(it.x[:3], ref[:3], rtol=0, atol=1e-6)
    assert np.linalg.norm(one.x[:3] - ref[:3]) > 1.0  # the single linearisation is metres off here
    assert it.nis == one.nis and np.array_equal(it.S, one.S)
    ekf = TrackEKF(make_motion("ca", 0.01), x_bar, P, 0.0, iterations=20)
    ekf.update(m, z)
    np.testing.assert_allclose(ekf.x, it.x, rtol=0, atol=1e-9)


@pytest.mark.parametrize("motion", [ConstantVelocity(2.0), ConstantAcceleration(0.5, "discrete"),
                                    PaddedConstantVelocity(1.0), ConstantTurn(0.5, 0.05)], ids=repr)
def test_F_and_Q_are_the_kronecker_products_of_the_axis_blocks(motion):
    """``F(dt)`` and ``Q(dt)`` are ``np.kron(F₁, I₃)`` and ``np.kron(Q₁, I₃)`` bit for bit
    (the sign of every zero too: a turn's ``F₁`` has negative entries)."""
    for dt in (0.0, 1e-3, 0.37, 4.0, 11.9):
        for got, axis in ((motion.F(dt), motion.F_axis(dt)), (motion.Q(dt), motion.Q_axis(dt))):
            ref = np.kron(axis, np.eye(3))
            assert got.shape == ref.shape and np.array_equal(got, ref)
            assert np.array_equal(np.signbit(got), np.signbit(ref))


def test_the_climb_bound_is_the_nearest_state_on_it_in_the_covariances_metric():
    """climb_projected (fusion.ekf): against a direct minimisation of
    (x̃ − x)ᵀ P⁻¹ (x̃ − x) under v_up = ±max_climb (scipy, SLSQP) on random states and
    covariances, to 1e-6; a state inside the bound unchanged."""
    from scipy.optimize import minimize

    from fusion.ekf import V_UP, climb_projected
    rng = np.random.default_rng(11)
    for _ in range(20):
        A = rng.normal(size=(9, 9))
        P = A @ A.T + 0.1 * np.eye(9)
        x = rng.normal(0.0, 50.0, 9)
        x[V_UP] = rng.choice([-1, 1]) * rng.uniform(31.0, 200.0)
        Pinv = np.linalg.inv(P)
        d = np.copysign(30.0, x[V_UP])
        best = minimize(lambda y: (y - x) @ Pinv @ (y - x), x, jac=lambda y: 2.0 * Pinv @ (y - x), method="SLSQP",
                        constraints=[{"type": "eq", "fun": lambda y: y[V_UP] - d}], options={"ftol": 1e-14})
        got = climb_projected(x, P, 30.0)
        assert got[V_UP] == pytest.approx(d, abs=1e-9)
        np.testing.assert_allclose(got, best.x, atol=1e-6 * (1.0 + np.abs(x).max()))
        inside = x.copy()
        inside[V_UP] = 29.0
        assert climb_projected(inside, P, 30.0) is inside


def test_a_track_blind_in_height_for_a_minute_takes_a_height_without_a_climb_no_aircraft_makes():
    """A level aircraft at 5 km tracked by a 2D radar alone (azimuth, slant range) for
    60 s, its height open by 1.5 km by then, then seen by an angle sensor (az, el) that
    puts it 1 km lower than the track: the EKF makes of it a descent of 40 m/s, faster
    than any airliner's (28 m/s at most in the paris-real recording), and a
    ``max_climb`` of 30 m/s holds the estimate at that bound."""
    motion = ConstantAcceleration(q=0.5, q_up=0.05)
    truth = lambda t: np.array([20e3 + 200.0 * t, 40e3, 5000.0])  # noqa: E731
    radar, eo = np.zeros(3), np.array([30e3, 20e3, 0.0])
    m2d = SphericalModel(("az", "range"), radar, [np.radians(0.15), 60.0], 9)
    mel = SphericalModel(("az", "el"), eo, [np.radians(0.05)] * 2, 9)
    x0 = np.zeros(9)
    x0[:3] = truth(0.0) + [0.0, 0.0, 1000.0]  # the track's height 1 km off from the start
    x0[3] = 200.0
    P0 = np.diag([100.0, 100.0, 50.0, 10.0, 10.0, 3.0, 1.0, 1.0, 0.3]) ** 2

    def run(max_climb):
        f = TrackEKF(motion, x0, P0, 0.0, max_climb=max_climb)
        for t in np.arange(4.0, 61.0, 4.0):
            f.predict(t)
            f.update(m2d, m2d.h(np.r_[truth(t), np.zeros(6)]))
        assert np.sqrt(f.P[2, 2]) > 1000.0  # the radar alone: the height a kilometre open
        f.predict(61.0)
        f.update(mel, mel.h(np.r_[truth(61.0), np.zeros(6)]))
        return f.x

    assert run(None)[5] < -35.0  # faster than any airliner descends
    bounded = run(30.0)
    assert bounded[5] == pytest.approx(-30.0)


@pytest.mark.parametrize("keys, says", [
    ({"max_climb": 0.0}, "'max_climb' must be > 0"),
    ({"max_climb": 30.0, "filter": "ukf"}, "bounds the 'ekf' filter's estimate"),
])
def test_the_climb_bound_is_checked(keys, says):
    from fusion.patent import TrackerConfig
    with pytest.raises(ValueError, match=says):
        TrackerConfig.from_dict(keys)


def test_the_climb_bound_reaches_every_ekf_of_a_method():
    """``max_climb`` in [tracker] gives each EKF the bound, the IMM's model-matched ones too."""
    from fusion.patent import TrackerConfig
    for motion in ("ca", "imm"):
        cfg = TrackerConfig.from_dict({"max_climb": 25.0, "motion": motion})
        f = cfg.new_filter(cfg.motion_model())(np.zeros(9), np.eye(9), 0.0)
        ekfs = getattr(f, "filters", [f])
        assert ekfs and {e.max_climb for e in ekfs} == {25.0}


def test_q_up_is_the_ca_and_cv_models_and_left_aside_by_the_imm():
    """A scenario's ``q_up`` (for its CA tracker) does not stop ``--set motion=imm``: the
    IMM's models have their own q's (paris-real sets q_up and its IMM runs)."""
    from fusion.imm import ModelSet
    from fusion.patent import TrackerConfig
    assert isinstance(TrackerConfig.from_dict({"motion": "imm", "q_up": 0.05}).motion_model(), ModelSet)
    assert TrackerConfig.from_dict({"motion": "ca", "q": 0.5, "q_up": 0.05}).motion_model().q_up == 0.05
    with pytest.raises(ValueError, match="'q_up' must be >= 0"):
        TrackerConfig.from_dict({"motion": "ca", "q_up": -1.0})
