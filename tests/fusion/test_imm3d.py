"""The 3D IMM (``motion = "imm"``, fusion/imm.py) and its models: the turn model against
the matrix exponential and quadrature, the IMM against FilterPy's ``IMMEstimator`` on a
linear case, against the single-model filter when one model has probability 1, NEES
consistency on a model-matched manoeuvre (χ² bounds), the configuration's errors, and
a reduced ``patent-3d-maneuver`` acceptance read from the eval JSON, and its report
(``python -m services.report patent-3d-maneuver``) against its JSON."""

from __future__ import annotations

import json

import numpy as np
import pytest
from filterpy.kalman import IMMEstimator, KalmanFilter
from scipy.integrate import quad_vec
from scipy.linalg import expm
from scipy.stats import chi2

from fusion.ekf import TrackEKF
from fusion.filters import filter_factory
from fusion.imm import ModelSet, TrackIMM, model_set
from fusion.measurement.kinds import model_for
from fusion.methods import make_method
from fusion.motion import ConstantAcceleration, ConstantTurn, CoordinatedTurn, PaddedConstantVelocity
from fusion.patent import TrackerConfig
from fusion.types import Measurement
from services.cli import main
from conftest import ROOT


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


def test_coordinated_turn_takes_its_rate_from_the_state():
    """``turn``: its Jacobian is the central finite difference of ``f`` (turning, general and
    straight states); at a turning state it is the fixed-rate model at that state's rate; at
    ``a = 0`` the CA model; and it flies a 6 g level turn as the truth's closed form does."""
    from sensors_sim.segments import CoordinatedTurn as TruthTurn

    md, dt = CoordinatedTurn(3.0), 1.0
    turning = np.array([100.0, -50.0, 3000.0, 250.0, 0.0, 0.0, 0.0, -39.2, 0.0])
    general = np.array([1.0, 2.0, 3.0, 200.0, 30.0, 5.0, 3.0, -20.0, 1.0])
    straight = np.array([0.0, 0.0, 3000.0, 180.0, -60.0, 2.0, 0.0, 0.0, 0.0])
    for x in (turning, general, straight):
        fx, J, Q = md.transition(x, dt)
        h = 1e-4 * np.maximum(1.0, np.abs(x))
        Jn = np.column_stack([(md.transition(x + h[i] * e, dt)[0] - md.transition(x - h[i] * e, dt)[0]) / (2 * h[i])
                              for i, e in enumerate(np.eye(9))])
        assert np.allclose(J, Jn, rtol=1e-6, atol=1e-7), np.abs(J - Jn).max()
        assert np.allclose(Q, Q.T) and np.all(np.linalg.eigvalsh(Q) > -1e-12)
    w = 39.2 / 250.0
    fx, J, Q = md.transition(turning, dt)
    ct = ConstantTurn(3.0, w)
    assert np.allclose(fx, ct.F(dt) @ turning, rtol=1e-12, atol=1e-9) and np.allclose(Q, ct.Q(dt), rtol=1e-10)
    fx, J, Q = md.transition(straight, dt)
    ca = ConstantAcceleration(3.0)
    assert np.allclose(fx, ca.F(dt) @ straight) and np.allclose(J, ca.F(dt)) and np.allclose(Q, ca.Q(dt))
    rate = 6.0 * 9.80665 / 250.0
    x0 = np.array([-6000.0, 9000.0, 3000.0, 250.0, 0.0, 0.0])
    truth = TruthTurn(rate=rate, duration=20.0).plan(np.r_[x0, np.zeros(3)])
    x = truth.state(0.0)
    for k in range(20):
        x = md.transition(x, dt)[0]
    assert np.allclose(x, truth.state(20.0), rtol=1e-9, atol=1e-6)


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
    model = model_for("az_el_range", np.zeros(3), std)
    for k in range(n):
        p = x[:3] + x[3:6] * k
        z = model.h(np.concatenate([p, np.zeros(6)])) + rng.normal(0.0, std)
        out.append(Measurement(float(k), "r3", "az_el_range", z, std, np.zeros(3), k))
    return out


