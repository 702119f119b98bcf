"""Regional scale-out: each regional fuser's and the system fuser's process time against
the single fuser's on the same plots.

One run of a scenario with ``[regions]`` (``region-4000``: four quadrants) is generated
once; the regional topology (:class:`fusion.regional.RegionalMethod`, each part timed by
``time.process_time`` around its own calls, as ``zfusion eval --topology regional``
reports ``cpu_s``) and then the single centralised fuser (``run_method`` timed whole)
run over the same plots in this process, in turn, ``--repeats`` times. The ratios are
what the regional issue's criterion reads: the busiest regional fuser's time and the
system fuser's over the single fuser's of the same repeat.

    python benchmarks/bench_regional.py --scenario region-4000 --duration-s 60 --repeats 2
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time

from _common import machine_line  # puts the repository on sys.path

import services  # noqa: F401  (the services' one BLAS thread, before NumPy loads)
from sensors_sim import load_scenario
from services.evaluation import build_method, merged_measurements, run_method
from services.scoring import Looks


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenario", default="region-4000")
    ap.add_argument("--duration-s", type=float, default=60.0)
    ap.add_argument("--run", type=int, default=0)
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--method", default="SS")
    args = ap.parse_args(argv)
    scenario = load_scenario(args.scenario)
    if not scenario.regions:
        ap.error(f"scenario {args.scenario!r} declares no [regions]")
    scenario = dataclasses.replace(scenario, duration=args.duration_s)
    plots = merged_measurements(scenario, args.run, looks=Looks())
    print(f"# Regional scale-out: {args.scenario}, run {args.run}, {args.duration_s:g} s, {len(plots)} plots, "
          f"{args.method}\n{machine_line()}\n")
    print("| repeat | single fuser (s) | " + " | ".join(f"{r} (s)" for r in scenario.regions)
          + " | system (s) | busiest ÷ single | system ÷ single |")
    print("|---" * (len(scenario.regions) + 5) + "|")
    for k in range(args.repeats):
        regional = build_method(scenario, args.method, {}, "regional", time.process_time)
        run_method(scenario, args.method, {}, args.run, plots, regional)
        t0 = time.process_time()
        run_method(scenario, args.method, {}, args.run, plots)
        single = time.process_time() - t0
        cpu = dict(regional.cpu)
        busiest = max(v for part, v in cpu.items() if part != "system")
        print(f"| {k} | {single:.1f} | " + " | ".join(f"{cpu[r]:.1f}" for r in scenario.regions)
              + f" | {cpu['system']:.1f} | {busiest / single:.3f} | {cpu['system'] / single:.3f} |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
