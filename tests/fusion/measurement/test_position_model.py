"""The position kind in fusion/: its model against finite differences and FilterPy's
Kalman filter, a report's own covariance, stacking beside spherical rows, and a track
started from a lone position report (one target and many)."""

from __future__ import annotations

import numpy as np
import pytest
from filterpy.kalman import KalmanFilter

from fusion.filters import filter_factory
from fusion.init3d import InitPriors, initial_state
from fusion.measurement.kinds import KINDS, POINT, kinds_of, model_for, model_of, partners
from fusion.measurement.models import PositionModel, SphericalModel, StackedModel, stack
from fusion.methods import make_method
from fusion.motion import ConstantAcceleration
from fusion.mtt import scores_hit
from fusion.types import Measurement

DEG = np.pi / 180.0
X = np.array([6000.0, 8000.0, 2000.0, -120.0, -60.0, 5.0, 0.5, 1.0, -0.05])
CORR = np.array([[1.0, 0.3, -0.2], [0.3, 1.0, 0.1], [-0.2, 0.1, 1.0]])


def report(t, z, std=(30.0, 30.0, 45.0), corr=None, sensor="adsb", seq=0) -> Measurement:
    return Measurement(float(t), sensor, "position", np.asarray(z, float), np.asarray(std, float), np.zeros(3),
                       seq, None if corr is None else np.asarray(corr, float))


def test_the_position_kind_is_a_3d_point_that_states_its_own_noise():
    k = KINDS["position"]
    assert k.names == ("east", "north", "up") and k.family == "3d" and k.start == POINT
    assert not k.sited and k.own_noise and k.fixes_range
    assert "position" in kinds_of("3d") and partners("position") == frozenset()
    assert not k.angles.any()


@pytest.mark.parametrize("n_x", [6, 9])
def test_h_and_jacobian_match_central_differences(n_x):
    rng = np.random.default_rng(5)
    m = model_for("position", [123.0, -4.0, 7.0], (30.0, 30.0, 45.0), n_x)  # the site does not enter
    for x in rng.normal(0.0, 5e3, (50, n_x)):
        H = m.jacobian(x)
        Hfd = np.column_stack([(m.h(x + e) - m.h(x - e)) / 2.0 for e in np.eye(n_x)])
        np.testing.assert_allclose(H, Hfd, rtol=0, atol=1e-9)
        np.testing.assert_array_equal(m.h(x), x[:3])
    np.testing.assert_array_equal(H, np.hstack([np.eye(3), np.zeros((3, n_x - 3))]))
    xs = rng.normal(0.0, 5e3, (4, 7, n_x))
    np.testing.assert_array_equal(m.h(xs), xs[..., :3])  # vectorised over states (the UKF's sigma points)
    z = m.h(xs[0, 0]) + 1.0
    nu, H = m.innovation_and_jacobian(z, xs[0, 0])
    np.testing.assert_allclose(nu, [1.0, 1.0, 1.0], rtol=0, atol=1e-9)


def test_a_report_s_own_covariance_is_its_model_s_R():
    std = np.array([20.0, 35.0, 50.0])
    m = model_of(report(0.0, X[:3], std, CORR))
    np.testing.assert_array_equal(m.R, np.outer(std, std) * CORR)
    np.testing.assert_array_equal(m.R, report(0.0, X[:3], std, CORR).R)
    np.testing.assert_array_equal(model_of(report(0.0, X[:3], std)).R, np.diag(std**2))
    with pytest.raises(ValueError, match="positive definite"):
        PositionModel(np.outer(std, std) * np.array([[1.0, 0.99, 0.99], [0.99, 1.0, -0.99], [0.99, -0.99, 1.0]]))
    with pytest.raises(ValueError, match="symmetric"):
        PositionModel(np.diag(std**2) + np.triu(np.ones((3, 3)), 1))
    with pytest.raises(ValueError, match="correlation matrix is 3×3"):
        model_of(report(0.0, X[:3], std, np.eye(2)))


def _ca_reference(x0, P0, reports, q):
    """FilterPy's linear Kalman filter on the same CA model and the same reports."""
    motion = ConstantAcceleration(q)
    kf = KalmanFilter(dim_x=9, dim_z=3)
    kf.x, kf.P = x0.copy(), P0.copy()
    kf.H = np.hstack([np.eye(3), np.zeros((3, 6))])
    t = 0.0
    for m in reports:
        kf.F, kf.Q = motion.F(m.t - t), motion.Q(m.t - t)
        kf.predict()
        kf.update(m.z, R=m.R)
        t = m.t
    return kf.x, kf.P


