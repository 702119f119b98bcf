"""``zfusion eval``: Monte Carlo evaluation in-process (:mod:`services.evaluation`), the
result table, and optionally the summary JSON and a Markdown report."""

from __future__ import annotations

import argparse
import json
import os
import sys
import tomllib
from pathlib import Path

from fusion.lazy import lazy
from fusion.topology import METHOD_TOPOLOGIES

from ..errors import UserError
from . import names, options

evaluation = lazy("services.evaluation")
methods_registry = lazy("fusion.methods")
report = lazy("services.report")
request = lazy("services.request")
summary = lazy("services.summary")
tqdm = lazy("tqdm")


def register(sub) -> None:
    p = sub.add_parser("eval", help="Monte Carlo evaluation in-process, with the services' own estimators")
    options.scenario(p)
    p.add_argument("--runs", type=int, required=True, help="number of Monte Carlo runs")
    p.add_argument("--methods", nargs="+",
                   help="methods to evaluate (default: every method the scenario's sensors can feed)")
    options.fusion_rule(p, "track-to-track fusion rule of the track-fusion methods")
    p.add_argument("--topology", choices=("regional",),
                   help="regional: each method as regional fusers over the scenario's [regions] under a system "
                        "fuser (docs/regional.md); default: each method's own topology")
    options.seed_option(p)
    p.add_argument("--json", help="write the summary JSON here")
    p.add_argument("--report", metavar="DIR", help="write a Markdown report with PNG plots into DIR")
    p.add_argument("--jobs", type=int, default=1, help="worker processes for the Monte Carlo runs (default 1)")
    options.tracker_options(p)
    p.add_argument("--progress", action=argparse.BooleanOptionalAction, default=None,
                   help="progress line on stderr (default: when stderr is a terminal)")
    options.verbose(p, tracebacks=True)
    p.set_defaults(main=run)


def run(args) -> int:
    if args.runs < 1:
        raise UserError("--runs must be >= 1")
    if args.jobs < 1:
        raise UserError("--jobs must be >= 1")
    names.check_scenario(args.scenario)
    names.check_methods(args.methods)
    names.check_settings(args.settings)
    if args.topology == "regional":
        check_regional(args.scenario, args.methods)
    if args.json:  # the outputs checked before the Monte Carlo, not after it
        options.writable_file(args.json, "--json")
    if args.report:
        options.writable_dir(Path(args.report), "--report")
        try:
            import matplotlib  # noqa: F401  (an optional dependency: only --report needs it)
        except ImportError:
            raise UserError("--report draws its plots with matplotlib, which is not installed: "
                            "pip install 'zfusion[report]', or leave out --report") from None
    scenario = request.scenario_of(args)
    methods = args.methods or evaluation.default_methods(scenario)
    if not methods:
        raise UserError(f"no method can use the sensors of scenario {scenario.name}")
    fusing = methods_registry.TRACK_FUSION_METHODS
    if args.fusion_rule and not set(methods) & set(fusing):
        raise UserError(f"--fusion-rule applies to the track-fusion methods ({', '.join(fusing)}); "
                        f"none of {', '.join(methods)} fuses tracks")
    overrides = options.overrides(args)
    request.check_methods(scenario, methods, overrides)
    show = sys.stderr.isatty() if args.progress is None else args.progress
    rule = args.fusion_rule or methods_registry.track_fusion_rule(scenario.tracker, methods)

    # Shown at once (before the first run ends), with the time left from the runs so far.
    bar = tqdm.tqdm(total=args.runs, desc=f"{scenario.name}: run", file=sys.stderr, disable=not show, ascii=" #",
                    bar_format="{desc} {n}/{total} [{bar:30}] {elapsed} spent, {remaining} left", mininterval=0.0)
    bar.refresh()
    try:
        doc = evaluation.evaluate(scenario, evaluation.variants_for(methods, overrides, args.topology), args.runs,
                                  jobs=args.jobs,
                                  progress=(lambda done, total: bar.update(done - bar.n)) if show else None,
                                  fusion_rule=rule, topology=args.topology or "in-process")
    except ValueError as exc:
        raise UserError(str(exc)) from None
    finally:
        bar.close()
    print(summary.format_table(doc))
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(doc, indent=1))
    if args.report:
        command = f"zfusion eval --scenario {args.scenario} --runs {args.runs}"
        command += f" --methods {' '.join(args.methods)}" if args.methods else ""
        command += f" --fusion-rule {args.fusion_rule}" if args.fusion_rule else ""
        command += f" --topology {args.topology}" if args.topology else ""
        command += f" --seed {args.seed}" if args.seed is not None else ""
        command += f" --duration-s {args.duration_s:g}" if args.duration_s else ""
        command += "".join(f" --set {k}={v!r}" for k, v in args.settings)
        path = report.write_eval_report(doc, Path(args.report), command=command)
        print(f"report: {path}")
    return 0


def check_regional(ref: str, methods: list[str] | None) -> None:
    """``--topology regional`` needs ``[regions]`` in the scenario and centralised methods
    named (a regional fuser is a centralised many-target tracker): read from the file
    itself, before the heavy imports (its validity is the loader's to check)."""
    try:
        path = Path(ref) if os.path.isfile(ref) else Path(names.builtin_dir()) / f"{ref}.toml"
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except (OSError, tomllib.TOMLDecodeError):
        return  # the loader says what is wrong with it
    if not data.get("regions"):
        raise UserError(f"--topology regional needs [regions.<name>] tables in the scenario (sensors_sim/README.md, "
                        f"\"Regions\"); {ref} has none")
    if not methods:
        raise UserError("--topology regional: name the centralised methods to run (--methods SS ...)")
    split = [m for m in methods if METHOD_TOPOLOGIES[m] != "centralised"]
    if split:
        raise UserError(f"--topology regional runs centralised methods as regional fusers; {', '.join(split)} "
                        f"{'is' if len(split) == 1 else 'are'} {METHOD_TOPOLOGIES[split[0]]}")
