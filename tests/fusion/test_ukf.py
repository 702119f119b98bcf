"""The UKF of a 3D track (fusion.ukf) against Stone Soup's UnscentedKalmanPredictor /
UnscentedKalmanUpdater on the same data with the same sigma-point parameters, its
``K·H`` identity, and its consistency (NEES, χ²) on patent-3d behind the ``filter``
key of the ``[tracker]`` table."""

from __future__ import annotations

import datetime as dt
import os

import numpy as np
import pytest
from scipy.stats import chi2

from sim3d import centre_track, nees, run_method, scenario_runs  # noqa: E402

from fusion.methods import make_method, method_config  # noqa: E402
from fusion.motion import make_motion  # noqa: E402
from fusion.measurement.models import SphericalModel  # noqa: E402
from fusion.ukf import TrackUKF  # noqa: E402
from sensors_sim import load_scenario  # noqa: E402

from stonesoup.base import Property  # noqa: E402
from stonesoup.models.measurement.nonlinear import CartesianToElevationBearing, CartesianToElevationBearingRange  # noqa: E402
from stonesoup.models.transition.linear import LinearGaussianTransitionModel  # noqa: E402
from stonesoup.predictor.kalman import UnscentedKalmanPredictor  # noqa: E402
from stonesoup.types.angle import Bearing, Elevation  # noqa: E402
from stonesoup.types.detection import Detection  # noqa: E402
from stonesoup.types.hypothesis import SingleHypothesis  # noqa: E402
from stonesoup.types.state import GaussianState, StateVector  # noqa: E402
from stonesoup.updater.kalman import UnscentedKalmanUpdater  # noqa: E402

T0 = dt.datetime(2026, 1, 1)
ENU_TO_SS = (1, 0, 2)  # Stone Soup's x, y, z = north, east, up: its bearing atan2(y, x) is our azimuth


class Motion(LinearGaussianTransitionModel):
    """Our motion model's F and Q as a Stone Soup transition model."""

    motion: object = Property()

    @property
    def ndim_state(self):
        return self.motion.n_x

    def matrix(self, time_interval, **kwargs):
        return self.motion.F(time_interval.total_seconds())

    def covar(self, time_interval, **kwargs):
        return self.motion.Q(time_interval.total_seconds())


def _trajectory(motion, steps: int, seed: int):
    rng = np.random.default_rng(seed)
    x = np.array([8000.0, 12000.0, 3000.0, -150.0, 60.0, 4.0, 1.0, -2.0, 0.1])
    out = []
    for _ in range(steps):
        x = motion.F(1.5) @ x + rng.multivariate_normal(np.zeros(x.size), motion.Q(1.5))
        out.append(x)
    return out


CASES = {  # our components, their Stone Soup order, the Stone Soup model class
    "az_el_range": (("az", "el", "range"), (1, 0, 2), CartesianToElevationBearingRange),
    "azel": (("az", "el"), (1, 0), CartesianToElevationBearing),
}


@pytest.mark.parametrize("kind", CASES)
@pytest.mark.parametrize("alpha, beta, kappa", [(0.5, 2.0, 0.0), (1.0, 2.0, -6.0), (0.3, 1.0, 2.0)])
def test_ukf_equals_stone_soup(kind, alpha, beta, kappa):
    components, order, ss_model = CASES[kind]
    std = np.array([{"az": 0.01, "el": 0.02, "range": 30.0}[c] for c in components])
    site = np.array([500.0, -300.0, 20.0])
    motion = make_motion("ca", 0.5)
    model = SphericalModel(components, site, std, motion.n_x)
    mm = ss_model(ndim_state=motion.n_x, mapping=ENU_TO_SS, noise_covar=np.diag(std[list(order)] ** 2),
                  translation_offset=StateVector(site[list(ENU_TO_SS)]))
    predictor = UnscentedKalmanPredictor(Motion(motion=motion), alpha=alpha, beta=beta, kappa=kappa)
    updater = UnscentedKalmanUpdater(mm, alpha=alpha, beta=beta, kappa=kappa)

    rng = np.random.default_rng(7)
    x0 = np.array([7000.0, 11000.0, 2500.0, -100.0, 50.0, 0.0, 0.0, 0.0, 0.0])
    P0 = np.diag([600.0, 600.0, 400.0, 80.0, 80.0, 30.0, 5.0, 5.0, 2.0]) ** 2
    ukf = TrackUKF(motion, x0, P0, 0.0, alpha, beta, kappa)
    state = GaussianState(StateVector(x0), P0, timestamp=T0)
    for k, truth in enumerate(_trajectory(motion, 12, 3), start=1):
        t = 1.5 * k
        z = model.h(truth) + rng.normal(0.0, std)
        z_ss = [Elevation(z[1]) if o == 1 else Bearing(z[0]) if o == 0 else z[2] for o in order]
        when = T0 + dt.timedelta(seconds=t)
        prediction = predictor.predict(state, timestamp=when)
        hyp = SingleHypothesis(prediction, Detection(StateVector(z_ss), timestamp=when, measurement_model=mm))
        state = updater.update(hyp)

        ukf.predict(t)
        np.testing.assert_allclose(ukf.x, np.asarray(prediction.state_vector, float).ravel(), rtol=1e-10, atol=1e-8)
        np.testing.assert_allclose(ukf.P, np.asarray(prediction.covar, float), rtol=1e-9, atol=1e-7)
        res = ukf.update(model, z)
        np.testing.assert_allclose(ukf.x, np.asarray(state.state_vector, float).ravel(), rtol=1e-10, atol=1e-8)
        np.testing.assert_allclose(ukf.P, np.asarray(state.covar, float), rtol=1e-8, atol=1e-7)
        S_ss = np.asarray(hyp.measurement_prediction.covar, float)
        np.testing.assert_allclose(res.S[np.ix_(order, order)], S_ss, rtol=1e-9, atol=1e-12)


