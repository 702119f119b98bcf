"""Bounded resources over a long run: ``zfusion run --scenario patent-3d-orbit --speed
max`` for a short and a long scenario duration, and the peak resident memory of the
fuser and the recorder from each run's summary (``processes.<id>.max_rss_mb``, the
kernel's high-water mark). The bound: the long run's peak within 15 % (+5 MB) of the
short run's, for both.

    python benchmarks/bench_soak.py [--short 600] [--long 7200] [--json PATH]

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


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--short", type=float, default=600.0, help="scenario seconds of the reference run")
    ap.add_argument("--long", type=float, default=7200.0, help="scenario seconds of the soak run")
    ap.add_argument("--speed", default="max", help="zfusion run --speed (default max)")
    ap.add_argument("--rotate-s", type=float, help="also rotate the recording every N scenario seconds")
    ap.add_argument("--json")
    args = ap.parse_args()
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
