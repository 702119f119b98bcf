"""The DF methods through the streaming interface: contract, config, geometries."""

from __future__ import annotations

import numpy as np
import pytest

from fusion.angles import compass_to_math, math_to_compass
from fusion.df import DF_METHODS, DFConfig, make
from fusion.df.crb import crb_rmse
from fusion.df.models import bearing, bearing_measurements
from fusion.df.noise import contaminated, gaussian
from fusion.metrics import rmse
from fusion.types import Measurement

EMITTER = np.array([15e3, 15e3])
C1 = np.array([[0.0, 0.0], [20e3, 0.0]])
C3 = np.array([[0.0, 0.0], [20e3, 0.0], [30e3, 0.0]])
SIGMA = 0.0175
ALL = sorted(DF_METHODS)


def stream(sites, n_epochs, noise, emitter=EMITTER, t0=1.0):
    sensors = [f"DF{i + 1}" for i in range(np.asarray(sites).shape[-2])]
    sites = np.asarray(sites, dtype=float)
    beta = bearing(emitter, sites if sites.ndim == 3 else sites[None]) + noise
    return bearing_measurements(t0 + np.arange(n_epochs, dtype=float), sensors, sites, beta, SIGMA)


def run(method, ms, watermarks=None, finish=True):
    """Drive a method; ``watermarks(t_next)`` gives the watermark sent after each
    bearing (it must stay below the next bearing's time ``t_next``)."""
    out = []
    for i, m in enumerate(ms):
        out += method.process(m)
        if watermarks is not None:
            t_next = ms[i + 1].t if i + 1 < len(ms) else np.inf
            out += method.advance(min(watermarks(t_next), 1e9))
    return out + method.finish() if finish else out


def test_registry_has_the_seeds_names_and_config_defaults():
    assert set(DF_METHODS) == {"EKF", "MEKF1", "MEKF2", "MEKF3", "MEKF4", "MEKF5", "IMM", "TORRIERI", "KF+TR", "MKF+TR"}
    c = DFConfig()
    assert (c.q22, c.sigma, c.imm_sigma2, c.imm_transition, c.torrieri_iterations) == (0.0, 0.0175, 0.25, "symmetric", 0)
    for name in ALL:
        assert make(name, {}).name == name


@pytest.mark.parametrize("name", ALL)
def test_output_does_not_depend_on_watermarks(name):
    rng = np.random.default_rng(21)
    ms = stream(C3, 8, gaussian(rng, SIGMA, (8, 3)))
    cfg = {"imm_p": 0.2, "gate": 3.0}
    plain = run(make(name, cfg), ms)
    # the latest legal watermark after every bearing, and random laggard ones
    eager = run(make(name, cfg), ms, watermarks=lambda t_next: np.nextafter(t_next, -np.inf))
    noisy = run(make(name, cfg), ms, watermarks=lambda t_next: t_next - rng.uniform(1e-9, 2.5))
    assert len(plain) == 8 and [e.t for e in plain] == list(1.0 + np.arange(8))
    assert len(run(make(name, cfg), ms, watermarks=lambda t: np.nextafter(t, -np.inf), finish=False)) == 8
    for other in (eager, noisy):
        assert [e.t for e in other] == [e.t for e in plain]
        for a, b in zip(plain, other):
            np.testing.assert_array_equal(a.x, b.x)
            np.testing.assert_array_equal(a.P, b.P)
    assert all(e.method == name for e in plain)
    for e in plain:
        assert e.x.shape == (2,) and e.P.shape == (2, 2)
        np.testing.assert_array_equal(e.P, e.P.T)
        assert np.all(np.linalg.eigvalsh(e.P) > 0)


