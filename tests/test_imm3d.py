"""The 3D IMM (``motion = "imm"``, fusion/imm.py) and its models: the turn model against
the matrix exponential and quadrature, the IMM against FilterPy's ``IMMEstimator`` on a
linear case, against the single-model filter when one model has probability 1, NEES
consistency on a model-matched manoeuvre (χ² bounds), the configuration's errors, and
a reduced ``patent-3d-maneuver`` acceptance read from the eval JSON."""

from __future__ import annotations

import json

import numpy as np
import pytest
from filterpy.kalman import IMMEstimator, KalmanFilter
from scipy.integrate import quad_vec
from scipy.linalg import expm
from scipy.stats import chi2

from fusion.filters import filter_factory
from fusion.imm import ModelSet, TrackIMM, model_set
from fusion.methods import make_method
from fusion.motion import ConstantAcceleration, ConstantTurn, PaddedConstantVelocity
from fusion.patent import TrackerConfig
from fusion.sensors3d import Radar3D, TrackEKF
from fusion.types import Measurement
from services.cli import main


class LinearPosition:
    """``z = H x`` (position, Cartesian), duck-typed as a measurement model for TrackEKF."""

    def __init__(self, std: float, n_x: int = 9):
        self.H = np.hstack([np.eye(3), np.zeros((3, n_x - 3))])
        self.R = np.eye(3) * std**2
        self.n_z = 3

    def innovation_and_jacobian(self, z, x):
        return np.asarray(z, float) - self.H @ x, self.H


def _models(q=(0.5, 2.0, 4.0), rate=0.2):
    return [PaddedConstantVelocity(q[0]), ConstantTurn(q[1], rate), ConstantAcceleration(q[2])]


def test_turn_model_is_the_matrix_exponential_and_tends_to_ca():
    ct = ConstantTurn(2.0, 0.3)
    A = ct.A_axis()
    np.testing.assert_allclose(ct.F_axis(0.7), expm(A * 0.7), atol=1e-14)
    G = np.array([0.0, 0.0, 1.0])
    Qn = quad_vec(lambda s: 2.0 * expm(A * s) @ np.outer(G, G) @ expm(A.T * s), 0.0, 0.7)[0]
    np.testing.assert_allclose(ct.Q_axis(0.7), Qn, atol=1e-12)
    slow, ca = ConstantTurn(1.0, 1e-5), ConstantAcceleration(1.0)
    np.testing.assert_allclose(slow.F(1.0), ca.F(1.0), atol=1e-9)
    np.testing.assert_allclose(slow.Q(1.0), ca.Q(1.0), atol=1e-9)
    # a coordinated turn is a fixed point: a = ω × v stays so after any step
    w, v = 0.3, 200.0
    x = np.array([0, 0, 0, v, 0, 0, 0, w * v, 0.0])
    y = ct.F(2.0) @ x
    assert np.linalg.norm(y[3:6]) == pytest.approx(v) and np.linalg.norm(y[6:9]) == pytest.approx(w * v)
    assert y[3:6] @ y[6:9] == pytest.approx(0.0, abs=1e-9)
    cv = PaddedConstantVelocity(1.0)
    np.testing.assert_array_equal((cv.F(1.0) @ x)[6:], 0.0)


