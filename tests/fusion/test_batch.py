"""fusion.batch: the batched EKF equals the single-track path (fusion.ekf +
fusion.kalman) to 1e-10, over random geometries, sensors and time steps."""

from __future__ import annotations

import numpy as np
import pytest

from fusion import batch
from fusion.angles import TWO_PI
from fusion.ekf import ekf_predict, ekf_update
from fusion.measurement.kinds import model_for
from fusion.measurement.models import SphericalModel
from fusion.motion import make_motion

TOL = 1e-10


def _close(a, b, what: str) -> None:
    """Equal to TOL relative to the quantity's scale (covariances span metres² to (m/s²)²)."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    scale = max(1.0, float(np.max(np.abs(b))))
    err = float(np.max(np.abs(a - b))) if a.size else 0.0
    assert err <= TOL * scale, f"{what}: max |batch − single| = {err:.3g} (scale {scale:.3g})"


def _random_cov(rng, n: int, stds: np.ndarray) -> np.ndarray:
    """SPD with the given standard deviations and random, moderate correlations."""
    A = rng.normal(size=(n, n))
    C = A @ A.T + n * np.eye(n)
    d = np.sqrt(np.diag(C))
    return (C / np.outer(d, d)) * np.outer(stds, stds)


def _random_states(rng, N: int, n_x: int) -> tuple[np.ndarray, np.ndarray]:
    pos = np.c_[rng.uniform(-30e3, 30e3, (N, 2)), rng.uniform(50.0, 8e3, (N, 1))]
    vel = rng.normal(0.0, 150.0, (N, 3))
    acc = rng.normal(0.0, 2.0, (N, 3))
    x = np.c_[pos, vel, acc][:, :n_x]
    stds = np.array([300.0, 300.0, 200.0, 40.0, 40.0, 20.0, 3.0, 3.0, 1.0])[:n_x]
    P = np.stack([_random_cov(rng, n_x, stds * rng.uniform(0.2, 3.0)) for _ in range(N)])
    return x, P


def _random_model(rng, n_x: int) -> SphericalModel:
    """A random sensor, or a random stack of rows from random sites (SS, LCDD-like)."""
    kind = rng.integers(4)
    site = rng.uniform(-2e3, 2e3, 3)
    if kind == 0:
        return model_for("az_el_range", site, [rng.uniform(1e-4, 0.03), rng.uniform(1e-4, 0.03), rng.uniform(1.0, 80.0)], n_x)
    if kind == 1:
        return model_for("azel", site, [rng.uniform(1e-4, 0.03), rng.uniform(1e-4, 0.03)], n_x)
    if kind == 2:
        return model_for("range_az", site, [rng.uniform(1e-4, 0.03), rng.uniform(1.0, 80.0)], n_x)
    n_z = int(rng.integers(1, 6))
    comps = rng.choice(["az", "el", "range"], n_z).tolist()
    std = [rng.uniform(1.0, 80.0) if c == "range" else rng.uniform(1e-4, 0.03) for c in comps]
    return SphericalModel(comps, rng.uniform(-2e3, 2e3, (n_z, 3)), std, n_x)


def _measure(rng, model: SphericalModel, x: np.ndarray) -> np.ndarray:
    """h(x) plus noise, angles kept in their wire ranges (so az wraps across 0/2π)."""
    z = model.h(x) + rng.normal(size=(x.shape[0], model.n_z)) * model.std * 3.0
    az = model.codes == 0
    z[:, az] = np.mod(z[:, az], TWO_PI)
    return z


@pytest.mark.parametrize("motion_name", ["ca", "cv"])
@pytest.mark.parametrize("seed", range(6))
def test_step_equals_single_track_path(motion_name, seed):
    rng = np.random.default_rng(seed)
    motion = make_motion(motion_name, rng.uniform(1e-3, 1.0), "continuous" if seed % 2 else "discrete")
    N = 64
    x, P = _random_states(rng, N, motion.n_x)
    model = _random_model(rng, motion.n_x)
    dt = rng.choice([0.0, 0.1, 0.5, 1.0, 2.5], N)  # per-track intervals, some zero
    z = _measure(rng, model, x)
    res = batch.ekf_step(motion, model, x, P, dt, z)
    for i in range(N):
        xp, Pp = ekf_predict(motion, x[i], P[i], float(dt[i]))
        one = ekf_update(model, xp, Pp, z[i])
        _close(res.x[i], one.x, f"x[{i}]")
        _close(res.P[i], one.P, f"P[{i}]")
        _close(res.nu[i], one.nu, f"nu[{i}]")
        _close(res.S[i], one.S, f"S[{i}]")
        _close(res.K[i], one.K, f"K[{i}]")
        assert abs(res.nis[i] - one.nis) <= TOL * max(1.0, one.nis)
    assert np.array_equal(res.P, res.P.swapaxes(1, 2))  # symmetrised, as the single path


def test_many_scans_stay_equal():
    """A stack run through 30 predict/update cycles stays on the single-track trajectory."""
    rng = np.random.default_rng(42)
    motion = make_motion("ca", 0.01)
    model = SphericalModel.stack([model_for("range_az", [0.0, 0.0, 0.0], [0.017, 20.0]), model_for("azel", [0.0, 0.0, 0.0], [1e-3, 1e-3])])
    N = 32
    x, P = _random_states(rng, N, 9)
    xs, Ps = x.copy(), P.copy()
    truth = x.copy()
    for _ in range(30):
        truth = truth @ np.asarray(motion.F(1.0)).T
        z = _measure(rng, model, truth)
        res = batch.ekf_step(motion, model, x, P, 1.0, z)
        x, P = res.x, res.P
        for i in range(N):
            xp, Pp = ekf_predict(motion, xs[i], Ps[i], 1.0)
            one = ekf_update(model, xp, Pp, z[i])
            xs[i], Ps[i] = one.x, one.P
    for i in range(N):
        _close(x[i], xs[i], f"x[{i}]")
        _close(P[i], Ps[i], f"P[{i}]")


def test_per_track_sites_and_noise():
    rng = np.random.default_rng(7)
    N = 40
    x, P = _random_states(rng, N, 9)
    model = model_for("az_el_range", [0.0, 0.0, 0.0], [0.01, 0.01, 10.0])
    sites = rng.uniform(-5e3, 5e3, (N, 1, 3)).repeat(3, axis=1)
    stds = np.c_[rng.uniform(1e-3, 0.02, (N, 2)), rng.uniform(5.0, 50.0, N)]
    R = np.stack([np.diag(s**2) for s in stds])
    z = np.stack([model_for("az_el_range", sites[i, 0], stds[i]).h(x[i]) for i in range(N)])
    res = batch.ekf_update(model, x, P, z, sites=sites, R=R)
    for i in range(N):
        one = ekf_update(model_for("az_el_range", sites[i, 0], stds[i]), x[i], P[i], z[i])
        _close(res.x[i], one.x, f"x[{i}]")
        _close(res.P[i], one.P, f"P[{i}]")
        assert abs(res.nis[i] - one.nis) <= TOL * max(1.0, one.nis)


def test_full_R_and_generic_predict():
    """A correlated R takes the general product; per-track F, Q take the stacked product."""
    rng = np.random.default_rng(3)
    N = 20
    x, P = _random_states(rng, N, 9)
    model = model_for("az_el_range", [100.0, -50.0, 0.0], [0.01, 0.01, 10.0])
    Rfull = _random_cov(rng, 3, model.std)
    zp, Hp = batch.spherical(model, x)
    z = _measure(rng, model, x)
    nu = batch.innovation(model, z, zp)
    res = batch.update(x, P, nu, Hp, Rfull)
    from fusion import kalman

    for i in range(N):
        one = kalman.update(x[i], P[i], nu[i], model.jacobian(x[i]), Rfull)
        _close(res.P[i], one.P, f"P[{i}]")
        _close(res.x[i], one.x, f"x[{i}]")
    motion = make_motion("ca", 0.3)
    dts = rng.uniform(0.1, 3.0, N)
    F = np.stack([motion.F(d) for d in dts])
    Q = np.stack([motion.Q(d) for d in dts])
    xp, Pp = batch.predict(x, P, F, Q)
    for i in range(N):
        x1, P1 = kalman.predict(x[i], P[i], F[i], Q[i])
        _close(xp[i], x1, f"x⁻[{i}]")
        _close(Pp[i], P1, f"P⁻[{i}]")


@pytest.mark.parametrize("m", [1, 2, 3, 4, 6, 9])
def test_spd_inverse(m):
    rng = np.random.default_rng(m)
    S = np.stack([_random_cov(rng, m, rng.uniform(1e-3, 1e3, m)) for _ in range(50)])
    Si = batch._spd_inverse(S)
    for i in range(50):
        np.testing.assert_allclose(Si[i] @ S[i], np.eye(m), atol=1e-9)
    S[17] = -S[17]
    with pytest.raises(np.linalg.LinAlgError):
        batch._spd_inverse(S)


def test_singular_geometry_names_the_track():
    rng = np.random.default_rng(0)
    x, P = _random_states(rng, 5, 9)
    x[3, :3] = [10.0, 20.0, 500.0]  # straight above the site
    with pytest.raises(ValueError, match="track 3: target straight above"):
        batch.spherical(model_for("azel", [10.0, 20.0, 0.0], [0.01, 0.01]), x)
    x[2, :3] = [10.0, 20.0, 0.0]  # at the site
    with pytest.raises(ValueError, match="track 2: target at a sensor site"):
        batch.spherical(SphericalModel(["range"], [10.0, 20.0, 0.0], [5.0]), x)


def test_shapes_are_checked():
    x, P = _random_states(np.random.default_rng(0), 4, 9)
    model = model_for("az_el_range", [0.0, 0.0, 0.0], [0.01, 0.01, 10.0])
    with pytest.raises(ValueError):
        batch.ekf_update(model, x, P[:3], np.zeros((4, 3)))
    with pytest.raises(ValueError):
        batch.ekf_update(model, x, P, np.zeros((4, 2)))
    with pytest.raises(ValueError):
        batch.ekf_predict(make_motion("ca", 0.1), x, P, np.ones(3))
    same_x, same_P = batch.ekf_predict(make_motion("ca", 0.1), x, P, 0.0)
    assert np.array_equal(same_x, x) and np.array_equal(same_P, P)


def test_large_stacks_go_through_in_passes(monkeypatch):
    """ekf_step's passes of CHUNK tracks give what one pass gives, to rounding.

    Not bit for bit: numpy's SIMD loops may sum in another order for a slice that
    starts at another alignment (numpy 2.4: relative differences up to 1e-14)."""
    rng = np.random.default_rng(11)
    N = 50
    motion = make_motion("ca", 0.05)
    x, P = _random_states(rng, N, 9)
    model = model_for("az_el_range", [0.0, 0.0, 0.0], [0.01, 0.01, 10.0])
    sites = rng.uniform(-5e3, 5e3, (N, 1, 3)).repeat(3, axis=1)
    R = np.stack([np.diag(rng.uniform(0.5, 2.0, 3) * model.std**2) for _ in range(N)])
    dt = rng.choice([0.0, 0.5, 1.0], N)
    z = _measure(rng, model, x)
    whole = batch.ekf_step(motion, model, x, P, dt, z, sites, R)
    monkeypatch.setattr(batch, "CHUNK", 7)
    passes = batch.ekf_step(motion, model, x, P, dt, z, sites, R)
    for a, b in zip(whole, passes):
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=0.0)