def test_a_watermark_releases_the_epoch_early_and_once():
    ms = stream(C1, 3, np.zeros((3, 2)))
    m = make("EKF", {})
    assert m.process(ms[0]) == [] and m.process(ms[1]) == []
    assert m.advance(0.5) == []                   # before the epoch: nothing proven yet
    out = m.advance(1.0)                          # epoch at t=1 proven complete
    assert len(out) == 1 and out[0].t == 1.0
    assert m.advance(1.0) == [] and m.advance(1.7) == []
    assert m.process(ms[2]) == []
    assert [e.t for e in m.finish()] == [2.0]


def test_bearings_within_pair_tol_form_one_epoch():
    base = stream(C3, 1, np.zeros((1, 3)))
    jittered = [Measurement(t=b.t + 0.004 * i, sensor=b.sensor, kind="bearing", z=b.z, std=b.std, site=b.site, seq=0)
                for i, b in enumerate(base)]                       # t = 1.000, 1.004, 1.008
    one = run(make("EKF", {"pair_tol": 0.01}), jittered)
    assert [e.t for e in one] == [1.008]
    assert [e.t for e in run(make("EKF", {"pair_tol": 0.0}), jittered)] == [1.004, 1.008]
    m = make("TORRIERI", {"pair_tol": 0.01})
    for b in jittered:
        m.process(b)
    assert m.advance(1.009) == [] and len(m.advance(1.01)) == 1


def test_stream_errors_are_clear():
    ms = stream(C1, 2, np.zeros((2, 2)))
    m = make("EKF", {})
    m.process(ms[1])
    with pytest.raises(ValueError, match="order"):
        m.process(ms[0])
    m = make("EKF", {})
    m.advance(5.0)
    with pytest.raises(ValueError, match="late"):
        m.process(ms[0])
    bad = Measurement(t=1.0, sensor="R1", kind="range_az", z=np.array([0.1, 1e3]), std=np.array([0.01, 5.0]),
                      site=np.zeros(3))
    with pytest.raises(ValueError, match="bearing"):
        make("EKF", {}).process(bad)
    nan = Measurement(t=1.0, sensor="DF1", kind="bearing", z=np.array([np.nan]), std=np.array([SIGMA]), site=np.zeros(3))
    with pytest.raises(ValueError, match="finite"):
        make("IMM", {}).process(nan)


@pytest.mark.parametrize("cfg,needle", [
    ({"q33": 1.0}, "q33"), ({"sigma": -1.0}, "sigma"), ({"sigma": "auto"}, "sigma"), ({"imm_p": 1.0}, "imm_p"),
    ({"imm_transition": "markov"}, "imm_transition"), ({"torrieri_iterations": 1.5}, "torrieri_iterations"),
    ({"gate": "x"}, "gate"), ({"q22": True}, "q22"), ({"mekf_handoff": "garbled"}, "mekf_handoff"),
])
def test_bad_config_names_the_key(cfg, needle):
    with pytest.raises(ValueError, match=needle):
        make("EKF", cfg)


def test_north_straddling_bearings_359_9_and_0_1_degrees():
    # two stations 2·35 m apart, emitter 20 km north: compass 0.1° and 359.9°
    half = 20e3 * np.tan(np.radians(0.1))
    sites = np.array([[-half, 0.0], [half, 0.0]])
    emitter = np.array([0.0, 20e3])
    ms = stream(sites, 30, np.zeros((30, 2)), emitter=emitter)
    assert ms[0].z[0] == pytest.approx(np.radians(0.1)) and ms[1].z[0] == pytest.approx(np.radians(359.9))
    for name in ("EKF", "TORRIERI", "KF+TR", "IMM"):
        # a 0.2° crossing needs a sharp DF (σ = 1e-4 rad) to be a usable fix at all
        out = run(make(name, {"q22": 0.0, "sigma": 1e-4}), ms)
        np.testing.assert_allclose(out[-1].x, emitter, atol=1e-3)
    # with σ = 1° the same crossing is refused as an initial fix (1σ axis >> range)
    assert run(make("EKF", {}), ms) == []
    # a moving observer flying under the emitter: bearings sweep through north
    k = np.arange(20)
    path = np.column_stack([-4e3 + 400.0 * k, np.zeros(20)])[:, None, :]
    rng = np.random.default_rng(3)
    az = math_to_compass(bearing(emitter, path[:, 0]))
    assert az.max() > np.radians(350) and az.min() < np.radians(10)
    ms = stream(path, 20, 1e-3 * rng.standard_normal((20, 1)), emitter=emitter)
    out = run(make("EKF", {"q22": 0.0}), ms)
    assert np.linalg.norm(out[-1].x - emitter) < 5 * crb_rmse(emitter, path[:, 0], 1e-3)


