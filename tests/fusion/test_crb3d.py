"""The posterior Cramér–Rao bound: exact for linear-Gaussian models (the Kalman filter's
Riccati recursion), the information form, the Jacobian expectation, and the scenario
bounds the evaluation computes."""

from __future__ import annotations

import numpy as np
import pytest

from fusion.crb3d import block_rmse, expected_information, posterior_crb
from fusion.kalman import predict, update
from fusion.measurement.kinds import model_for
from fusion.motion import ConstantAcceleration, ConstantVelocity

DEG = np.pi / 180.0


@pytest.mark.parametrize("noise", ["continuous", "discrete"])
def test_linear_gaussian_bound_is_the_kalman_covariance(noise):
    """With h linear the PCRB recursion is the Riccati recursion of the KF, exactly."""
    motion = ConstantVelocity(0.5, noise)
    rng = np.random.default_rng(0)
    H = np.zeros((3, 6))
    H[:, :3] = np.eye(3)
    H[2, 3] = 0.3  # something not purely positional
    R = np.diag([4.0, 9.0, 1.0])
    times = np.cumsum(rng.uniform(0.5, 2.0, size=30))
    P0 = np.diag([100.0, 100.0, 100.0, 25.0, 25.0, 25.0])
    info = np.array([np.zeros((6, 6))] + [H.T @ np.linalg.inv(R) @ H] * (times.size - 1))
    C = posterior_crb(P0, times, motion, info)
    P = P0
    for k in range(1, times.size):
        dt = times[k] - times[k - 1]
        _, P = predict(np.zeros(6), P, motion.F(dt), motion.Q(dt))
        P = update(np.zeros(6), P, np.zeros(3), H, R).P
        assert C[k] == pytest.approx(P, rel=1e-9, abs=1e-9)
    assert C[0] == pytest.approx(P0)


def test_information_form_recursion():
    """J_{k+1} = (Q + F J_k⁻¹ Fᵀ)⁻¹ + I, written out with explicit inverses."""
    motion = ConstantAcceleration(0.01)
    rng = np.random.default_rng(3)
    A = rng.normal(size=(4, 9))
    info = [np.zeros((9, 9))] + [A.T @ A * s for s in rng.uniform(0.1, 2.0, size=12)]
    P0 = np.diag([50.0] * 3 + [20.0] * 3 + [2.0] * 3)
    times = np.arange(13, dtype=float)
    C = posterior_crb(P0, times, motion, np.array(info))
    J = np.linalg.inv(P0)
    for k in range(1, 13):
        F, Q = motion.F(1.0), motion.Q(1.0)
        J = np.linalg.inv(Q + F @ np.linalg.inv(J) @ F.T) + info[k]
        assert np.linalg.inv(C[k]) == pytest.approx(J, rel=1e-6, abs=1e-9)


def _fd_jacobian(model, x, h=1e-3):
    cols = []
    for i in range(x.size):
        d = np.zeros(x.size)
        d[i] = h
        diff = model.h(x + d) - model.h(x - d)
        diff = np.where(model.angles, (diff + np.pi) % (2 * np.pi) - np.pi, diff)
        cols.append(diff / (2 * h))
    return np.array(cols).T


def test_expected_information_is_the_average_of_HtRinvH():
    rng = np.random.default_rng(5)
    models = [model_for("range_az", [0, 0, 0], [1 * DEG, 20.0]), model_for("azel", [100, -50, 3], [0.05 * DEG, 0.05 * DEG])]
    X = np.hstack([rng.normal([6000, 8000, 2000], 300, size=(7, 3)), rng.normal(size=(7, 6))])
    ref = np.zeros((9, 9))
    for x in X:
        for m, w in zip(models, (1.0, 0.7)):
            H = _fd_jacobian(m, x)
            ref += w * H.T @ np.linalg.inv(m.R) @ H
    ref /= len(X)
    got = expected_information(models, X, weights=[1.0, 0.7])
    assert got == pytest.approx(ref, rel=1e-5, abs=1e-12)
    with pytest.raises(ValueError):
        expected_information(models, X, weights=[1.5, 0.0])


