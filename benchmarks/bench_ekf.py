"""Estimation core: one predict + update of the 9-state CA EKF with a 3-component
measurement ``[az, el, range]`` (a 3D radar), single and batched over many tracks, beside
FilterPy's ``ExtendedKalmanFilter`` and Stone Soup's EKF on the same models, in the same
run (candidates are timed round-robin, so whatever else loads the machine loads all).

    python benchmarks/bench_ekf.py [--repeats 15] [--tracks 1000] [--json out.json]

Prints the figures as markdown tables. Every candidate is first checked against the
project's single-track path (same posterior to 1e-8, or the peer's own convention).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import time

import _common as C
import numpy as np

from ekf_kernels import lean_step, numba_kernels
from fusion import batch, kalman
from fusion.angles import wrap_pi
from fusion.motion import make_motion
from fusion.ekf import ekf_predict, ekf_update
from fusion.measurement.kinds import model_for

DT = 1.0
Q_PSD = 0.01
SITE = np.array([0.0, 0.0, 0.0])
STD = np.array([math.radians(1.0), math.radians(1.0), 20.0])
PERM = [0, 3, 6, 1, 4, 7, 2, 5, 8]  # Stone Soup's state [x vx ax y vy ay z vz az] from ours


def scene(N: int, seed: int = 1):
    """N tracks 5–30 km out with a realistic (correlated) covariance, and their measurements."""
    rng = np.random.default_rng(seed)
    motion = make_motion("ca", Q_PSD, "continuous")
    model = model_for("az_el_range", SITE, STD)
    F = np.array(motion.F(DT))
    rng_m = rng.uniform(5e3, 30e3, N)
    az = rng.uniform(0, 2 * np.pi, N)
    el = rng.uniform(0.02, 0.4, N)
    pos = np.c_[rng_m * np.cos(el) * np.sin(az), rng_m * np.cos(el) * np.cos(az), rng_m * np.sin(el)]
    x = np.c_[pos, rng.normal(0, 150, (N, 3)), rng.normal(0, 1, (N, 3))]
    stds = np.array([60, 60, 60, 15, 15, 15, 2, 2, 2.0])
    corr = np.eye(9)
    for i in range(3):  # position-velocity-acceleration correlation per axis
        corr[i, 3 + i] = corr[3 + i, i] = 0.6
        corr[3 + i, 6 + i] = corr[6 + i, 3 + i] = 0.5
        corr[i, 6 + i] = corr[6 + i, i] = 0.2
    P0 = corr * np.outer(stds, stds)
    P = np.repeat(P0[None], N, axis=0) * rng.uniform(0.5, 2.0, (N, 1, 1))
    truth = x @ F.T
    z = model.h(truth) + rng.normal(size=(N, 3)) * STD
    z[:, 0] = np.mod(z[:, 0], 2 * np.pi)
    return motion, model, x, P, z


# Peers ---------------------------------------------------------------------------------
def filterpy_filter(motion, model):
    from filterpy.kalman import ExtendedKalmanFilter

    site = model.site

    def hx(x):
        de, dn, du = x[0] - site[0], x[1] - site[1], x[2] - site[2]
        rho = math.hypot(de, dn)
        return np.array([math.atan2(de, dn) % (2 * math.pi), math.atan2(du, rho), math.hypot(rho, du)])

    def HJ(x):
        de, dn, du = x[0] - site[0], x[1] - site[1], x[2] - site[2]
        rho2 = de * de + dn * dn
        rho = math.sqrt(rho2)
        r2 = rho2 + du * du
        r = math.sqrt(r2)
        H = np.zeros((3, 9))
        H[0, :3] = dn / rho2, -de / rho2, 0.0
        H[1, :3] = -de * du / (rho * r2), -dn * du / (rho * r2), rho / r2
        H[2, :3] = de / r, dn / r, du / r
        return H

    def residual(a, b):
        y = a - b
        y[0] = (y[0] + math.pi) % (2 * math.pi) - math.pi
        return y

    f = ExtendedKalmanFilter(dim_x=9, dim_z=3)
    f.F = np.array(motion.F(DT))
    f.Q = np.array(motion.Q(DT))
    f.R = model.R.copy()

    def step(x, P, z):
        f.x, f.P = x, P  # FilterPy's predict/update build new arrays: no copy needed
        f.predict()
        f.update(z, HJ, hx, residual=residual)
        return f.x, f.P

    return step


def stonesoup_filter(model):
    from datetime import datetime, timedelta

    from stonesoup.models.measurement.nonlinear import CartesianToElevationBearingRange
    from stonesoup.models.transition.linear import CombinedLinearGaussianTransitionModel, ConstantAcceleration
    from stonesoup.predictor.kalman import ExtendedKalmanPredictor
    from stonesoup.types.detection import Detection
    from stonesoup.types.hypothesis import SingleHypothesis
    from stonesoup.types.state import GaussianState
    from stonesoup.updater.kalman import ExtendedKalmanUpdater

    trans = CombinedLinearGaussianTransitionModel([ConstantAcceleration(noise_diff_coeff=Q_PSD)] * 3)
    meas = CartesianToElevationBearingRange(ndim_state=9, mapping=(0, 3, 6), noise_covar=model.R.copy(),
                                            translation_offset=np.array([[s] for s in model.site]))
    predictor = ExtendedKalmanPredictor(trans)
    updater = ExtendedKalmanUpdater(meas, use_joseph_cov=True)
    t0 = datetime(2025, 1, 1)
    t1 = t0 + timedelta(seconds=DT)

    def to_ss(z):  # ours [compass az, el, range] -> Stone Soup's [el, bearing ccw from x, range]
        return np.array([[z[1]], [wrap_pi(math.pi / 2 - z[0])], [z[2]]])

    def step(x_ss, P_ss, z_ss):
        prior = GaussianState(x_ss, P_ss, timestamp=t0)
        pred = predictor.predict(prior, timestamp=t1)
        post = updater.update(SingleHypothesis(pred, Detection(z_ss, timestamp=t1, measurement_model=meas)))
        return post.state_vector, post.covar

    return step, to_ss


# Checks --------------------------------------------------------------------------------
def rel(a, b) -> float:
    a, b = np.asarray(a, float), np.asarray(b, float)
    return float(np.max(np.abs(a - b)) / max(1.0, np.max(np.abs(b))))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeats", type=int, default=15, help="timed rounds per candidate (median taken)")
    ap.add_argument("--tracks", type=int, default=1000, help="tracks in the batched update")
    ap.add_argument("--loop-tracks", type=int, default=200,
                    help="tracks the looped single-track peers run through per round (per-track time is what counts)")
    ap.add_argument("--json", help="also write the figures here")
    args = ap.parse_args()

    print(f"# Estimation core — {C.machine_line()}\n")
    motion, model, X, PP, Z = scene(max(args.tracks, args.loop_tracks, 10000))
    F, Q = np.array(motion.F(DT)), np.array(motion.Q(DT))
    x, P, z = X[0], PP[0], Z[0]
    r_diag = np.diag(model.R).copy()

    # The project's single-track path (what the fuser runs for each measurement).
    def zf_single():
        xp, Pp = ekf_predict(motion, x, P, DT)
        return ekf_update(model, xp, Pp, z)

    ref = zf_single()
    fp_step = filterpy_filter(motion, model)
    ss_step, to_ss = stonesoup_filter(model)
    x_ss, P_ss, z_ss = x[PERM].reshape(9, 1), P[np.ix_(PERM, PERM)], to_ss(z)
    t0 = time.perf_counter()
    kernels = numba_kernels()
    if kernels:  # what numba costs a process that uses it: import, then the first call compiles
        t1 = time.perf_counter()
        kernels[0](x, P, F, Q, model.site, np.diag(model.R).copy(), z)
        print(f"numba: import {t1 - t0:.2f} s, compiling the single-track step {time.perf_counter() - t1:.2f} s\n")

    checks = {}
    xl, Pl, nis_l = lean_step(x, P, F, Q, model.site, r_diag, z)
    checks["lean numpy (3×3 special case)"] = max(rel(xl, ref.x), rel(Pl, ref.P), abs(nis_l - ref.nis))
    b1 = batch.ekf_step(motion, model, x[None], P[None], DT, z[None])
    checks["zfusion batch, N = 1"] = max(rel(b1.x[0], ref.x), rel(b1.P[0], ref.P))
    xf, Pf = fp_step(x, P, z)
    checks["FilterPy EKF"] = max(rel(xf, ref.x), rel(Pf, ref.P))
    xs, Ps = ss_step(x_ss, P_ss, z_ss)
    inv = np.argsort(PERM)
    checks["Stone Soup EKF (numerical Jacobian)"] = max(rel(np.asarray(xs, float).ravel()[inv], ref.x),
                                                        rel(np.asarray(Ps, float)[np.ix_(inv, inv)], ref.P))
    if kernels:
        step_nb, batch_nb = kernels
        xn, Pn, nis_n = step_nb(x, P, F, Q, model.site, r_diag, z)
        checks["numba (optional)"] = max(rel(xn, ref.x), rel(Pn, ref.P), abs(nis_n - ref.nis))
    print("Agreement with the project's path (max relative difference of x⁺, P⁺):")
    for k, v in checks.items():
        print(f"  {k:<38} {v:.1e}")
    bad = {k: v for k, v in checks.items() if v > (1e-4 if "Stone" in k else 1e-8)}
    if bad:
        raise SystemExit(f"candidates disagree with the project's path: {bad}")

    # --- single update ---------------------------------------------------------------
    single = {
        "zfusion (ekf.ekf_predict + ekf_update)": zf_single,
        "zfusion batch, N = 1": lambda: batch.ekf_step(motion, model, x[None], P[None], DT, z[None]),
        "lean numpy, 3×3 special case (benchmark only)": lambda: lean_step(x, P, F, Q, model.site, r_diag, z),
        "FilterPy ExtendedKalmanFilter": lambda: fp_step(x, P, z),
        "Stone Soup ExtendedKalman{Predictor,Updater}": lambda: ss_step(x_ss, P_ss, z_ss),
    }
    if kernels:
        single["numba @njit (optional dependency)"] = lambda: step_nb(x, P, F, Q, model.site, r_diag, z)
    load0 = C.load_now()
    res_single = C.interleaved(single, args.repeats)
    fp = res_single["FilterPy ExtendedKalmanFilter"]["median_us"]
    fp_cpu = res_single["FilterPy ExtendedKalmanFilter"]["cpu_median_us"]
    rows = [[k, C.fmt_us(v["median_us"]), C.fmt_us(v["min_us"]), C.fmt_us(v["cpu_median_us"]),
             f"{fp / v['median_us']:.2f}×"] for k, v in res_single.items()]
    print(f"\n## One predict + update, one track (µs per call; load {load0:.1f} → {C.load_now():.1f})\n")
    print(C.table(["implementation", "median", "min", "CPU median", "speed vs FilterPy"], rows))

    # --- where the project's single path spends its time --------------------------------
    xp, Pp = ekf_predict(motion, x, P, DT)
    nu, H = model.innovation_and_jacobian(z, xp)
    stages = {
        "ekf_predict (F P Fᵀ + Q, symmetrise)": lambda: ekf_predict(motion, x, P, DT),
        "SphericalModel.innovation_and_jacobian (h, wrap, H)": lambda: model.innovation_and_jacobian(z, xp),
        "kalman.update (Cholesky, gain, Joseph, symmetrise, NIS)": lambda: kalman.update(xp, Pp, nu, H, model.R),
    }
    res_stages = C.interleaved(stages, max(5, args.repeats // 2))
    print("\n## Where the project's single-track step goes (µs per call)\n")
    print(C.table(["stage", "median", "CPU median"],
                  [[k, C.fmt_us(v["median_us"]), C.fmt_us(v["cpu_median_us"])] for k, v in res_stages.items()]))

    # --- batched ------------------------------------------------------------------------
    N, L = args.tracks, args.loop_tracks
    xb, Pb, zb = X[:N].copy(), PP[:N].copy(), Z[:N].copy()
    xs_ss = [X[i][PERM].reshape(9, 1) for i in range(L)]
    Ps_ss = [PP[i][np.ix_(PERM, PERM)] for i in range(L)]
    zs_ss = [to_ss(Z[i]) for i in range(L)]

    def loop_zf():
        for i in range(L):
            xp, Pp = ekf_predict(motion, X[i], PP[i], DT)
            ekf_update(model, xp, Pp, Z[i])

    def loop_fp():
        for i in range(L):
            fp_step(X[i], PP[i], Z[i])

    def loop_ss():
        for i in range(L):
            ss_step(xs_ss[i], Ps_ss[i], zs_ss[i])

    cands = {
        f"zfusion batch.ekf_step, N = {N}": (lambda: batch.ekf_step(motion, model, xb, Pb, DT, zb), N),
        "zfusion single path, looped": (loop_zf, L),
        "FilterPy, looped": (loop_fp, L),
        "Stone Soup, looped": (loop_ss, L),
    }
    if kernels:
        cands[f"numba batch kernel, N = {N} (optional)"] = (
            lambda: batch_nb(xb, Pb, F, Q, model.site, r_diag, zb), N)
    load0 = C.load_now()
    res_b = C.interleaved({k: f for k, (f, _) in cands.items()}, max(5, args.repeats // 2), target_s=0.05)
    fp_track = res_b["FilterPy, looped"]["median_us"] / L
    rows = []
    for k, (_, n) in cands.items():
        v = res_b[k]
        per = v["median_us"] / n
        rows.append([k, C.fmt_us(per), C.fmt_us(v["min_us"] / n), C.fmt_us(v["cpu_median_us"] / n),
                     f"{fp_track / per:.1f}×"])
    print(f"\n## Batched: µs per track per predict + update (load {load0:.1f} → {C.load_now():.1f}; looped peers "
          f"over {L} tracks)\n")
    print(C.table(["implementation", "median", "min", "CPU median", "speed vs FilterPy"], rows))

    sweep = {}
    for n in (1, 10, 100, 1000, 10000):
        xs_, Ps_, zs_ = X[:n].copy(), PP[:n].copy(), Z[:n].copy()
        sweep[n] = lambda xs_=xs_, Ps_=Ps_, zs_=zs_: batch.ekf_step(motion, model, xs_, Ps_, DT, zs_)
    res_sw = C.interleaved(sweep, max(5, args.repeats // 2), target_s=0.05)
    print("\n## zfusion batch.ekf_step by stack size\n")
    print(C.table(["tracks", "µs per call (median)", "µs per track (median)", "µs per track (CPU median)"],
                  [[n, C.fmt_us(v["median_us"]), C.fmt_us(v["median_us"] / n), C.fmt_us(v["cpu_median_us"] / n)]
                   for n, v in res_sw.items()]))

    zf1 = res_single["zfusion (ekf.ekf_predict + ekf_update)"]["median_us"]
    bper = res_b[f"zfusion batch.ekf_step, N = {N}"]["median_us"] / N
    print("\n## Targets\n")
    print(f"- single update ≥ 3× faster than FilterPy: project path {fp / zf1:.2f}× "
          f"({'met' if fp / zf1 >= 3 else 'MISSED'}); lean 3×3 numpy {fp / res_single['lean numpy, 3×3 special case (benchmark only)']['median_us']:.2f}×"
          + (f"; numba {fp / res_single['numba @njit (optional dependency)']['median_us']:.1f}×" if kernels else
             "; numba not installed (pip install numba for that row)"))
    print(f"- batched update of {N} tracks < 2 µs per track: {bper:.2f} µs ({'met' if bper < 2 else 'MISSED'})")
    if args.json:
        with open(args.json, "w") as fh:
            json.dump({"machine": C.machine_line(), "checks": checks, "single": res_single, "stages": res_stages,
                       "batched": {k: {**res_b[k], "tracks": n} for k, (_, n) in cands.items()},
                       "sweep": {str(k): v for k, v in res_sw.items()}, "FilterPy_single_us": fp,
                       "FilterPy_single_cpu_us": fp_cpu, "time": time.strftime("%Y-%m-%d %H:%M:%S"),
                       "pid": os.getpid()}, fh, indent=1)


if __name__ == "__main__":
    main()