def _mirror_y(v, y0=15e3):
    v = np.array(v, dtype=float)
    v[..., 1] = 2 * y0 - v[..., 1]
    return v


@pytest.mark.parametrize("name", ["EKF", "IMM", "TORRIERI", "KF+TR"])
def test_stations_north_of_the_emitter_mirror_the_thesis_case(name):
    # reflecting the whole problem about y = 15 km must reflect every estimate: a method
    # using atan (mod π) or an unwrapped innovation fails this with bearings pointing south
    rng = np.random.default_rng(8)
    noise = gaussian(rng, SIGMA, (15, 2))
    south = run(make(name, {}), stream(C1, 15, noise))
    north_sites = _mirror_y(C1)                     # (0, 30) and (20, 30) km
    north = run(make(name, {}), stream(north_sites, 15, -noise))  # mirrored bearings
    assert compass_to_math(stream(north_sites, 1, np.zeros((1, 2)))[0].z[0]) < 0  # looking south
    for a, b in zip(south, north):
        np.testing.assert_allclose(b.x, _mirror_y(a.x), atol=1e-6)
        np.testing.assert_allclose(np.abs(b.P), np.abs(a.P), rtol=1e-6)


def test_station_on_the_emitter_x_coordinate():
    sites = np.array([[15e3, 0.0], [0.0, 0.0]])     # DF1 looks due north: Δx = 0
    rng = np.random.default_rng(30)
    runs = 40
    errs = []
    for r in range(runs):
        out = run(make("EKF", {"q22": 0.0}), stream(sites, 40, gaussian(rng, SIGMA, (40, 2))))
        errs.append(out[-1].x - EMITTER)
    bound = crb_rmse(EMITTER, np.repeat(sites, 40, axis=0), SIGMA)
    assert 0.75 < rmse(np.array(errs)) / bound < 1.3
    # the thesis's EKFS would divide by Δx there: MEKF4 (EKFS/EKFS) uses the documented
    # EKFT fallback when the estimate sits exactly on the station's x coordinate
    ms = stream(sites, 3, np.zeros((3, 2)))
    out = run(make("MEKF4", {"q22": 0.0}), ms)
    assert out[-1].extra["fallbacks"] > 0
    np.testing.assert_allclose(out[-1].x, EMITTER, atol=1e-6)


def test_single_moving_observer_initialises_from_two_epochs():
    k = np.arange(9)
    path = np.column_stack([130e3 + 30e3 * k, 11e3 + 30e3 * k])[:, None, :]   # the thesis's aircraft
    emitter = np.array([141e3, 141e3])
    ms = stream(path, 9, np.zeros((9, 1)), emitter=emitter)
    for name in ("EKF", "MEKF2", "IMM", "TORRIERI"):
        out = run(make(name, {"q22": 0.0}), ms)
        assert len(out) == 8 and out[0].t == ms[1].t
        np.testing.assert_allclose(out[-1].x, emitter, atol=1e-3)
    with pytest.raises(ValueError, match="moved"):
        run(make("KF+TR", {}), ms)


