"""Bounded resources over a long run: ``zfusion run --scenario patent-3d-orbit --speed
max`` for a short and a long scenario duration, and the peak resident memory of the
fuser and the recorder from each run's summary (``processes.<id>.max_rss_mb``, the
kernel's high-water mark). The bound: the long run's peak within 15 % (+5 MB) of the
short run's, for both.

    python benchmarks/bench_soak.py [--short 600] [--long 7200] [--json PATH]
    python benchmarks/bench_soak.py --scoring 2 24
    python benchmarks/bench_soak.py --scoring-many 1 4

``--scoring H ...`` measures, in process and without Zenoh, what the launcher of a *live*
run holds to score it (``services.summary.RunScorer``: Python heap by ``tracemalloc``)
after H hours of one fused update a second, against a scenario run's, which keeps every
estimate: a live run of hours cannot be played faster than real time. ``--scoring-many
H ...`` does the same for a live many-target run (``air-picture-live``'s traffic, each
aircraft followed by a track of its own and a clutter track 3 s in 10, one step a second).

Each run is the command line a user types (printed), with ``--duration-s`` setting the
scenario's length (the scenario file's copy with ``duration_s`` replaced, where this
version of ``zfusion run`` has no ``--duration-s``).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import _common as C

SCENARIO = "patent-3d-orbit"
WATCHED = ("fuser", "recorder")


def has_duration_flag() -> bool:
    out = subprocess.run([sys.executable, "-m", "services.cli", "run", "--help"], capture_output=True, text=True,
                         cwd=C.REPO).stdout
    return "--duration-s" in out


def scenario_with(duration: float, tmp: Path) -> str:
    from sensors_sim.loader import _builtin_dir

    text = (_builtin_dir() / f"{SCENARIO}.toml").read_text()
    lines = [f"duration_s = {duration!r}" if line.startswith("duration_s") else line for line in text.splitlines()]
    path = tmp / f"{SCENARIO}.toml"
    path.write_text("\n".join(lines) + "\n")
    return str(path)


def one_run(duration: float, tmp: Path, flag: bool, speed: str, extra: list[str]) -> dict:
    js, rrd = tmp / f"soak-{duration:g}.json", tmp / f"soak-{duration:g}.rrd"
    scenario = ["--scenario", SCENARIO, "--duration-s", f"{duration:g}"] if flag else \
        ["--scenario", scenario_with(duration, tmp)]
    cmd = ["zfusion", "run", *scenario, "--speed", speed, "--json", str(js), "--rrd", str(rrd), *extra]
    print("$ " + " ".join(cmd), flush=True)
    t0 = time.monotonic()
    p = subprocess.run([sys.executable, "-m", "services.cli", *cmd[1:]], capture_output=True, text=True, cwd=C.REPO)
    wall = time.monotonic() - t0
    if p.returncode != 0:
        sys.exit(f"bench_soak: the {duration:g} s run failed (exit {p.returncode}):\n{p.stderr[-3000:]}")
    doc = json.loads(js.read_text())
    files = [Path(f) for f in doc["recordings"]]
    return {"duration_s": duration, "wall_s": wall, "processes": doc["processes"],
            "n_updates": sum(m["n_updates"] for m in doc["methods"].values()),
            "series_len": max(len(m["series"]["t"]) for m in doc["methods"].values()),
            "rrd_mb": sum(f.stat().st_size for f in files if f.exists()) / 2**20}


def scoring_memory(hours: list[float]) -> None:
    """Peak Python heap of the launcher's scorer fed ``h`` hours of 1 Hz estimates, live
    (settled as it goes, the default OOSM window and max delay) and kept (a scenario run)."""
    import dataclasses
    import tracemalloc

    from sensors_sim import load_scenario
    from services.evaluation import run_method
    from services.summary import RunScorer

    sc = dataclasses.replace(load_scenario(SCENARIO), duration=600.0)
    base = run_method(sc, "SS")  # 601 real estimates, repeated with their times shifted
    period = base[-1].t - base[0].t + 1.0
    epoch = 1.7e9
    rows = []
    for h in hours:
        n = int(h * 3600)
        row = [f"{h:g}", str(n)]
        for live in (True, False):
            tracemalloc.start()
            scorer = RunScorer(sc, epoch, 10.0 + 1.0 + 1.0) if live else RunScorer(sc)
            for k in range(n):
                e = base[k % len(base)]
                scorer.add(dataclasses.replace(e, t=e.t + (k // len(base)) * period + (epoch if live else 0.0)))
            doc = scorer.method_summary()
            peak = tracemalloc.get_traced_memory()[1]
            tracemalloc.stop()
            row.append(f"{peak / 2**20:.1f}")
            if live:
                row.append(str(len(doc["series"]["t"])))
        rows.append(row)
    print(C.table(["hours", "updates", "live: peak heap MB", "series points", "kept (scenario run): MB"], rows))


def scoring_memory_many(hours: list[float]) -> None:
    """Peak Python heap of a live many-target run's scorer after ``h`` hours of a
    synthetic air picture (a perfect track per aircraft, a clutter track 3 s in 10)."""
    import dataclasses
    import tracemalloc

    import numpy as np

    from fusion.types import Estimate
    from sensors_sim import load_scenario
    from sensors_sim.traffic import Traffic
    from services.summary import RunScorer

    sc = load_scenario("air-picture-live")
    epoch, P = 1.7e9, np.eye(9)
    rows = []
    for h in hours:
        n = int(h * 3600)
        traffic = Traffic(sc.traffic, sc.seed, 0)
        tracemalloc.start()
        t0 = time.process_time()
        scorer = RunScorer(sc, epoch, 10.0 + 1.0 + 1.0)
        for k in range(n):
            t = float(k)
            for a in traffic.alive(t):
                scorer.add(Estimate(t=epoch + t, x=np.concatenate([a.position(t), np.zeros(6)]), P=P,
                                    method="SS", track=f"T{a.id}"))
            if k % 10 < 3:
                scorer.add(Estimate(t=epoch + t, x=np.zeros(9), P=P, method="SS", track=f"G{k // 10}"))
        doc = scorer.method_summary(dataclasses.replace(sc, duration=scorer.played()))
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
        rows.append([f"{h:g}", str(scorer.n), str(doc["tracks"]), f"{peak / 2**20:.1f}", str(len(doc["series"]["t"])),
                     f"{time.process_time() - t0:.0f}"])
    print(C.table(["hours", "estimates", "tracks", "live: peak heap MB", "series points", "CPU s"], rows))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--short", type=float, default=600.0, help="scenario seconds of the reference run")
    ap.add_argument("--long", type=float, default=7200.0, help="scenario seconds of the soak run")
    ap.add_argument("--speed", default="max", help="zfusion run --speed (default max)")
    ap.add_argument("--rotate-s", type=float, help="also rotate the recording every N scenario seconds")
    ap.add_argument("--scoring", type=float, nargs="+", metavar="H",
                    help="only measure the launcher's scoring memory after H hours (in process)")
    ap.add_argument("--scoring-many", type=float, nargs="+", metavar="H",
                    help="only measure a live many-target run's scoring memory after H hours (in process)")
    ap.add_argument("--json")
    args = ap.parse_args()
    if args.scoring_many:
        print(f"# Launcher scoring memory, air-picture-live, 1 step/s — {C.machine_line()}\n")
        scoring_memory_many(args.scoring_many)
        return
    if args.scoring:
        print(f"# Launcher scoring memory, {SCENARIO}, 1 Hz — {C.machine_line()}\n")
        scoring_memory(args.scoring)
        return
    print(f"# Soak: {SCENARIO} at --speed {args.speed}, {args.short:g} s vs {args.long:g} s — {C.machine_line()}\n")
    flag = has_duration_flag()
    extra = ["--rotate-s", f"{args.rotate_s:g}"] if args.rotate_s else []
    with tempfile.TemporaryDirectory() as d:
        runs = [one_run(dur, Path(d), flag, args.speed, extra) for dur in (args.short, args.long)]
    short, long_ = runs
    rows, verdict = [], {}
    for name in [*WATCHED, *sorted(set(long_["processes"]) - set(WATCHED))]:
        a, b = short["processes"].get(name), long_["processes"].get(name)
        if not a or not b:
            continue
        bound = 1.15 * a["max_rss_mb"] + 5.0
        ok = b["max_rss_mb"] <= bound
        if name in WATCHED:
            verdict[name] = {"short_mb": a["max_rss_mb"], "long_mb": b["max_rss_mb"], "bound_mb": bound, "met": ok}
        rows.append([name, f"{a['max_rss_mb']:.1f}", f"{b['max_rss_mb']:.1f}",
                     f"{bound:.1f}" if name in WATCHED else "", ("met" if ok else "NOT MET") if name in WATCHED else "",
                     f"{a['cpu_s']:.1f}", f"{b['cpu_s']:.1f}"])
    print()
    print(C.table(["process", f"peak RSS MB, {args.short:g} s", f"peak RSS MB, {args.long:g} s", "bound MB", "",
                   f"CPU s, {args.short:g} s", f"CPU s, {args.long:g} s"], rows))
    for r in runs:
        print(f"\n{r['duration_s']:g} s: {r['wall_s']:.0f} s wall, {r['n_updates']} fused updates, summary series "
              f"{r['series_len']} points, recording {r['rrd_mb']:.1f} MB")
    if args.json:
        Path(args.json).write_text(json.dumps({"machine": C.machine_line(), "runs": runs, "verdict": verdict},
                                              indent=1))
    if not all(v["met"] for v in verdict.values()):
        sys.exit(1)


if __name__ == "__main__":
    main()
