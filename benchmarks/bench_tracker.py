"""One scenario's many-target tracker against another checkout's, in the same run: CPU
per run and whether the two give the same tracks.

    python benchmarks/bench_tracker.py --scenario air-picture-dense --duration 60
        [--runs 1] [--set association=jipda] --against CHECKOUT

Each side runs in a process of its own with its own code (``CHECKOUT`` first, then this
checkout, per run): the run's plots (``services.evaluation.merged_measurements``, not
timed) through ``run_method`` with the SS method, as ``zfusion eval`` feeds it, its
process CPU timed. The two sides' estimates are then compared field by field (time,
track, state, covariance): a change meant to be only faster must print ``same``.
"""

from __future__ import annotations

import argparse
import ast
import pickle
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

_CHILD = r"""
import pickle, sys, time
from services.evaluation import merged_measurements, run_method
from services.scenario import load
scenario, duration, run, overrides, out = sys.argv[1], float(sys.argv[2]), int(sys.argv[3]), eval(sys.argv[4]), sys.argv[5]
sc = load(scenario, duration=duration)
plots = merged_measurements(sc, run)
t0 = time.process_time()
est = run_method(sc, "SS", overrides, run, plots)
cpu = time.process_time() - t0
rows = [(e.t, e.track, e.x, e.P) for e in est]
pickle.dump({"cpu": cpu, "rows": rows}, open(out, "wb"))
"""


def side(checkout: Path, scenario: str, duration: float, run: int, overrides: dict) -> dict:
    with tempfile.NamedTemporaryFile(suffix=".pkl") as f:
        subprocess.run([sys.executable, "-c", _CHILD, scenario, str(duration), str(run), repr(overrides), f.name],
                       cwd=checkout, check=True, env={"PYTHONPATH": str(checkout), "PATH": "/usr/bin:/bin"})
        return pickle.load(open(f.name, "rb"))


def same(a: list, b: list) -> bool:
    return len(a) == len(b) and all(
        ta == tb and ka == kb and np.array_equal(xa, xb) and np.array_equal(Pa, Pb)
        for (ta, ka, xa, Pa), (tb, kb, xb, Pb) in zip(a, b))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenario", required=True)
    ap.add_argument("--duration", type=float, required=True)
    ap.add_argument("--runs", type=int, default=1)
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="a [tracker] key (Python literal)")
    ap.add_argument("--against", type=Path, required=True, help="another checkout of the project")
    args = ap.parse_args(argv)
    overrides = {}
    for kv in args.set:
        key, _, value = kv.partition("=")
        try:
            overrides[key] = ast.literal_eval(value)
        except (ValueError, SyntaxError):
            overrides[key] = value
    here = Path(__file__).resolve().parents[1]
    print(f"{args.scenario}, {args.duration:g} s, SS {overrides or ''}: tracker CPU s per run")
    print("run  against  this  against/this  tracks")
    for run in range(args.runs):
        old = side(args.against.resolve(), args.scenario, args.duration, run, overrides)
        new = side(here, args.scenario, args.duration, run, overrides)
        print(f"{run:3d}  {old['cpu']:7.1f}  {new['cpu']:5.1f}  {old['cpu'] / new['cpu']:12.2f}  "
              f"{'same' if same(old['rows'], new['rows']) else 'DIFFERENT'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