@pytest.mark.parametrize("last", ["ca", "turn"])
def test_one_model_of_probability_one_without_switching_is_that_filter(last):
    """Also for the state-dependent ``turn`` model: the IMM's cycle predicts it as its EKF does."""
    models = _models()
    if last == "turn":
        models[2] = CoordinatedTurn(4.0)
    ca = models[2]
    x0 = np.array([6000.0, 8000.0, 2000.0, -100.0, -50.0, 0.0, 0.0, 0.0, 0.0])
    P0 = np.diag([1e4] * 3 + [1e4] * 3 + [100.0] * 3)
    imm = TrackIMM(ModelSet(models, np.eye(3), [0.0, 0.0, 1.0]), [filter_factory("ekf", m) for m in models],
                   x0, P0, 0.0)
    ekf = TrackEKF(ca, x0, P0, 0.0)
    for m in _radar_scans()[1:]:
        model = model_for("az_el_range", m.site, m.std)
        imm.predict(m.t)
        ekf.predict(m.t)
        r_imm, r_ekf = imm.update(model, m.z), ekf.update(model, m.z)
        np.testing.assert_allclose(imm.x, ekf.x, rtol=1e-12, atol=1e-9)
        np.testing.assert_allclose(imm.P, ekf.P, rtol=1e-12, atol=1e-9)
        assert r_imm.nis == pytest.approx(r_ekf.nis, rel=1e-10)
        np.testing.assert_allclose(imm.KH, ekf.KH, atol=1e-8)
    np.testing.assert_array_equal(imm.mu, [0.0, 0.0, 1.0])
    if last == "turn":
        assert np.linalg.norm(ekf.x[6:]) > 0.1  # the scans turn it: the state-dependent rate is exercised


@pytest.mark.parametrize("method", ["SS", "PHHNV"])
def test_a_one_model_imm_through_the_tracker_config_is_the_ca_tracker(method):
    scans = _radar_scans(20, seed=3)
    base = {"init_vel_std": 1000.0, "init_acc_std": 100.0, "init_vel_std_up": 1000.0, "init_acc_std_up": 100.0}
    runs = {}
    for name, table in {"ca": {"motion": "ca", "q": 0.3},
                        "imm": {"motion": "imm", "imm_models": "ca", "imm_q_ca": 0.3}}.items():
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


def test_sojourn_times_give_the_continuous_time_markov_chain():
    """``Π(dt) = exp(G dt)``: for two models (leaving rates λ₁ = 1/τ₁, λ₂ = 1/τ₂) the closed
    form ``Π₁₁ = (λ₂ + λ₁ e^{−(λ₁+λ₂) dt}) / (λ₁ + λ₂)``; for three, the semigroup
    ``Π(a + b) = Π(a) Π(b)``, rows of probabilities, and ``1 − Πᵢᵢ(dt) ≈ dt/τᵢ`` for a
    short dt, the exits shared equally. The ``[tracker]`` set: one CT model per rate."""
    cv, ca = PaddedConstantVelocity(1.0), ConstantAcceleration(1.0)
    two = ModelSet([cv, ca], sojourn=[20.0, 2.0])
    l1, l2 = 1 / 20.0, 1 / 2.0
    for dt in (0.3, 1.0, 4.0):
        Pi = two.transition(dt)
        assert Pi[0, 0] == pytest.approx((l2 + l1 * np.exp(-(l1 + l2) * dt)) / (l1 + l2), rel=1e-12)
        assert Pi[1, 1] == pytest.approx((l1 + l2 * np.exp(-(l1 + l2) * dt)) / (l1 + l2), rel=1e-12)
    three = ModelSet(_models(), sojourn=[20.0, 15.0, 2.0])
    np.testing.assert_allclose(three.transition(1.7), three.transition(1.0) @ three.transition(0.7), atol=1e-14)
    np.testing.assert_allclose(three.transition(1.0).sum(axis=1), 1.0, atol=1e-14)
    small = three.transition(1e-4)
    np.testing.assert_allclose(1 - np.diag(small), 1e-4 / np.array([20.0, 15.0, 2.0]), rtol=1e-3)
    assert small[2, 0] == pytest.approx(small[2, 1], rel=1e-3)
    np.testing.assert_array_equal(ModelSet([ca], sojourn=[5.0]).transition(1.0), [[1.0]])
    mset = TrackerConfig.from_dict({"motion": "imm", "imm_turn_rates": "0.1,0.2,0.3"}).motion_model()
    assert mset.names == ("cv", "ct", "ct", "ct", "ca")
    assert [md.turn_rate for md in mset.models[1:4]] == [0.1, 0.2, 0.3]
    with pytest.raises(ValueError, match="not both"):
        ModelSet([cv, ca], np.eye(2), sojourn=[1.0, 1.0])


