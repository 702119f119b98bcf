"""The patent's six methods and the single-sensor baselines: streaming contract,
configuration, exact equalities the maths promises (HNDD = SS; PHHNV/DDHNV with the
``info`` rule = SS), asynchronous sensors, on the patent-3d set-up simulated by
tests/sim3d.py. Their 200-run Monte Carlo consistency (NEES) is in
tests/fusion/test_patent_consistency.py."""

from __future__ import annotations


import numpy as np
import pytest
from scipy.stats import chi2

from sim3d import ANGLE, RADAR2D, RADAR3D, SensorSpec, centre_track, nees, run_method, simulate  # noqa: E402

from fusion.links import LocalReport  # noqa: E402
from fusion.methods import method_config  # noqa: E402
from fusion.methods import METHODS, make_method as make  # noqa: E402
from fusion.patent import LocalTracker, TrackerConfig, pieces_hndd, pieces_lcdd  # noqa: E402
from fusion.types import Measurement  # noqa: E402

ALL = [name for name, spec in METHODS.items() if spec.family == "3d"]
FIRST = 5  # "after the first five scans"


def _same(a, b, tol=1e-9):
    """Estimates equal to ``tol`` in units of the estimate's own standard deviations."""
    assert len(a) == len(b)
    for ea, eb in zip(a, b):
        assert (ea.t, ea.node) == (eb.t, eb.node)
        sd = np.sqrt(np.diag(eb.P))
        assert np.all(np.abs(ea.x - eb.x) <= tol * sd), (ea.t, np.abs(ea.x - eb.x) / sd)
        assert np.abs((ea.P - eb.P) / np.outer(sd, sd)).max() <= tol


def _centre(est):
    return [e for e in est if e.node == "centre"]


@pytest.fixture(scope="module")
def short_runs():
    return simulate(3, seed=11, duration=12.0)


# Configuration -------------------------------------------------------------------------
def test_config_defaults_and_errors():
    cfg = TrackerConfig.from_dict({})
    assert (cfg.motion, cfg.q, cfg.fusion_rule, cfg.ci_criterion, cfg.pair_tol) == ("ca", 0.01, "info", "trace", 1e-3)
    assert TrackerConfig.from_dict({"q": 1, "motion": "cv"}).q == 1.0
    with pytest.raises(ValueError, match="'q_psd'"):
        make("SS", {"q_psd": 0.1})
    with pytest.raises(ValueError, match="fusion_rule"):
        make("HNV", {"fusion_rule": "mmse"})
    with pytest.raises(ValueError, match="'q' must be a finite number"):
        make("SS", {"q": "0.1"})
    with pytest.raises(ValueError, match="init_range_std"):
        make("SS", {"init_range_std": 0.0})
    with pytest.raises(ValueError, match="unknown method"):
        make("KALMAN", {})
    assert make("SS", {"motion": "cv"}).n_x == 6


# Streaming contract ---------------------------------------------------------------------
@pytest.mark.parametrize("name", ALL)
def test_output_does_not_depend_on_watermarks(name, short_runs):
    meas = short_runs.measurements[0] + [  # a 3D radar for RADAR3D; ignored or used by the rest
        Measurement(m.t, "radar3d", "az_el_range", np.array([m.z[0], 0.2, m.z[1]]), np.array([0.02, 0.02, 20.0]), m.site, m.seq)
        for m in short_runs.measurements[0]
        if m.kind == "range_az"
    ]
    meas.sort(key=lambda m: m.order_key)
    runs = [run_method(make(name, {}), meas, advance_every=k) for k in (None, 1, 3)]
    for r in runs[1:]:
        _same(r, runs[0], tol=0.0)
        assert [(e.method, e.nis, e.nis_dof) for e in r] == [(e.method, e.nis, e.nis_dof) for e in runs[0]]
    c = _centre(runs[0])
    times = [e.t for e in c]
    assert times == sorted(set(times)) and len(times) == 13  # one centre estimate per scan
    assert all(e.method == name for e in runs[0])


