"""Where the fuser's time goes per measurement, without Zenoh: the same bytes the Zenoh
benchmark sends, fed to :class:`services.fuser.FuserCore` and ``encode_estimate`` exactly
as ``services/fuser.py``'s loop does, timed stage by stage (thread CPU time, so other
load on the machine does not inflate it), plus a cProfile of the whole loop.

    python benchmarks/profile_fuser.py [--sensors 4] [--measurements 20000] [--tracks 1]

The sum of the stages bounds the fuser's throughput on one core from above (the real
process also pays Zenoh's receive path, the queue and the publish).
"""

from __future__ import annotations

import argparse
import cProfile
import io
import math
import pstats
import statistics
import tempfile
import time
from pathlib import Path

import _common as C
import msgpack
import numpy as np

import _rig


T_STEP = 0.002  # s between a sensor's scans in the profiled stream (2,000/s over 4 sensors)


def wire_stream(S: int, N: int, n_meas: int, rate: float = 2000.0) -> list[tuple[str, bytes]]:
    """(key, bytes) in publication order: what the load generator publishes."""
    from schemas import KeySpace

    keys = KeySpace("prof")
    ids = _rig.sensor_ids(S)
    sites = _rig.sensor_sites(S)
    p0, v0 = _rig.targets(N)
    stds = [math.radians(_rig.STD[0]), math.radians(_rig.STD[1]), _rig.STD[2]]
    T = S * N / rate
    n_scans = max(S, n_meas // N)
    out = []
    seq = [0] * S
    wm = [0] * S
    rng = np.random.default_rng(3)
    for k in range(n_scans):
        s = k % S
        t = 1.0 + k * T / S
        d = p0 + v0 * t - sites[s]
        rho = np.hypot(d[:, 0], d[:, 1])
        z = np.c_[np.mod(np.arctan2(d[:, 0], d[:, 1]), 2 * np.pi), np.arctan2(d[:, 2], rho), np.hypot(rho, d[:, 2])]
        z += rng.normal(size=z.shape) * stds
        z[:, 0] = np.mod(z[:, 0], 2 * np.pi)
        for az, el, rg in z.tolist():
            out.append((keys.meas(ids[s]), msgpack.packb({
                "v": 1, "kind": "az_el_range", "src": ids[s], "seq": seq[s], "t": t, "sensor": ids[s],
                "site": sites[s].tolist(), "az": az, "el": el, "range": rg, "std_az": stds[0], "std_el": stds[1],
                "std_range": stds[2]})))
            seq[s] += 1
        wm[s] += 1
        out.append((keys.meas(ids[s]), msgpack.packb({"v": 1, "kind": "watermark", "src": ids[s], "seq": wm[s],
                                                      "t": t, "final": False})))
    return out


def make_core(S: int, N: int, ekf: str = "batch"):
    from fusion.methods import make_method
    from schemas import KeySpace
    from services.fuser import FuserCore
    from services.node import RejectLog

    with tempfile.TemporaryDirectory() as d:
        sc_path = _rig.write_scenario(Path(d) / "bench.toml", S, 1e6)
        from sensors_sim import load_scenario

        sc = load_scenario(str(sc_path))
    method = make_method("RADAR3D", sc.tracker) if N == 1 else _rig.MultiTrack(sc.tracker, N, ekf)
    return FuserCore(method, list(sc.sensors), KeySpace("prof"), RejectLog("prof"), timeout=1e9)


class _Stub:
    name = "stub"

    def process(self, m):
        return []

    def advance(self, t):
        return []

    def finish(self):
        return []


def run_loop(core, stream, publish, encode: bool = True) -> int:
    """The loop of services/fuser.py when it is never behind: offer each message, step,
    encode and publish each estimate."""
    from schemas import encode_estimate

    seq = 0
    for key, data in stream:
        core.offer(key, data, 0.0)
        for e in core.step(0.0):
            seq += 1
            if encode:
                publish(encode_estimate(e, "fuser", seq))
    return seq


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sensors", type=int, default=4)
    ap.add_argument("--tracks", type=int, default=1)
    ap.add_argument("--measurements", type=int, default=20000)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--top", type=int, default=25, help="lines of the cProfile listing")
    args = ap.parse_args()
    from schemas import decode, encode_estimate, to_measurement

    S, N = args.sensors, args.tracks
    stream = wire_stream(S, N, args.measurements)
    n_meas = sum(1 for _, b in stream if b"az_el_range" in b[:40])
    print(f"# Fuser per-measurement cost without Zenoh — {C.machine_line()}")
    print(f"{S} sensors, {N} track(s), {n_meas} measurements + {len(stream) - n_meas} watermarks\n")

    def loop_cpu(method_stub: bool = False, encode: bool = True) -> float:
        vals = []
        for _ in range(args.repeats):
            core = make_core(S, N)
            if method_stub:
                core.method = _Stub()
            c0 = time.thread_time()
            run_loop(core, stream, lambda b: None, encode)
            vals.append((time.thread_time() - c0) / n_meas * 1e6)
        return statistics.median(vals)

    def per(fn, items, count):
        vals = []
        for _ in range(args.repeats):
            c0 = time.thread_time()
            for it in items:
                fn(it)
            vals.append((time.thread_time() - c0) / count * 1e6)
        return statistics.median(vals)

    whole = loop_cpu()
    no_encode = loop_cpu(encode=False)
    stub = loop_cpu(method_stub=True, encode=False)
    print(f"whole loop (offer + step + encode_estimate): {whole:.1f} µs CPU per measurement "
          f"→ at most {1e6 / whole:,.0f} measurements/s on one core, before Zenoh's share\n")

    msgs = [decode(b) for _, b in stream]
    meas = [to_measurement(m) for m in msgs if m.kind == "az_el_range"]
    core = make_core(S, N)
    ests = []
    for key, data in stream:
        core.offer(key, data, 0.0)
        ests += core.step(0.0)
    dec = per(lambda kb: decode(kb[1]), stream, n_meas)
    tom = per(to_measurement, [m for m in msgs if m.kind == "az_el_range"], n_meas)
    stages = {
        "decode (msgpack + validation): a measurement and its watermark": dec,
        "to_measurement": tom,
        "merger and FuserCore bookkeeping (offer, step)": stub - dec - tom,
        "method: scan grouping, models, EKF predict + update, Estimate": no_encode - stub,
        "encode_estimate (validation + msgpack of x, P)": whole - no_encode,
    }
    rows = [[k, f"{v:.1f}"] for k, v in stages.items()] + [["total", f"{whole:.1f}"]]
    rows.append(["→ measurements/s on one core (before Zenoh's share)", f"{1e6 / whole:,.0f}"])
    print(C.table(["stage (whole-loop differences)", "µs CPU per measurement"], rows))
    # In isolation, on the same inputs: the wire encode, and the EKF step beside the lean
    # 3 × 3 special case of benchmarks/ekf_kernels.py (a lower bound for numpy).
    from ekf_kernels import lean_step
    from fusion.ekf import ekf_predict, ekf_update
    from fusion.measurement.kinds import model_of

    enc = per(lambda e: encode_estimate(e, "fuser", 1), ests, len(ests)) * len(ests) / n_meas
    line = f"\n(in isolation: encode_estimate {enc:.1f} µs per measurement"
    motion = getattr(core.method, "motion", None)
    if motion is not None and N == 1:
        F, Q = np.array(motion.F(T_STEP)), np.array(motion.Q(T_STEP))
        x0, P0 = ests[-1].x, ests[-1].P
        mdl = model_of(meas[-1])
        r_diag = np.diag(mdl.R).copy()
        zz = np.asarray(meas[-1].z, float)
        lean = per(lambda _: lean_step(x0, P0, F, Q, mdl.site, r_diag, zz), range(2000), 2000)
        cur = per(lambda _: ekf_update(mdl, *ekf_predict(motion, x0, P0, T_STEP), zz), range(2000), 2000)
        line += f"; EKF predict + update {cur:.1f} µs, lean 3 × 3 special case {lean:.1f} µs"
    print(line + ")")

    pr = cProfile.Profile()
    core = make_core(S, N)
    pr.enable()
    run_loop(core, stream, lambda b: None)
    pr.disable()
    s = io.StringIO()
    pstats.Stats(pr, stream=s).sort_stats("tottime").print_stats(args.top)
    print("\ncProfile of the loop, by own time:\n")
    out = s.getvalue().replace(str(C.REPO) + "/", "")  # paths relative to the repository
    print("\n".join(line for line in out.splitlines() if line.strip())[:6000])


if __name__ == "__main__":
    main()