def test_config_errors_are_one_line_each(capsys):
    for table, message in [
        ({"motion": "imm", "imm_models": "cv,spiral"}, "imm_models"),
        ({"motion": "imm", "imm_models": "cv,cv"}, "imm_models"),
        ({"motion": "imm", "imm_sojourn_cv": 0.0}, "imm_sojourn_cv"),
        ({"motion": "imm", "imm_sojourn_ca": -2.0}, "imm_sojourn_ca"),
        ({"motion": "imm", "imm_turn_rates": "0.1,-0.2"}, "imm_turn_rates"),
        ({"motion": "imm", "imm_turn_rates": "fast"}, "imm_turn_rates"),
        ({"motion": "imm", "imm_q_ct": -1.0}, "imm_q_ct"),
        ({"motion": "imm", "imm_q_ca": "big"}, "imm_q_ca"),
        ({"motion": "spiral"}, "motion"),
        ({"imm_bogus": 1.0}, "imm_bogus"),
    ]:
        with pytest.raises(ValueError, match=message):
            TrackerConfig.from_dict(table)
    with pytest.raises(ValueError):
        model_set(("cv",), {"cv": 1.0}, (), {"cv": -1.0})
    with pytest.raises(ValueError):
        model_set(("cv", "ct"), {"cv": 1.0, "ct": 1.0}, (), {"cv": 1.0, "ct": 1.0})
    for bad in (["--set", "imm_sojourn_ct=0"], ["--set", "imm_bogus=1"], ["--set", "motion=spiral"]):
        code = main(["eval", "--scenario", "patent-3d-maneuver", "--runs", "1", "--methods", "SS",
                     "--set", "motion=imm", *bad])
        assert code == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and "Traceback" not in err, err


def test_bar_shalom_campo_refuses_local_imms_in_one_line(capsys):
    """Its cross-covariances are built from each local update's K·H, which a mixture of
    models does not have: before the check HNV ran on to a fused covariance that was not
    positive definite (a negative ANEES), PHHNV stopped with an indefinite innovation."""
    for method in ("HNV", "PHHNV", "DDHNV"):
        code = main(["eval", "--scenario", "patent-3d-maneuver", "--runs", "1", "--methods", method,
                     "--fusion-rule", "bar-shalom-campo", "--set", "motion=imm"])
        assert code == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and "bar-shalom-campo" in err and "'info'" in err, err


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


def _md_rows(md: str, first_header: str) -> list[dict[str, str]]:
    """The rows of the Markdown table whose header row starts with ``first_header``."""
    lines = md.splitlines()
    i = next(k for k, line in enumerate(lines) if line.startswith(f"| {first_header} |"))
    head = [c.strip() for c in lines[i].strip("|").split("|")]
    rows = []
    for line in lines[i + 2:]:
        if not line.startswith("|"):
            break
        rows.append(dict(zip(head, (c.strip() for c in line.strip("|").split("|")))))
    return rows


