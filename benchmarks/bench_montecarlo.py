"""Monte Carlo evaluation: the time of ``zfusion eval --scenario patent-3d --runs 1000``,
and the speed-up from running the estimator over all runs at once (``fusion.batch``)
instead of run after run.

    python benchmarks/bench_montecarlo.py [--runs 1000] [--all-methods] [--repeats 1]

1. The command itself, timed from outside (wall clock, and the CPU time of the child):
   ``zfusion eval --scenario patent-3d --runs N --methods SS`` (the scenario's method),
   and with ``--all-methods`` the plain command (every method the scenario can feed).
2. In-process, for the SS method, the parts: building every run's measurement stream
   (``services.evaluation.merged_measurements``), the estimator run by run
   (``run_method``), and the same estimator vectorised across runs — one
   :func:`fusion.batch.ekf_step` per scan for all runs. The vectorised estimates are
   checked against the run-by-run ones (1e-9) before any time is reported.
"""

from __future__ import annotations

import argparse
import json
import resource
import statistics
import subprocess
import sys
import time

import _common as C
import numpy as np

SCENARIO = "patent-3d"


def time_cli(argv: list[str], repeats: int) -> dict:
    walls, cpus = [], []
    for _ in range(repeats):
        r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
        t0 = time.perf_counter()
        p = subprocess.run([sys.executable, "-m", "services.cli", *argv], capture_output=True, text=True,
                           cwd=str(C.REPO))
        wall = time.perf_counter() - t0
        r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
        if p.returncode != 0:
            raise SystemExit(f"zfusion {' '.join(argv)} failed:\n{p.stderr[-3000:]}")
        walls.append(wall)
        cpus.append((r1.ru_utime - r0.ru_utime) + (r1.ru_stime - r0.ru_stime))
    return {"wall_s": statistics.median(walls), "cpu_s": statistics.median(cpus), "walls": walls}