def test_imm_equals_filterpy_imm_estimator_on_a_linear_case():
    rng = np.random.default_rng(4)
    models = _models()
    Pi = np.array([[0.9, 0.05, 0.05], [0.1, 0.8, 0.1], [0.05, 0.15, 0.8]])
    mu0 = np.array([0.5, 0.3, 0.2])
    meas = LinearPosition(15.0)
    x0 = np.array([1000.0, 2000.0, 500.0, 100.0, -50.0, 0.0, 0.0, 0.0, 0.0])
    P0 = np.diag([100.0] * 3 + [400.0] * 3 + [25.0] * 3)
    imm = TrackIMM(ModelSet(models, Pi, mu0), [filter_factory("ekf", m) for m in models], x0, P0, 0.0)
    dt = 1.0
    kfs = []
    for m in models:
        kf = KalmanFilter(dim_x=9, dim_z=3)
        kf.x, kf.P = x0.copy(), P0.copy()
        kf.F, kf.Q, kf.H, kf.R = np.array(m.F(dt)), np.array(m.Q(dt)), meas.H, meas.R
        kfs.append(kf)
    ref = IMMEstimator(kfs, mu0.copy(), Pi)
    truth = x0.copy()
    for k in range(1, 25):
        truth = ConstantTurn(0.0, 0.1).F(dt) @ truth if k > 8 else models[0].F(dt) @ truth
        if k == 9:
            truth[6:8] = [0.0, 0.1 * np.hypot(*truth[3:5])]
        z = meas.H @ truth + rng.normal(0.0, 15.0, 3)
        imm.predict(k * dt)
        imm.update(meas, z)
        ref.predict()
        ref.update(z)
        np.testing.assert_allclose(imm.mu, ref.mu, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(imm.x, ref.x, rtol=1e-9, atol=1e-7)
        np.testing.assert_allclose(imm.P, ref.P, rtol=1e-9, atol=1e-7)
        for f, kf in zip(imm.filters, kfs):
            np.testing.assert_allclose(f.x, kf.x, rtol=1e-9, atol=1e-7)
    assert imm.mu[0] < 0.5  # the turn is not flown straight


def _radar_scans(n=30, seed=0):
    rng = np.random.default_rng(seed)
    std = np.array([np.radians(1.0), np.radians(1.0), 20.0])
    x = np.array([6000.0, 8000.0, 2000.0, -120.0, -60.0, 5.0, 0.0, 0.0, 0.0])
    out = []
    model = Radar3D(np.zeros(3), std)
    for k in range(n):
        p = x[:3] + x[3:6] * k
        z = model.h(np.concatenate([p, np.zeros(6)])) + rng.normal(0.0, std)
        out.append(Measurement(float(k), "r3", "az_el_range", z, std, np.zeros(3), k))
    return out


def test_one_model_of_probability_one_without_switching_is_that_filter():
    models = _models()
    ca = models[2]
    x0 = np.array([6000.0, 8000.0, 2000.0, -100.0, -50.0, 0.0, 0.0, 0.0, 0.0])
    P0 = np.diag([1e4] * 3 + [1e4] * 3 + [100.0] * 3)
    imm = TrackIMM(ModelSet(models, np.eye(3), [0.0, 0.0, 1.0]), [filter_factory("ekf", m) for m in models],
                   x0, P0, 0.0)
    ekf = TrackEKF(ca, x0, P0, 0.0)
    for m in _radar_scans()[1:]:
        model = Radar3D(m.site, m.std)
        imm.predict(m.t)
        ekf.predict(m.t)
        r_imm, r_ekf = imm.update(model, m.z), ekf.update(model, m.z)
        np.testing.assert_allclose(imm.x, ekf.x, rtol=1e-12, atol=1e-9)
        np.testing.assert_allclose(imm.P, ekf.P, rtol=1e-12, atol=1e-9)
        assert r_imm.nis == pytest.approx(r_ekf.nis, rel=1e-10)
        np.testing.assert_allclose(imm.KH, ekf.KH, atol=1e-8)
    np.testing.assert_array_equal(imm.mu, [0.0, 0.0, 1.0])


@pytest.mark.parametrize("method", ["SS", "PHHNV"])
def test_a_one_model_imm_through_the_tracker_config_is_the_ca_tracker(method):
    scans = _radar_scans(20, seed=3)
    base = {"init_vel_std": 1000.0, "init_acc_std": 100.0, "init_vel_std_up": 1000.0, "init_acc_std_up": 100.0}
    runs = {}
    for name, table in {"ca": {"motion": "ca", "q": 0.3},
                        "imm": {"motion": "imm", "imm_models": "ca", "imm_q_ca": 0.3, "imm_p_stay": 1.0}}.items():
        meth = make_method(method, {**base, **table})
        est = [e for m in scans for e in meth.process(m)] + meth.finish()
        runs[name] = [e for e in est if e.node == "centre"]
    assert len(runs["ca"]) == len(runs["imm"]) == len(scans)
    for a, b in zip(runs["ca"], runs["imm"]):
        np.testing.assert_allclose(b.x, a.x, rtol=1e-10, atol=1e-8)
        np.testing.assert_allclose(b.P, a.P, rtol=1e-10, atol=1e-8)


def _sample(model, x, dt, rng):
    Q = np.array(model.Q(dt))
    w, V = np.linalg.eigh(Q)
    return model.F(dt) @ x + V @ (np.sqrt(np.clip(w, 0.0, None)) * rng.standard_normal(w.size))


def test_nees_is_chi2_consistent_on_markov_switching_manoeuvres():
    """A truth that switches between the IMM's own models as its Markov chain says
    (CV, turn, CA, each with its process noise; the turn entered from the CV model's
    zero acceleration): the NEES averaged over runs and steps lies in its 99 % χ²
    interval, and most per-step averages lie in theirs."""
    rng = np.random.default_rng(11)
    models = _models(q=(0.05, 0.5, 1.0), rate=0.2)
    Pi = np.array([[0.9, 0.05, 0.05], [0.1, 0.85, 0.05], [0.1, 0.05, 0.85]])
    mset = ModelSet(models, Pi, [1.0, 0.0, 0.0])
    meas = LinearPosition(20.0)
    runs, steps, dt = 100, 40, 1.0
    nees = np.zeros((runs, steps))
    switched = 0
    for r in range(runs):
        truth = np.array([0.0, 0.0, 1000.0, 200.0, 0.0, 0.0, 0.0, 0.0, 0.0])
        P0 = np.diag([400.0] * 3 + [100.0] * 3 + [0.0] * 3)
        x0 = truth + np.sqrt(np.diag(P0)) * rng.standard_normal(9)
        imm = TrackIMM(mset, [filter_factory("ekf", m) for m in models], x0, P0, 0.0)
        mode = 0
        for k in range(steps):
            mode = rng.choice(3, p=Pi[mode])
            switched += mode != 0
            truth = _sample(models[mode], truth, dt, rng)
            z = meas.H @ truth + rng.normal(0.0, 20.0, 3)
            imm.predict((k + 1) * dt)
            imm.update(meas, z)
            e = imm.x - truth
            nees[r, k] = e @ np.linalg.pinv(imm.P, hermitian=True) @ e
    assert switched > 0.2 * runs * steps  # the truth manoeuvres
    n = 9
    lo, hi = chi2.ppf([0.005, 0.995], runs * steps * n) / (runs * steps)
    assert lo <= nees.mean() <= hi, nees.mean()
    slo, shi = chi2.ppf([0.005, 0.995], runs * n) / runs
    inside = np.mean((nees.mean(axis=0) >= slo) & (nees.mean(axis=0) <= shi))
    assert inside >= 0.8, inside


def test_config_errors_are_one_line_each(capsys):
    for table, message in [
        ({"motion": "imm", "imm_models": "cv,spiral"}, "imm_models"),
        ({"motion": "imm", "imm_models": "cv,cv"}, "imm_models"),
        ({"motion": "imm", "imm_p_stay": 0.0}, "imm_p_stay"),
        ({"motion": "imm", "imm_models": "ca", "imm_p_stay": 0.9}, "imm_p_stay"),
        ({"motion": "imm", "imm_turn_rate": -0.1}, "imm_turn_rate"),
        ({"motion": "imm", "imm_q_ct": -1.0}, "imm_q_ct"),
        ({"motion": "imm", "imm_q_ca": "big"}, "imm_q_ca"),
        ({"motion": "spiral"}, "motion"),
        ({"imm_bogus": 1.0}, "imm_bogus"),
    ]:
        with pytest.raises(ValueError, match=message):
            TrackerConfig.from_dict(table)
    with pytest.raises(ValueError):
        model_set(("cv",), {"cv": 1.0}, 0.1, 0.5)
    for bad in (["--set", "imm_p_stay=2.0"], ["--set", "imm_bogus=1"], ["--set", "motion=spiral"]):
        with pytest.raises(SystemExit) as exc:
            main(["eval", "--scenario", "patent-3d-maneuver", "--runs", "1", "--methods", "SS",
                  "--set", "motion=imm", *bad])
        assert exc.value.code != 0
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and "Traceback" not in err, err


def test_reduced_acceptance_on_patent_3d_maneuver(tmp_path):
    """``--runs 5`` of the acceptance: SS with ``motion=imm`` has at most 0.7× the
    position RMSE of ``motion=ca`` (the full 50-run numbers: docs/results/patent-3d-maneuver.md)."""
    docs = {}
    for motion in ("ca", "imm"):
        out = tmp_path / f"{motion}.json"
        assert main(["eval", "--scenario", "patent-3d-maneuver", "--runs", "5", "--methods", "SS",
                     "--set", f"motion={motion}", "--json", str(out)]) == 0
        docs[motion] = json.loads(out.read_text())["methods"]["SS"]
    assert docs["imm"]["rmse_pos"] <= 0.7 * docs["ca"]["rmse_pos"]
    assert docs["imm"]["nees_dof"] == 9


def test_committed_report_is_its_json():
    """docs/results/patent-3d-maneuver.md: every RMSE and band fraction is its JSON's, and
    each verdict follows from them."""
    from pathlib import Path

    root = Path(__file__).resolve().parent.parent / "docs" / "results"
    md = (root / "patent-3d-maneuver.md").read_text()
    found = {}
    for f in sorted((root / "patent-3d-maneuver").glob("*.json")):
        r = next(iter(json.loads(f.read_text())["methods"].values()))
        a = np.array(r["series"]["anees"], float)
        band = np.mean((a >= r["anees_bounds"][0]) & (a <= r["anees_bounds"][1]))
        motion = f.stem.rsplit("-", 1)[1]
        row = next(line for line in md.splitlines() if line.startswith("| ") and f" {motion} | {r['rmse_pos']:.2f} |" in line)
        assert row.rstrip(" |").endswith(f"{band:.2f}"), row
        found[f.stem] = (r["rmse_pos"], band)
    ss = found["SS-imm"][0] / found["SS-ca"][0]
    verdict = "holds" if ss <= 0.7 else "fails"
    assert f"| SS | — | {ss:.3f} | {verdict} |" in md


def test_an_imm_of_ukfs_runs_on_the_semi_definite_cv_model_and_agrees_with_the_ekf_one():
    """The CV model holds the acceleration with zero variance: the UKF's sigma points and
    K·H must accept a semi-definite covariance. On a straight radar track the IMM of
    UKFs and the IMM of EKFs give nearly one estimate."""
    scans = _radar_scans(25, seed=5)
    table = {"motion": "imm", "init_vel_std": 1000.0, "init_acc_std": 100.0,
             "init_vel_std_up": 1000.0, "init_acc_std_up": 100.0}
    out = {}
    for name in ("ekf", "ukf"):
        meth = make_method("SS", {**table, "filter": name})
        out[name] = [e for m in scans for e in meth.process(m)] + meth.finish()
    for a, b in zip(out["ekf"][5:], out["ukf"][5:]):
        assert np.linalg.norm(a.x[:3] - b.x[:3]) < 0.1 * np.sqrt(np.trace(a.P[:3, :3]))
        assert np.all(np.isfinite(b.P))