def check_maneuver_report(md: str, bundle: dict) -> int:
    """Every row of the report's tables against its JSON: RMSE and band fractions recomputed
    here from the per-scan series and χ² quantiles, verdicts from the criteria's numbers."""
    ms, runs = bundle["evaluation"]["methods"], bundle["runs"]
    lo6, hi6 = chi2.ppf([0.025, 0.975], 6 * runs) / runs
    n = 0
    for row in _md_rows(md, "method | fusion rule | motion"):
        key = "-".join(x for x in (row["method"], row["fusion rule"].replace("—", ""), row["motion"]) if x)
        m = ms[key]
        lo, hi = chi2.ppf([0.025, 0.975], 9 * runs) / runs
        assert np.allclose(m["anees_bounds"], [lo, hi])
        a = np.array([np.inf if v is None else v for v in m["series"]["anees"]], float)
        assert row["pos RMSE (m)"] == f"{m['rmse_pos']:.2f}" and row["in band"] == f"{np.mean((a >= lo) & (a <= hi)):.2f}"
        n += 1
    for row in _md_rows(md, "method | fusion rule | RMSE imm / ca"):
        rule = row["fusion rule"].replace("—", "")
        imm, ca = (ms["-".join(x for x in (row["method"], rule, mo) if x)] for mo in ("imm", "ca"))
        q = imm["rmse_pos"] / ca["rmse_pos"]
        a = np.array([np.inf if v is None else v for v in imm["series"]["anees"]], float)
        f = np.mean((a >= imm["anees_bounds"][0]) & (a <= imm["anees_bounds"][1]))
        assert row["RMSE imm / ca"] == f"{q:.3f}" and row["≤ 0.7"] == ("holds" if q <= 0.7 else "fails"), row
        assert row["in band (imm)"] == f"{f:.2f}" and row["≥ 0.8"] == ("holds" if f >= 0.8 else "fails"), row
        n += 1
    ss = ms["SS-imm"]
    a9 = np.array(ss["series"]["anees"], float)
    pv = dict(zip(bundle["pv_anees"]["t"], bundle["pv_anees"]["anees"]))
    a6 = np.array([pv[t] for t in ss["series"]["t"]], float)
    total = _md_rows(md, "phase")[-1]
    lo, hi = ss["anees_bounds"]
    assert total["scans"] == str(a9.size)
    assert total["in (9)"] == str(int(np.sum((a9 >= lo) & (a9 <= hi)))) and total["below (9)"] == str(int(np.sum(a9 < lo)))
    assert total["in (6)"] == str(int(np.sum((a6 >= lo6) & (a6 <= hi6)))) and total["below (6)"] == str(int(np.sum(a6 < lo6)))
    return n


def test_committed_maneuver_report_is_its_json():
    """docs/results/patent-3d-maneuver.md: every number of its tables is its JSON's, each
    verdict follows from them, and PHHNV with ``info`` is the centralised IMM."""
    root = ROOT / "docs" / "results"
    bundle = json.loads((root / "patent-3d-maneuver.json").read_text())
    md = (root / "patent-3d-maneuver.md").read_text()
    assert bundle["command"] in md and check_maneuver_report(md, bundle) == 6 + 3
    ms = bundle["evaluation"]["methods"]
    assert np.allclose(ms["SS-imm"]["series"]["rmse_pos"], ms["PHHNV-info-imm"]["series"]["rmse_pos"], atol=1e-6)


def test_tiny_maneuver_report_tables_equal_their_json(tmp_path):
    """One run of ``python -m services.report patent-3d-maneuver``: tables = JSON; the
    position–velocity NEES is the one recomputed from an eval run's estimates."""
    from services.evaluation import run_method
    from services.report import build_maneuver, write_maneuver_report
    from services.scoring import truth_function
    from sensors_sim import load_scenario

    bundle = build_maneuver(runs=1)
    md = write_maneuver_report(bundle, tmp_path).read_text()
    assert check_maneuver_report(md, json.loads((tmp_path / "patent-3d-maneuver.json").read_text())) == 6 + 3
    sc = load_scenario("patent-3d-maneuver")
    truth = truth_function(sc)
    e = [e for e in run_method(sc, "SS", {"motion": "imm"}, 0) if e.node == "centre"][30]
    err = e.x[:6] - truth(0, e.track, e.t)[:6]
    k = bundle["pv_anees"]["t"].index(e.t)
    assert bundle["pv_anees"]["anees"][k] == pytest.approx(err @ np.linalg.inv(np.asarray(e.P)[:6, :6]) @ err, rel=1e-9)


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