def test_kh_is_the_statistical_linearisation():
    """``P⁺ = (I − K·H) P⁻`` for the UKF's ``K·H``, as the fusion rules assume of every filter."""
    motion = make_motion("ca", 0.5)
    model = SphericalModel(("az", "el"), np.zeros(3), [0.01, 0.02], motion.n_x)
    x = np.array([7000.0, 11000.0, 2500.0, -100.0, 50.0, 0.0, 0.0, 0.0, 0.0])
    ukf = TrackUKF(motion, x, np.diag([3000.0, 3000.0, 2000.0, 80.0, 80.0, 30.0, 5.0, 5.0, 2.0]) ** 2, 0.0)
    ukf.predict(1.0)
    prior = ukf.P
    ukf.update(model, model.h(ukf.x) + np.array([0.004, -0.01]))
    np.testing.assert_allclose((np.eye(9) - ukf.KH) @ prior, ukf.P, rtol=1e-9, atol=1e-9 * np.abs(prior).max())


@pytest.mark.parametrize("name", ["SS", "HNV", "DDHNV"])
def test_the_filter_key_chooses_every_track_filter(name):
    """``filter = "ukf"`` reaches the centralised filter, the local trackers and the
    tracks of the many-target managers; an unknown filter is refused."""
    sim = scenario_runs("patent-3d", 1)
    for table in ({"filter": "ukf"}, {"filter": "ukf", "association": "gnn"}):
        method = make_method(name, dict(table))
        run_method(method, sim.measurements[0][:40])
        if hasattr(method, "nodes"):  # split: its local trackers
            trackers = [tr for node in method.nodes.values()
                        for tr in (node.tracks.values() if hasattr(node, "tracks") else [node.tracker])]
            filters = [tr.filter for tr in trackers]
        else:
            filters = [tr.filter for tr in method.tracks] if hasattr(method, "tracks") else [method.filter]
        assert filters and all(isinstance(f, TrackUKF) for f in filters)
    with pytest.raises(ValueError, match="'filter' must be one of"):
        make_method(name, {"filter": "pf"})


# Consistency on patent-3d ------------------------------------------------------------------
N_RUNS, FIRST = 200, 5
SEED = int(os.environ.get("ZF_MC_SEED", "1"))


@pytest.mark.slow
@pytest.mark.parametrize("method", ["SS", "PHHNV"])
def test_ukf_is_consistent_on_patent_3d(method):
    """NEES of the UKF (the scenario's consistent configuration of the method, with
    ``filter = "ukf"``) over 200 runs: the mean over runs of each run's NEES averaged over
    scans 5… (independent across runs) within 4 standard errors of 9, and the
    run-averaged NEES inside the two-sided 99.9 % χ²(200·9)/200 band at ≥ 90 % of those
    scans — each fails about one batch in a thousand for a consistent filter."""
    sim = scenario_runs("patent-3d", N_RUNS, SEED)
    table = load_scenario("patent-3d").tracker
    cfg = {**method_config(table, method), "filter": "ukf"}
    if method == "PHHNV":
        cfg.update(fusion_rule="bar-shalom-campo", init_vel_std=1e3, init_vel_std_up=1e3, init_acc_std=1e2,
                   init_acc_std_up=1e2)
    tracks = [centre_track(run_method(make_method(method, cfg), meas)) for meas in sim.measurements]
    n = np.array([nees(sim.truth[r], tr[1], tr[2]) for r, tr in enumerate(tracks)])
    per_run = n[:, FIRST:].mean(axis=1)
    z = (per_run.mean() - 9) / (per_run.std(ddof=1) / np.sqrt(N_RUNS))
    lo, hi = chi2.ppf([0.0005, 0.9995], 9 * N_RUNS) / N_RUNS
    a = n[:, FIRST:].mean(axis=0)
    inside = np.mean((a >= lo) & (a <= hi))
    assert abs(z) < 4.0 and inside >= 0.9, f"level z {z:+.2f}, {inside:.0%} inside; ANEES {np.round(a, 2).tolist()}"