def ss_vectorised(scenario, streams: list[list], clock: dict | None = None) -> list[list[tuple]]:
    """The SS method (fusion.patent, CentralisedMethod + pieces_stacked) over all runs at
    once. Needs every run to have the same scan structure (sensors, times): true for
    patent-3d (detection probability 1); anything else is refused."""
    from fusion import batch
    from fusion.methods import method_config
    from fusion.init3d import initial_state
    from fusion.grouping import TimeGrouper
    from fusion.patent import TrackerConfig, pieces_stacked

    cfg = TrackerConfig.from_dict(method_config(scenario.tracker, "SS"))
    motion = cfg.motion_model()
    n_x = motion.n_x
    scans = []
    for stream in streams:  # group each run's stream into scans exactly as the method does
        g = TimeGrouper(cfg.pair_tol, one_per_sensor=True)
        out, t_prev = [], None
        for m in stream:
            if t_prev is not None and m.t > t_prev:
                out += g.advance(t_prev)
            out += g.push(m)
            t_prev = m.t
        out += g.finish()
        scans.append(out)
    shape = [[(m.t, m.sensor, m.kind) for m in s] for s in scans[0]]
    for s in scans[1:]:
        if [[(m.t, m.sensor, m.kind) for m in sc] for sc in s] != shape:
            raise SystemExit("runs differ in scan structure; the vectorised path needs identical scans")
    R = len(streams)
    models, zs = [], []
    for k in range(1, len(scans[0])):  # the stacked model and every run's stacked z, per scan
        (model, _), = pieces_stacked(scans[0][k], n_x)
        models.append(model)
        zs.append(np.stack([np.concatenate([np.asarray(m.z, float) for m in s[k]]) for s in scans]))
    c0 = time.perf_counter()
    first = [initial_state(s[0], n_x, cfg.priors()) for s in scans]
    x = np.stack([f[0] for f in first])
    P = np.stack([f[1] for f in first])
    t = scans[0][0][0].t
    out = [[(t, x[r], P[r], None)] for r in range(R)]
    results = []
    for k in range(1, len(scans[0])):
        tk = scans[0][k][0].t
        res = batch.ekf_step(motion, models[k - 1], x, P, tk - t, zs[k - 1])
        x, P, t = res.x, res.P, tk
        results.append((t, res))
    if clock is not None:
        clock["filter"] = time.perf_counter() - c0  # initialisation + the batched steps
    for t, res in results:
        for r in range(R):
            out[r].append((t, res.x[r], res.P[r], float(res.nis[r])))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", type=int, default=1000)
    ap.add_argument("--repeats", type=int, default=1, help="timings of each part (median reported)")
    ap.add_argument("--all-methods", action="store_true",
                    help="also time the plain command (every method of the scenario; several minutes)")
    ap.add_argument("--json")
    args = ap.parse_args()
    from sensors_sim import load_scenario
    from services.evaluation import merged_measurements, run_method

    print(f"# Monte Carlo, {SCENARIO}, {args.runs} runs — {C.machine_line()}\n", flush=True)
    cli = {}
    cmd_ss = ["eval", "--scenario", SCENARIO, "--runs", str(args.runs), "--methods", "SS"]
    cli["zfusion eval --scenario patent-3d --runs %d --methods SS" % args.runs] = time_cli(cmd_ss, args.repeats)
    if args.all_methods:
        cli["zfusion eval --scenario patent-3d --runs %d" % args.runs] = time_cli(cmd_ss[:5], args.repeats)
    print(C.table(["command", "wall s (median)", "CPU s"],
                  [[k, f"{v['wall_s']:.1f}", f"{v['cpu_s']:.1f}"] for k, v in cli.items()]), flush=True)

    sc = load_scenario(SCENARIO)
    parts: dict[str, list[float]] = {"streams": [], "run by run": [], "vectorised": [], "vectorised filter": []}
    for _ in range(args.repeats):
        t0 = time.perf_counter()
        streams = [merged_measurements(sc, r) for r in range(args.runs)]
        t1 = time.perf_counter()
        scalar = [run_method(sc, "SS", None, r, measurements=streams[r]) for r in range(args.runs)]
        t2 = time.perf_counter()
        clock: dict = {}
        vec = ss_vectorised(sc, streams, clock)
        t3 = time.perf_counter()
        parts["vectorised filter"].append(clock["filter"])
        parts["streams"].append(t1 - t0)
        parts["run by run"].append(t2 - t1)
        parts["vectorised"].append(t3 - t2)
    worst = 0.0
    for r in range(args.runs):
        a = [e for e in scalar[r] if e.node == "centre"]
        b = vec[r]
        assert len(a) == len(b), (r, len(a), len(b))
        for ea, (t, x, P, nis) in zip(a, b):
            assert ea.t == t
            worst = max(worst, float(np.max(np.abs(ea.x - x)) / max(1.0, np.max(np.abs(ea.x)))),
                        float(np.max(np.abs(ea.P - P)) / max(1.0, np.max(np.abs(ea.P)))))
    if worst > 1e-9:
        raise SystemExit(f"vectorised estimates differ from the run-by-run ones by {worst:.3g} (relative)")
    med = {k: statistics.median(v) for k, v in parts.items()}
    print(f"\n## SS estimator over {args.runs} runs, in-process (s, median of {args.repeats}; vectorised = "
          f"run-by-run to {worst:.1e} relative)\n")
    rows = [["measurement streams (sensors_sim, all runs)", f"{med['streams']:.2f}", ""],
            ["estimator run by run (run_method)", f"{med['run by run']:.2f}", "1.0×"],
            ["estimator vectorised across runs (fusion.batch), all of it", f"{med['vectorised']:.3f}",
             f"{med['run by run'] / med['vectorised']:.0f}×"],
            ["  of which: scan grouping and arrays, run by run in Python",
             f"{med['vectorised'] - med['vectorised filter']:.3f}", ""],
            ["  of which: initialisation + batched EKF steps", f"{med['vectorised filter']:.3f}",
             f"{med['run by run'] / med['vectorised filter']:.0f}×"],
            ["streams + estimator, run by run", f"{med['streams'] + med['run by run']:.2f}", "1.0×"],
            ["streams + estimator, vectorised", f"{med['streams'] + med['vectorised']:.2f}",
             f"{(med['streams'] + med['run by run']) / (med['streams'] + med['vectorised']):.1f}×"]]
    print(C.table(["part", "time s", "speed-up"], rows))
    if args.json:
        with open(args.json, "w") as fh:
            json.dump({"machine": C.machine_line(), "runs": args.runs, "cli": cli, "parts": parts,
                       "agreement": worst}, fh, indent=1)


if __name__ == "__main__":
    main()