def test_per_model_info_fusion_is_the_stacked_update_and_its_likelihood():
    """One model of the per-model info fusion (fusion.track_fusion.fuse_info_model): two
    linear updates of one prior, fused, are the stacked Kalman update, and the fused
    log-likelihood is ``log N(z; H x̄, H P̄ Hᵀ + R)`` of the stacked measurement; with a
    prior that holds some coordinates exactly (the CV model's acceleration), on the rest."""
    from fusion.kalman import gaussian_loglikelihood, update
    from fusion.track_fusion import fuse_info_model

    rng = np.random.default_rng(4)
    n = 6
    A = rng.normal(size=(n, n))
    P_c = A @ A.T + np.eye(n)
    P_c[4:, :] = P_c[:, 4:] = 0.0  # two coordinates known exactly
    x_c = rng.normal(size=n)
    Hs = [rng.normal(size=(2, n)), rng.normal(size=(3, n))]
    Rs = [np.diag([0.5, 2.0]), np.diag([1.0, 0.3, 0.7])]
    zs = [H @ x_c + rng.normal(size=H.shape[0]) for H in Hs]
    local = [update(x_c, P_c, z - H @ x_c, H, R) for H, R, z in zip(Hs, Rs, zs)]
    lls = [gaussian_loglikelihood(r.nu, r.S) for r in local]
    xf, Pf, ll = fuse_info_model([r.x for r in local], [r.P for r in local], [x_c, x_c], [P_c, P_c], lls, x_c, P_c)
    H, R, z = np.vstack(Hs), np.diag(np.concatenate([np.diag(R) for R in Rs])), np.concatenate(zs)
    ref = update(x_c, P_c, z - H @ x_c, H, R)
    np.testing.assert_allclose(xf, ref.x, atol=1e-10)
    np.testing.assert_allclose(Pf, ref.P, atol=1e-10)
    assert ll == pytest.approx(gaussian_loglikelihood(z - H @ x_c, H @ P_c @ H.T + R), rel=1e-10)
    assert ll != pytest.approx(sum(lls), rel=1e-3)  # not the product of the local likelihoods


def _maneuver_scans(until: float):
    from sensors_sim import load_scenario
    from services.evaluation import merged_measurements

    return [m for m in merged_measurements(load_scenario("patent-3d-maneuver"), 0) if m.t <= until]


def test_feedback_and_two_stage_info_fusion_of_local_imms_is_the_centralised_imm():
    """PHHNV and DDHNV with ``fusion_rule = info`` and ``motion = imm`` (per-model fusion,
    the per-model estimates and mode probabilities fed back) give the centralised SS IMM
    estimate at every scan, through the first manoeuvre onset of patent-3d-maneuver."""
    from sensors_sim import load_scenario
    from fusion.methods import method_config

    tracker = load_scenario("patent-3d-maneuver").tracker
    scans = _maneuver_scans(24.0)
    out = {}
    for method in ("SS", "PHHNV", "DDHNV"):
        meth = make_method(method, method_config(tracker, method, {"motion": "imm", "fusion_rule": "info"}))
        est = [e for m in scans for e in meth.process(m)] + meth.finish()
        out[method] = [e for e in est if e.node == "centre"]
    assert len(out["SS"]) == 25
    for method in ("PHHNV", "DDHNV"):
        assert len(out[method]) == 25
        for a, b in zip(out["SS"], out[method]):
            np.testing.assert_allclose(b.x, a.x, rtol=0, atol=1e-7)
            np.testing.assert_allclose(b.P, a.P, rtol=1e-8, atol=1e-9)


@pytest.mark.slow
def test_distributed_per_model_fusion_equals_in_process(tmp_path, deployment):
    """The per-model reports and feedback (imm_* fields) over the wire: a feedback run of
    PHHNV with info and motion=imm equals the in-process evaluation to 1e-9."""
    import dataclasses
    import subprocess

    from sensors_sim import load_scenario
    from services.evaluation import run_method
    from services.scoring import truth_function
    from services.summary import method_summary

    from _runs import run_cmd, same_series

    cmd = run_cmd(tmp_path, "patent-3d-maneuver", deployment, "--topology", "feedback", "--method", "PHHNV",
                  "--fusion-rule", "info", "--set", "motion=imm", "--speed", "max", "--duration-s", "8")
    p = subprocess.run(cmd, capture_output=True, text=True, timeout=180)
    assert p.returncode == 0, p.stderr[-3000:]
    doc = json.loads((tmp_path / "out.json").read_text())
    sc = dataclasses.replace(load_scenario("patent-3d-maneuver"), duration=8.0)
    ref = method_summary([run_method(sc, "PHHNV", {"motion": "imm", "fusion_rule": "info"})], truth_function(sc))
    same_series(doc["methods"]["PHHNV"], ref)