@pytest.mark.parametrize("name", ["ekf", "ukf"])
def test_a_filter_on_position_reports_is_filterpy_s_kalman_filter(name):
    rng = np.random.default_rng(7)
    q = 0.5
    P0 = np.diag([900.0, 900.0, 2000.0, 1e4, 1e4, 400.0, 25.0, 25.0, 4.0])
    reports, x, t = [], X.copy(), 0.0
    motion = ConstantAcceleration(q)
    for k in range(30):
        dt = rng.uniform(0.5, 2.0)
        t += dt
        x = motion.F(dt) @ x
        std = rng.uniform(10.0, 80.0, 3)  # every report its own noise, correlated
        corr = CORR if k % 2 else None
        reports.append(report(t, x[:3] + rng.normal(0.0, 1.0, 3) * std, std, corr, seq=k))
    f = filter_factory(name, motion)(X, P0, 0.0)
    for m in reports:
        f.predict(m.t)
        f.update(model_of(m), np.asarray(m.z))
    x_ref, P_ref = _ca_reference(X, P0, reports, q)
    np.testing.assert_allclose(f.x, x_ref, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(f.P, P_ref, rtol=1e-9, atol=1e-9 * np.abs(P_ref).max())


def test_ss_stacks_a_position_report_beside_the_spherical_rows():
    radar = Measurement(0.0, "radar2d", "range_az", np.array([0.64, 10200.0]), np.array([DEG, 20.0]), np.zeros(3))
    angle = Measurement(0.0, "angle", "azel", np.array([0.64, 0.2]), np.array([1e-3, 1e-3]), np.zeros(3))
    pos = report(0.0, X[:3] + 10.0, corr=CORR)
    models = [model_of(m) for m in (angle, radar, pos)]
    s = stack(models)
    assert isinstance(s, StackedModel) and isinstance(s.blocks[0], SphericalModel) and s.blocks[1] is models[2]
    assert s.components == ("az", "el", "az", "range", "east", "north", "up")
    np.testing.assert_array_equal(s.R[4:, 4:], pos.R)
    np.testing.assert_array_equal(s.R[:4, 4:], 0.0)
    np.testing.assert_array_equal(s.h(X)[4:], X[:3])
    np.testing.assert_array_equal(s.jacobian(X)[4:, :3], np.eye(3))


def test_a_lone_position_report_starts_a_track_at_its_point():
    pos = report(0.0, X[:3], corr=CORR)
    x, P = initial_state([pos], 9, InitPriors(vel_std=300.0))
    np.testing.assert_array_equal(x[:3], X[:3])
    np.testing.assert_array_equal(x[3:], 0.0)
    np.testing.assert_allclose(P[:3, :3], pos.R, rtol=1e-15)
    np.testing.assert_allclose(np.diag(P)[3:5], 300.0**2)
    # a scan with a radar and an angle sensor too: the position report's point (smallest tr R)
    radar = Measurement(0.0, "radar2d", "range_az", np.array([0.64, 10200.0]), np.array([DEG, 20.0]), np.zeros(3))
    better = report(0.0, X[:3] + 1.0, (5.0, 5.0, 5.0), sensor="adsb2")
    x2, P2 = initial_state([radar, pos, better], 9)
    np.testing.assert_array_equal(x2[:3], X[:3] + 1.0)
    np.testing.assert_allclose(P2[:3, :3], better.R, rtol=1e-15)


def test_a_confirmed_track_fed_by_position_reports_alone_scores_hits():
    assert scores_hit(["position"], confirmed=True, evidence=2)  # it fixes a point, as a radar fixes a range
    assert not scores_hit(["azel"], confirmed=True, evidence=2)
    assert not scores_hit(["position"], confirmed=False, evidence=2)


def test_the_many_target_tracker_starts_tracks_from_lone_position_reports():
    """Two aircraft seen by position reports alone: each lone report starts a tentative
    track at its point, the next reports confirm them (M of N), and each confirmed track
    follows its aircraft."""
    rng = np.random.default_rng(11)
    truths = [np.array([5000.0, 2000.0, 3000.0, 150.0, 0.0, 0.0, 0, 0, 0]),
              np.array([-4000.0, 6000.0, 9000.0, 0.0, -200.0, 0.0, 0, 0, 0])]
    motion = ConstantAcceleration(0.01)
    method = make_method("SS", {"association": "gnn", "confirm_m": 3, "confirm_n": 4, "motion": "ca", "q": 0.01,
                                "init_vel_std": 300.0})
    out, seq = [], 0
    for k in range(8):
        t = float(k)
        for i, x0 in enumerate(truths):
            p = (motion.F(t) @ x0)[:3]
            out += method.process(report(t, p + rng.normal(0.0, 30.0, 3), sensor="adsb", seq=seq))
            seq += 1
        out += method.advance(t + 0.5)
    out += method.finish()
    last = {}
    for e in out:
        last[e.track] = e
    assert len(last) == 2, sorted(last)
    for e in last.values():
        errors = [np.linalg.norm(e.x[:3] - (motion.F(e.t) @ x0)[:3]) for x0 in truths]
        assert min(errors) < 100.0, errors
        assert {e.track for e in out if e.t < 2.0} == set()  # confirmed at the third report
