"""The many-target reports (``air-picture``, ``df-multi``): GOSPA, track holding and breaks
per method on a picture of several targets.
"""

from __future__ import annotations

from pathlib import Path

from sensors_sim import load_scenario

from ..evaluation import default_methods, evaluate, variants_for
from .figures import plot_series
from .tables import fmt, md_table, ratio, write_report

#: per report: the methods (one per topology; DF: every method), the reference of the
#: GOSPA ratio, and the criteria (None: not part of that scenario's acceptance)
MANY = {
    "air-picture": {"methods": ("SS", "HNV", "PHHNV", "DDHNV"), "reference": "SS",
                    "gospa_factor": 1.2, "max_break_rate": 0.01, "max_ghost": None},
    "df-multi": {"methods": None, "reference": None, "gospa_factor": None, "max_break_rate": None,
                 "max_ghost": 10},
}


def build_many(name: str, runs: int, jobs: int = 1, progress=None) -> dict:
    sc = load_scenario(name)
    spec = MANY[name]
    methods = list(spec["methods"] or default_methods(sc))
    doc = evaluate(sc, variants_for(methods), runs, jobs=jobs, progress=progress)
    return {"report": name, "runs": runs, "command": f"python -m services.report {name} --runs {runs}",
            "criteria": spec, "evaluation": doc}


def many_verdicts(bundle: dict) -> list[str]:
    """One sentence per (method, criterion), computed from the numbers."""
    spec, doc, runs = bundle["criteria"], bundle["evaluation"], bundle["runs"]
    methods = doc["methods"]
    ref = methods.get(spec["reference"]) if spec["reference"] else None
    out = []
    for name, m in methods.items():
        checks = []
        found = m["all_found_runs"] == runs
        checks.append((found, f"every target held at the end of {m['all_found_runs']} of {runs} runs"))
        if spec["max_break_rate"] is not None:
            checks.append((m["break_rate"] <= spec["max_break_rate"],
                           f"break rate {100 * m['break_rate']:.3f} % (limit {100 * spec['max_break_rate']:g} %)"))
        if spec["gospa_factor"] is not None and ref is not None:
            r = m["gospa"] / ref["gospa"]
            checks.append((r <= spec["gospa_factor"], f"mean GOSPA {m['gospa']:.1f} m, {r:.3f}× {spec['reference']}'s "
                                                      f"(limit {spec['gospa_factor']:g}×)"))
        if spec["max_ghost"] is not None:
            per_run = m["longest_ghost_per_run"]
            bad = [r for r, g in enumerate(per_run) if g > spec["max_ghost"]]
            checks.append((not bad, f"no ghost longer than {spec['max_ghost']} epochs in {runs - len(bad)} of {runs} "
                                    f"runs (longest {m['longest_ghost']}"
                                    + (f"; {_runs_list(bad)}" if bad else "") + ")"))
        lost = [r for r, f in enumerate(m["found_at_end_per_run"]) if f < 1.0]
        if lost:
            checks[0] = (False, checks[0][1] + f" (not in {_runs_list(lost)})")
        ok = all(c for c, _ in checks)
        out.append(f"* **{name}: {'meets' if ok else 'misses'}** — " + "; ".join(
            f"{text}{'' if c else ' ✗'}" for c, text in checks) + ".")
    return out


def _runs_list(runs: list[int], most: int = 8) -> str:
    return "runs " + ", ".join(map(str, runs[:most])) + (f" and {len(runs) - most} more" if len(runs) > most else "")


def write_many_report(bundle: dict, out_dir: Path) -> Path:
    out_dir = Path(out_dir)
    name, runs, doc, spec = bundle["report"], bundle["runs"], bundle["evaluation"], bundle["criteria"]
    methods = doc["methods"]
    ref = methods.get(spec["reference"]) if spec["reference"] else None
    rows = [[f"`{m}`", fmt(v["gospa"], 1), fmt(ratio(v["gospa"], ref["gospa"]) if ref else None, 3),
             fmt(v["held"], 4), fmt(v["worst_hold"], 3), str(v["breaks"]), f"{100 * v['break_rate']:.3f}",
             fmt(v["purity"], 4), str(v["tracks"]), str(v["false_tracks"]), str(v["longest_ghost"]),
             f"{v['all_found_runs']}/{runs}"] for m, v in methods.items()]
    headers = ["method", "GOSPA (m)", f"/ {spec['reference']}" if ref else "ratio", "held", "min hold", "breaks",
               "break %", "purity", "tracks", "false", "ghost", "all found"]
    curves = {m: (v["series"]["t"], v["series"]["gospa"]) for m, v in methods.items()}
    png = plot_series(curves, out_dir / name / "gospa.png", "mean GOSPA (m)",
                      f"{name}: GOSPA against time ({runs} runs)", logy=True)
    text = [
        f"# Many targets: `{name}` over {runs} Monte Carlo runs",
        "",
        f"Regenerate: `{bundle['command']}` (writes `{name}.md`, `{name}.json`, `{name}/gospa.png`); "
        f"scenario `sensors_sim/scenarios/{name}.toml`, seed {doc['seed']}. Every number below is read from "
        f"`{name}.json`, written by the code `zfusion eval` runs.",
        "",
        "Columns (`fusion/mtt_metrics.py`): GOSPA (p = 2, cut-off c = "
        f"{doc.get('gospa_cutoff', 1000.0):g} m, mean over steps and runs); *held*: truth-steps with a track "
        "within c; *min hold*: the least, over targets and runs, of the fraction of steps a target was held "
        "from the first step it was; *breaks*: a target's track changes or is lost between two steps "
        "(*break %*: of the chances); *purity*: track-steps on the track's main target; *false*: tracks on no "
        "target all their life; *ghost*: the most consecutive steps one track spent on no target (any run); "
        "*all found*: runs whose last step held every target.",
        "",
        md_table(headers, rows),
        "",
        "## Against the acceptance criteria",
        "",
        *many_verdicts(bundle),
        "",
        "## GOSPA against time",
        "",
        f"![GOSPA against time]({name}/{png})",
        "",
    ]
    return write_report(out_dir, name, bundle, text)
