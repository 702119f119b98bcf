"""The cost of a re-filtering checkpoint (:class:`fusion.oosm.Refiltering`): a live fuser
copies its estimator at every release that changed it. Per many-target method, on
``air-picture`` run 0 fed up to ``--t`` with the frame at ``--t`` still open (as at a
release), the CPU time of one checkpoint as taken now (the measurements the estimator
holds shared with the re-filtering log) and as it was (everything deep-copied).

    python benchmarks/bench_oosm.py [--t 60] [--methods SS HNV] [--repeats 5]
"""

from __future__ import annotations

import argparse
import copy
import json
import statistics
import time

import _common as C
from fusion.methods import make_method, method_config
from fusion.oosm import Refiltering
from sensors_sim import load_scenario
from services.evaluation import merged_measurements

SCENARIO = "air-picture"


def fed(method_name: str, t_end: float):
    """A Refiltering of the method, fed run 0 up to ``t_end`` (its frame left open)."""
    sc = load_scenario(SCENARIO)
    rf = Refiltering(make_method(method_name, method_config(sc.tracker, method_name)), window=10.0)
    stream = merged_measurements(sc, 0)
    for t in sorted({m.t for m in stream if m.t <= t_end}):
        rf.step([m for m in stream if m.t == t], t - 0.5)
    return rf


def cpu_ms(fn, repeats: int) -> float:
    """Median CPU time of one call (ms) over ``repeats`` batches of calls."""
    n = C.calibrate(fn, 0.2)
    times = []
    for _ in range(repeats):
        c0 = time.thread_time()
        for _ in range(n):
            fn()
        times.append((time.thread_time() - c0) / n * 1e3)
    return statistics.median(times)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--t", type=float, default=60.0, help="scenario time the estimator is fed to (s)")
    ap.add_argument("--methods", nargs="+", default=["SS", "HNV"], help="many-target methods to measure")
    ap.add_argument("--repeats", type=int, default=5, help="batches of calls per figure (median)")
    ap.add_argument("--json", help="also write the figures here")
    args = ap.parse_args()
    rows, out = [], {}
    for name in args.methods:
        rf = fed(name, args.t)
        method = rf.method
        tracks = len(method.tracks) if hasattr(method, "tracks") else len(method.centre.tracks)
        now = cpu_ms(lambda: rf._copy(method), args.repeats)
        before = cpu_ms(lambda: copy.deepcopy(method), args.repeats)
        out[name] = {"tracks": tracks, "log": len(rf._log), "checkpoint_ms": now, "deepcopy_ms": before}
        rows.append([name, tracks, len(rf._log), f"{before:.2f}", f"{now:.2f}", f"{before / now:.1f}×"])
    print(f"# Re-filtering checkpoint ({SCENARIO}, run 0, at t = {args.t:g} s)\n")
    print(C.machine_line() + "\n")
    print(C.table(["method", "tracks", "measurements logged", "deep copy (ms CPU)", "checkpoint now (ms CPU)",
                   "gain"], rows))
    if args.json:
        with open(args.json, "w") as f:
            json.dump(out, f, indent=1)


if __name__ == "__main__":
    main()