def test_kf_tr_with_two_stations_is_the_batch_ml_fix():
    # with q = 0 each smoother returns its mean bearing, and with two stations the batch
    # ML fix crosses exactly those two means
    rng = np.random.default_rng(13)
    ms = stream(C1, 12, gaussian(rng, SIGMA, (12, 2)))
    a, b = run(make("KF+TR", {}), ms), run(make("TORRIERI", {}), ms)
    for ea, eb in zip(a, b):
        np.testing.assert_allclose(ea.x, eb.x, rtol=1e-9)
        np.testing.assert_allclose(ea.P, eb.P, rtol=1e-6)
    mk = run(make("MKF+TR", {}), ms)
    np.testing.assert_array_equal(mk[-1].x, a[-1].x)


def test_torrieri_gate_rejects_jammed_bearings():
    rng = np.random.default_rng(17)
    noise, mask = contaminated(rng, SIGMA, 0.25, 0.2, (20, 3), return_mask=True)
    ms = stream(C3, 20, noise)
    plain = run(make("TORRIERI", {}), ms)[-1]
    gated = run(make("TORRIERI", {"gate": 3.0}), ms)[-1]
    assert gated.extra["n_used"] < gated.extra["n_bearings"]
    assert gated.extra["n_bearings"] - gated.extra["n_used"] <= mask.sum()
    assert np.linalg.norm(gated.x - EMITTER) < np.linalg.norm(plain.x - EMITTER)
    one = run(make("TORRIERI", {"torrieri_iterations": 1}), ms)[-1]
    assert one.extra["iterations"] == 1


def test_torrieri_keeps_its_latest_bearings_only():
    """A live fuser's TORRIERI is bounded: with ``torrieri_bearings = 30`` its fixes over
    40 epochs of three stations are, from the tenth epoch on, the ML fixes of the latest
    30 bearings (10 epochs), as a fresh run on those alone gives them (to the
    Gauss–Newton tolerance: another warm start)."""
    rng = np.random.default_rng(19)
    ms = stream(C3, 40, gaussian(rng, SIGMA, (40, 3)))
    kept = run(make("TORRIERI", {"torrieri_bearings": 30}), ms)
    assert [e.extra["n_bearings"] for e in kept][-1] == 30
    for k in (10, 25, 40):  # epoch k's fix (kept[k - 1]): the bearings of epochs k - 9 .. k
        fresh = run(make("TORRIERI", {}), ms[3 * (k - 10):3 * k])[-1]
        np.testing.assert_allclose(kept[k - 1].x, fresh.x, rtol=0, atol=1e-6)
        np.testing.assert_allclose(kept[k - 1].P, fresh.P, rtol=1e-6)
    whole = run(make("TORRIERI", {}), ms)[-1]
    assert whole.extra["n_bearings"] == 120 and not np.allclose(whole.x, kept[-1].x, atol=1e-3)


@pytest.mark.parametrize("cross_fed", [False, True])
def test_station_smoothers_plus_centre_reproduce_kf_tr(cross_fed):
    # the distributed topology: one smoother per station process, the fix at the centre
    from fusion.df import centre_fix, make_station_smoother

    rng = np.random.default_rng(19)
    ms = stream(C3, 10, gaussian(rng, SIGMA, (10, 3)))
    cfg = {"smoother_q": 1e-7, "gate": 3.0}
    smoothers = {s: make_station_smoother(cfg, cross_fed) for s in ("DF1", "DF2", "DF3")}
    latest, x, fixes = {}, None, []
    for k in range(10):
        for m in ms[3 * k:3 * k + 3]:
            latest[m.sensor] = smoothers[m.sensor].update(m)   # what crosses the wire
        fix = centre_fix(latest, cfg, x)
        x = fix.x
        fixes.append(fix)
    ref = run(make("MKF+TR" if cross_fed else "KF+TR", cfg), ms)
    for f, e in zip(fixes, ref):
        np.testing.assert_array_equal(f.x, e.x)
        np.testing.assert_array_equal(f.P, e.P)
