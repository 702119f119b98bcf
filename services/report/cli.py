"""The command line: ``python -m services.report NAME [--runs N] [--jobs J] [--out DIR]``
(or ``--render-only`` from the JSON already in ``--out``).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Callable

from tqdm import tqdm

from ..evaluation import default_jobs
from .dense import DENSE, build_dense, write_dense_report
from .maneuver import MANEUVER, build_maneuver, write_maneuver_report
from .many import MANY, build_many, write_many_report
from .moving import build_moving, write_moving_report
from .patent import build_patent, write_patent_report
from .sweep import build_sweep, write_sweep_report
from .thesis import build_thesis, write_thesis_report

DEFAULT_RUNS = {"patent-3d": 100, "patent-3d-60": 100, "thesis-cep": 100, "jammed-df-sweep": 40,
                "air-picture": 50, "df-multi": 50, "df-moving": 50, "patent-3d-maneuver": 50,
                DENSE: 50}
REPORT_NAMES = tuple(DEFAULT_RUNS)


def bundle_kind(name: str) -> str:
    return "patent" if name in ("patent-3d", "patent-3d-60") else "many" if name in MANY else name


RENDER = {"patent": write_patent_report, "thesis-cep": write_thesis_report, "jammed-df-sweep": write_sweep_report,
          "many": write_many_report, "df-moving": write_moving_report, MANEUVER: write_maneuver_report,
          DENSE: write_dense_report}


def make_report(name: str, out_dir: Path, runs: int | None = None, jobs: int = 1,
                progress: Callable[[int, int], None] | None = None, duration_s: float | None = None) -> Path:
    runs = runs or DEFAULT_RUNS[name]
    if duration_s is not None and name != DENSE:
        raise ValueError(f"--duration-s shortens only the {DENSE} report")
    if name == DENSE:
        return write_dense_report(build_dense(runs, jobs, progress, duration_s), out_dir)
    if name in ("patent-3d", "patent-3d-60"):
        return write_patent_report(build_patent(name, runs, jobs, progress), out_dir)
    if name == "thesis-cep":
        return write_thesis_report(build_thesis(runs, jobs, progress), out_dir)
    if name == "jammed-df-sweep":
        return write_sweep_report(build_sweep(runs, jobs, progress), out_dir)
    if name in MANY:
        return write_many_report(build_many(name, runs, jobs, progress), out_dir)
    if name == "df-moving":
        return write_moving_report(build_moving(runs, jobs, progress), out_dir)
    if name == MANEUVER:
        return write_maneuver_report(build_maneuver(runs, jobs, progress), out_dir)
    raise ValueError(f"unknown report {name!r}; known: {', '.join(REPORT_NAMES)}")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m services.report",
                                 description="Regenerate the reproduction reports in docs/results/.")
    ap.add_argument("names", nargs="+", choices=(*REPORT_NAMES, "all"))
    ap.add_argument("--out", default="docs/results", help="output directory (default: %(default)s)")
    ap.add_argument("--runs", type=int, help="Monte Carlo runs (default: per report, " +
                    ", ".join(f"{k} {v}" for k, v in DEFAULT_RUNS.items()) + ")")
    ap.add_argument("--jobs", type=int, default=min(2, default_jobs()),
                    help="worker processes (default: 2, or 1 on a single core); results do not depend on it")
    ap.add_argument("--duration-s", type=float,
                    help=f"{DENSE} only: shorten every run to this many seconds (a first look; the report says so)")
    ap.add_argument("--render-only", action="store_true",
                    help="rewrite the Markdown and plots from the existing NAME.json in --out (no evaluation)")
    args = ap.parse_args(argv)
    names = REPORT_NAMES if "all" in args.names else args.names
    if args.render_only:
        for name in names:
            bundle = json.loads((Path(args.out) / f"{name}.json").read_text())
            print(f"{name}: {RENDER[bundle_kind(name)](bundle, Path(args.out))}")
        return 0

    for name in names:
        with tqdm(total=args.runs, desc=f"  {name}: run", file=sys.stderr, disable=not sys.stderr.isatty(),
                  ascii=" #", bar_format="{desc} {n}/{total} [{bar:30}] {remaining} left") as bar:
            path = make_report(name, Path(args.out), args.runs, args.jobs,
                               lambda done, total: bar.update(done - bar.n), args.duration_s)
        print(f"{name}: {path}")
    return 0
