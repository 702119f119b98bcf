"""The true-association reference of a many-target scenario: the floor any associator
can reach with zfusion's filter and track logic on the same plots.

Each aircraft's own detections only (the events the emulator made from it; every false
alarm and every other aircraft's plot left out) go through the same method and
``[tracker]`` as ``zfusion eval`` runs — one tracker per aircraft, so no plot can be
taken by the wrong track — and the union of their tracks is scored as ``zfusion eval``
scores a run (:func:`services.scoring.track_steps`, GOSPA c = 1000 m, p = 2), with the
dense report's GOSPA parts and formation merges (:mod:`services.report.dense`).

Two start rules: ``tracker`` (the scenario's own confirmation, M of N, as the real
trackers confirm) and ``first`` (``confirm_m = confirm_n = 1``: a track is published from
the frame of its aircraft's first detection). Neither is a product: the association is
the truth's.

    python benchmarks/oracle_dense.py --runs 4 --duration-s 60
"""

from __future__ import annotations

import argparse
import dataclasses
import heapq
import json
import sys
import time

import numpy as np

from _common import machine_line  # noqa: F401  (puts the repository on sys.path)

from sensors_sim import load_scenario
from sensors_sim.emulators import sensor_events
from services.evaluation import GOSPA_CUTOFF, run_method
from services.report.dense import formation_merges, formation_pairs, gospa_parts
from services.scoring import track_steps
from services.summary import tracks_summary
from fusion.mtt_metrics import score_tracks

START_RULES = {"tracker": {}, "first": {"confirm_m": 1, "confirm_n": 1}}


def own_plots(scenario, run: int) -> dict[str, list]:
    """Per target, its own published plots in ``(t, sensor, seq)`` order."""
    per: dict[str, list[list]] = {}
    for sid in scenario.sensors:
        streams: dict[str, list] = {}
        for ev in sensor_events(scenario, sid, run=run):
            if ev.measurement is not None and not ev.clutter and ev.target:
                streams.setdefault(ev.target, []).append(ev.measurement)
        for target, plots in streams.items():
            per.setdefault(target, []).append(plots)
    return {t: list(heapq.merge(*s, key=lambda m: m.order_key)) for t, s in per.items()}


def run_oracle(scenario, run: int, method: str, overrides: dict) -> tuple[list, float]:
    """The union of the per-aircraft trackers' estimates (track ids ``target/track``) and
    their CPU seconds."""
    estimates, cpu = [], 0.0
    for target, plots in own_plots(scenario, run).items():
        t0 = time.process_time()
        got = run_method(scenario, method, overrides, run, plots)
        cpu += time.process_time() - t0
        estimates += [dataclasses.replace(e, track=f"{target}/{e.track}") for e in got]
    estimates.sort(key=lambda e: e.t)
    return estimates, cpu


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenario", default="air-picture-dense")
    ap.add_argument("--method", default="SS")
    ap.add_argument("--association", default="gnn", help="the association of each aircraft's own tracker")
    ap.add_argument("--runs", type=int, default=4)
    ap.add_argument("--first-run", type=int, default=0)
    ap.add_argument("--duration-s", type=float, default=None)
    ap.add_argument("--json", default=None)
    args = ap.parse_args(argv)
    scenario = load_scenario(args.scenario)
    if args.duration_s is not None:
        scenario = dataclasses.replace(scenario, duration=args.duration_s)
    pairs = formation_pairs(scenario)
    print(f"# True-association reference on {args.scenario}, runs {args.first_run}–{args.first_run + args.runs - 1}, "
          f"{args.method} with association {args.association}\n{machine_line()}\n")
    out = {"scenario": args.scenario, "duration_s": args.duration_s, "runs": args.runs, "first_run": args.first_run,
           "command": "python benchmarks/oracle_dense.py " + " ".join(argv if argv is not None else sys.argv[1:]),
           "rules": {}}
    for rule, extra in START_RULES.items():
        overrides = {"association": args.association, **extra}
        scores, merges, cpu = [], [], []
        for run in range(args.first_run, args.first_run + args.runs):
            estimates, c = run_oracle(scenario, run, args.method, overrides)
            steps = track_steps(scenario, estimates, run)
            scores.append(score_tracks(steps, GOSPA_CUTOFF))
            merges.append(formation_merges(steps, pairs))
            cpu.append(c)
        m = tracks_summary(scores)
        m.update(overrides=overrides, cpu_s_per_run=cpu, merges_per_run=merges, gospa_parts=gospa_parts(scores),
                 gospa_per_run=[s.mean_gospa for s in scores], false_tracks_per_run=[s.false_tracks for s in scores])
        m.pop("series")
        out["rules"][rule] = m
        p = m["gospa_parts"]
        print(f"{rule}: GOSPA {m['gospa']:.1f} m (start-up {p['startup']['gospa']:.1f}, steady "
              f"{p['steady']['gospa']:.1f}), held {m['held']:.4f}, tracks {m['tracks']}, false {m['false_tracks']}, "
              f"missed/step {p['all']['n_missed']:.2f}, false/step {p['all']['n_false']:.2f}, "
              f"longest merge {max(max(v.values(), default=0) for v in merges)}, CPU {np.mean(cpu):.1f} s/run",
              flush=True)
    if args.json:
        with open(args.json, "w") as f:
            json.dump(out, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