def test_watermark_closes_a_scan_early_and_finish_flushes():
    runs = simulate(1, seed=3, duration=3.0)
    meas = runs.measurements[0]
    m = make("SS", {})
    out = m.process(meas[0])  # angle @ 0
    out += m.process(meas[1])  # radar @ 0: first scan still open (sensors not yet known)
    assert out == []
    out = m.advance(0.0005)  # within pair_tol of the scan: cannot close yet
    assert out == []
    out = m.advance(0.002)
    assert [e.t for e in out] == [0.0]
    assert m.process(meas[2]) == []  # angle @ 1, the radar may still come
    out = m.process(meas[3])  # radar @ 1 completes the scan (all known sensors present)
    assert [e.t for e in out] == [1.0] and out[0].nis_dof == 4
    m.process(meas[4])
    assert [e.t for e in m.finish()] == [2.0]


def test_scans_group_within_pair_tol_and_fall_back_to_sequential():
    base = simulate(1, seed=4, duration=0.0).measurements[0]
    a0, r0 = base
    later = lambda m, dt, seq: Measurement(m.t + dt, m.sensor, m.kind, m.z, m.std, m.site, seq)
    # Within pair_tol: one stacked update; beyond it: two sequential scans.
    for dt, n_scans in [(0.0004, 2), (0.01, 3)]:
        stream = [a0, r0, later(a0, 1.0, 1), later(r0, 1.0 + dt, 1)]
        out = _centre(run_method(make("SS", {"pair_tol": 1e-3}), stream))
        assert len(out) == n_scans
    out = _centre(run_method(make("SS", {"pair_tol": 1e-3}), [a0, r0, later(a0, 1.0, 1), later(r0, 1.01, 1)]))
    assert [e.t for e in out] == [0.0, 1.0, 1.01] and [e.nis_dof for e in out[1:]] == [2, 2]


def test_bad_streams_are_clear_errors():
    a0, r0 = simulate(1, seed=4, duration=0.0).measurements[0]
    m = make("SS", {})
    m.process(r0)
    with pytest.raises(ValueError, match="out of order"):
        m.process(a0)
    m.advance(5.0)
    with pytest.raises(ValueError, match="after watermark"):
        m.process(Measurement(4.0, "z", "azel", a0.z, a0.std, a0.site))
    with pytest.raises(ValueError, match="bearing"):
        make("HNV", {}).process(Measurement(0.0, "df1", "bearing", np.array([1.0]), np.array([0.01]), np.zeros(3)))


def test_baselines_use_only_their_kind():
    runs = simulate(1, seed=5, duration=5.0, sensors=(ANGLE, RADAR2D, RADAR3D))
    for name, kind in [("RADAR2D", "range_az"), ("ANGLE", "azel"), ("RADAR3D", "az_el_range")]:
        mine = [m for m in runs.measurements[0] if m.kind == kind]
        _same(run_method(make(name, {}), runs.measurements[0]), run_method(make(name, {}), mine), tol=0.0)


def test_roles_come_from_measurement_kind_not_sensor_id(short_runs):
    swap = {"angle": "radar2d", "radar2d": "angle"}
    meas = short_runs.measurements[1]
    renamed = sorted(
        (Measurement(m.t, swap[m.sensor], m.kind, m.z, m.std, m.site, m.seq) for m in meas), key=lambda m: m.order_key
    )
    for name in ("LCDD", "HNDD", "SS", "PHHNV", "DDHNV"):
        _same(_centre(run_method(make(name, {}), meas)), _centre(run_method(make(name, {}), renamed)))