def test_block_rmse():
    C = np.diag(np.arange(1.0, 10.0))
    assert block_rmse(C, slice(0, 3)) == pytest.approx(np.sqrt(6.0))
    assert block_rmse(np.stack([C, 4 * C]), slice(3, 6)) == pytest.approx([np.sqrt(15.0), 2 * np.sqrt(15.0)])


def test_static_3d_radar_bound_is_the_measurement_average():
    """A motionless target (q = 0), a 3D radar, no prior on position beyond the first scan:
    after k scans the position bound is (Σ HᵀR⁻¹H)⁻¹ (linearised at the true point)."""
    model = model_for("az_el_range", [0, 0, 0], [1 * DEG, 1 * DEG, 20.0], 6)
    x = np.array([6000.0, 8000.0, 2000.0, 0, 0, 0])
    H = model.jacobian(x)
    I1 = H.T @ np.linalg.inv(model.R) @ H
    P0 = np.diag([1e12] * 3 + [1e-12] * 3)  # no position prior, velocity known (zero)
    times = np.arange(10.0)
    C = posterior_crb(P0, times, ConstantVelocity(0.0), np.array([I1] * 10))
    for k in (0, 4, 9):
        expect = np.linalg.inv(I1[:3, :3] * (k + 1))
        assert C[k][:3, :3] == pytest.approx(expect, rel=1e-6)


# The evaluation's bounds for built-in scenarios ------------------------------------------------------------


def test_scenario_bound_emitter_equals_the_closed_form():
    from sensors_sim import load_scenario
    from services.evaluation import crb_summary

    sc = load_scenario("thesis-fixed-c1")
    crb = crb_summary(sc, runs=2)
    p = np.array([15000.0, 15000.0])
    sites = np.array([[0.0, 0.0], [20000.0, 0.0]])
    d = p - sites
    G = np.stack([-d[:, 1], d[:, 0]], axis=1) / np.sum(d * d, axis=1)[:, None]
    J1 = G.T @ G / 0.0175**2
    assert crb["t"] == pytest.approx(np.arange(1.0, 41.0).tolist())
    for k in (0, 9, 39):
        assert crb["rmse_pos"][k] == pytest.approx(np.sqrt(np.trace(np.linalg.inv((k + 1) * J1))), rel=1e-10)
    assert np.array(crb["final_P"]) == pytest.approx(np.linalg.inv(40 * J1), rel=1e-10)


def test_scenario_bound_3d_with_jamming_is_weaker():
    """patent-3d-jammed: the jammer only removes information, so its bound is never below
    the unjammed one on the same target."""
    from sensors_sim import load_scenario
    from services.evaluation import crb_summary

    clean = crb_summary(load_scenario("patent-3d"), runs=3)
    jammed = crb_summary(load_scenario("patent-3d-jammed"), runs=3)
    assert clean["t"] == jammed["t"]
    assert np.all(np.array(jammed["rmse_pos"]) >= np.array(clean["rmse_pos"]) * (1 - 1e-9))
    assert max(np.array(jammed["rmse_pos"]) / np.array(clean["rmse_pos"])) > 1.05
    assert clean["rmse_pos"][0] == pytest.approx(jammed["rmse_pos"][0])


def test_centralised_filter_meets_the_bound_on_patent_3d():
    """The acceptance criterion, on fewer runs: the centralised EKF (SS) is within 25 % of
    the posterior CRB on position RMSE over the run, and not below it by more than
    Monte Carlo noise allows."""
    from sensors_sim import load_scenario
    from services.evaluation import Variant, evaluate

    doc = evaluate(load_scenario("patent-3d"), [Variant("SS", "SS")], 20)
    ratio = doc["methods"]["SS"]["rmse_pos"] / doc["crb"]["overall"]["rmse_pos"]
    assert 0.8 < ratio < 1.25
    assert doc["crb"]["t"] == doc["methods"]["SS"]["series"]["t"]