def test_hndd_fuses_azimuths_across_north():
    s_i, s_r = 1e-3, 1e-2
    ang = Measurement(0.0, "a", "azel", np.array([0.001, 0.2]), np.array([s_i, s_i]), np.zeros(3))
    rad = Measurement(0.0, "r", "range_az", np.array([2 * np.pi - 0.003, 9000.0]), np.array([s_r, 20.0]), np.zeros(3))
    (model, z), = pieces_hndd([ang, rad], 9)
    unwrapped = (0.001 / s_i**2 + (-0.003) / s_r**2) / (1 / s_i**2 + 1 / s_r**2)
    assert z[0] == pytest.approx(unwrapped % (2 * np.pi), abs=1e-15)
    assert model.std[0] == pytest.approx((s_i**-2 + s_r**-2) ** -0.5)
    np.testing.assert_array_equal(z[1:], [0.2, 9000.0])
    (model, z), = pieces_lcdd([ang, rad], 9)
    assert model.components == ("az", "el", "range")
    np.testing.assert_array_equal(z, [0.001, 0.2, 9000.0])


# Equalities the maths promises ----------------------------------------------------------
@pytest.mark.parametrize("run", [0, 1, 2])
def test_hndd_equals_ss(run, short_runs):
    meas = short_runs.measurements[run]
    _same(_centre(run_method(make("HNDD", {}), meas)), _centre(run_method(make("SS", {}), meas)))


@pytest.mark.parametrize("name", ["PHHNV", "DDHNV"])
@pytest.mark.parametrize("motion", ["ca", "cv"])
def test_feedback_and_two_stage_with_info_rule_equal_centralised(name, motion, short_runs):
    for meas in short_runs.measurements:
        cfg = {"fusion_rule": "info", "motion": motion}
        _same(_centre(run_method(make(name, cfg), meas)), _centre(run_method(make("SS", cfg), meas)))


@pytest.mark.parametrize("rule", ["info", "bar-shalom-campo", "ci"])
def test_two_stage_equals_feedback_for_consistent_rules(rule, short_runs):
    # Stage 1 fuses two copies of one prediction, which these rules (unlike naive) leave as is.
    meas = short_runs.measurements[0]
    cfg = {"fusion_rule": rule}
    _same(_centre(run_method(make("DDHNV", cfg), meas)), _centre(run_method(make("PHHNV", cfg), meas)))


def test_asynchronous_sensors():
    # Radar every 1 s, angle sensor every 0.7 s: after t = 0 (and 7, 14) no scan pairs them.
    sensors = (SensorSpec("angle", "azel", ANGLE.std, period=0.7), RADAR2D)
    runs = simulate(4, seed=6, duration=20.0, sensors=sensors)
    for meas in runs.measurements:
        times = sorted({m.t for m in meas})
        ss = _centre(run_method(make("SS", {}), meas))
        assert [e.t for e in ss] == times
        # Each scan holds one sensor; feedback/two-stage with `info` still equal the centralised filter.
        for name in ("PHHNV", "DDHNV"):
            _same(_centre(run_method(make(name, {"fusion_rule": "info"}), meas)), ss)
    # Every method emits at every measurement time and ends within a few σ of the truth.
    cfg = {"fusion_rule": "bar-shalom-campo", "init_vel_std_up": 20.0, "init_acc_std_up": 1.0}
    for r, meas in enumerate(runs.measurements):
        for name in ("LCDD", "HNDD", "SS", "HNV", "PHHNV"):
            out = _centre(run_method(make(name, cfg), meas))
            assert [e.t for e in out] == sorted({m.t for m in meas})
            err = out[-1].x[:3] - runs.truth_at(r, out[-1].t)[:3]
            assert err @ np.linalg.solve(out[-1].P[:3, :3], err) < chi2.ppf(0.9999, 3)


def test_lcdd_with_separated_sites_and_hndd_refuses():
    sensors = (SensorSpec("angle", "azel", ANGLE.std, site=(2000.0, -1000.0, 30.0)), RADAR2D)
    runs = simulate(40, seed=7, duration=15.0, sensors=sensors)
    n = []
    for r, meas in enumerate(runs.measurements):
        t, x, P = centre_track(run_method(make("LCDD", {}), meas))
        n.append(nees(runs.truth[r], x, P))
    anees = np.mean(n, axis=0)[FIRST:]
    assert np.all(anees < chi2.ppf(0.999, 9 * 40) / 40)
    with pytest.raises(ValueError, match="co-located"):
        run_method(make("HNDD", {}), runs.measurements[0])


def test_local_reports_carry_what_the_fusion_rules_need(short_runs):
    method = make("HNV", {"fusion_rule": "bar-shalom-campo"})
    sent = []
    process = method.centre.process
    method.centre.process = lambda u: sent.append(u) or process(u)
    out = run_method(method, short_runs.measurements[0])
    reports = [u for u in sent if isinstance(u, LocalReport)]
    local = [e for e in out if e.node != "centre"]
    assert [u.estimate for u in reports] == local and {u.node for u in reports} == {"angle", "radar2d"}
    first = {u.node: u for u in reversed(reports)}
    for u in reports:
        e = u.estimate
        assert e.nis_dof == 2 and e.nis >= 0 and u.models is None and e.extra == {}
        # x = x̄ + K ν: the report's K·H moves the prior's information exactly as the Joseph update did.
        A = np.eye(9) - u.KH
        assert np.all(np.linalg.eigvalsh(A @ u.prior.P @ A.T - e.P) <= 1e-6 * np.abs(e.P).max())
    assert all(u.feedback_t == 0.0 for u in first.values())  # started from the centre's initial state
    assert all(u.feedback_t is None for u in reports if u.t > 1.0)  # HNV: no feedback
    lt = LocalTracker("angle", make("SS", {}).motion)
    with pytest.raises(ValueError, match="no prior"):
        lt.predict(short_runs.measurements[0][0], 1)


# Fusion rules ------------------------------------------------------------------------------
# (The 200-run Monte Carlo consistency tests are in tests/fusion/test_patent_consistency.py.)
@pytest.mark.parametrize("name", ["PHHNV", "DDHNV"])
def test_naive_rule_double_counts_the_shared_prior(name, short_runs):
    # The optimal (centralised) covariance bounds any achievable one from below; naive
    # fusion of updates from one prior claims less — overconfidence, with certainty.
    meas = short_runs.measurements[0]
    naive = _centre(run_method(make(name, {"fusion_rule": "naive"}), meas))
    ss = _centre(run_method(make("SS", {}), meas))
    for a, b in zip(naive[1:], ss[1:]):
        assert np.linalg.eigvalsh(b.P - a.P).min() > 0


def test_method_config_layers_common_per_method_and_overrides():
    table = {"motion": "ca", "q": 0.01,
             "methods": {"LCDD, SS": {"init_vel_std": 1e3}, "HNV": {"fusion_rule": "ci", "q": 0.02}}}
    assert method_config(table, "SS") == {"motion": "ca", "q": 0.01, "init_vel_std": 1e3}
    assert method_config(table, "HNV") == {"motion": "ca", "q": 0.02, "fusion_rule": "ci"}
    assert method_config(table, "HNV", {"fusion_rule": "naive"})["fusion_rule"] == "naive"  # the command line wins
    assert method_config(table, "RADAR2D") == method_config(table, None) == {"motion": "ca", "q": 0.01}
    assert table["methods"]  # the caller's table is not consumed
    for bad, why in [({"methods": {"XX": {}}}, "unknown method 'XX'"),
                     ({"methods": {"SS": {}, "LCDD,SS": {}}}, "two tables"),
                     ({"methods": {"SS": 1.0}}, "must be a table")]:
        with pytest.raises(ValueError, match=why):
            method_config(bad, "SS")
    with pytest.raises(ValueError, match="unknown tracker config key 'methods'"):
        make("SS", table)  # an unresolved table cannot reach a method by mistake


def test_an_unknown_tracker_key_close_to_a_known_one_is_suggested():
    from fusion.methods import make_method

    with pytest.raises(ValueError, match="unknown tracker config key 'motoin' \\(did you mean 'motion'\\?"):
        make_method("SS", {"motoin": "ca"})
