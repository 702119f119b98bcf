"""The ``air-picture-dense`` report: SS with ``association = "jipda"`` against the same
with ``"gnn"`` on the same plots (common random numbers), and ``air-picture`` likewise,
with the acceptance verdicts of JIPDA computed from the numbers.

Per run and association: the many-target scores (:func:`fusion.mtt_metrics.score_tracks`),
the CPU seconds of the tracker alone (``time.process_time`` around the method's run),
and the longest *formation merge* of each pair (:func:`formation_merges`).
"""

from __future__ import annotations

import dataclasses
import multiprocessing
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path

import numpy as np

from fusion.mtt_metrics import score_tracks
from sensors_sim import load_scenario

from ..evaluation import GOSPA_CUTOFF, merged_measurements, run_method
from ..scoring import track_steps
from ..summary import summary, tracks_summary
from .figures import plot_series
from .tables import fmt, md_table, write_report

DENSE = "air-picture-dense"
METHOD = "SS"
ASSOCIATIONS = ("gnn", "jipda")
#: the acceptance of JIPDA: GOSPA at most this times GNN's on the dense picture, no more
#: false tracks, no pair merged longer than MAX_MERGE steps, air-picture no worse
CRITERIA = {"gospa_factor": 0.8, "max_merge": 3, "air_picture_factor": 1.0}
MERGE_RADIUS = 500.0  # m: a track this close to an aircraft is on it (the pairs fly 500 m apart)
MERGE_GRACE = 5  # steps after a pair is first held before a merge counts (3-of-4 confirmation, plus one)
STARTUP_S = 10.0  # s: the start-up of a run (every aircraft flies from t = 0; a track needs ~4 scans)


def formation_pairs(scenario) -> list[tuple[str, str]]:
    """The formation pairs: each target ``XW`` (a wingman) with its leader ``X``."""
    return [(t[:-1], t) for t in scenario.targets if t.endswith("W") and t[:-1] in scenario.targets]


def formation_merges(steps, pairs, radius: float = MERGE_RADIUS, grace: int = MERGE_GRACE) -> dict[str, int]:
    """Per pair ``"X/XW"``: the most consecutive steps in which both aircraft fly and the
    tracks within ``radius`` of either are exactly one — one track holding two aircraft.
    Counted from ``grace`` steps after the first step with any track near the pair (a
    second track needs its confirmation first)."""
    out = {}
    for a, b in pairs:
        first, run, longest = None, 0, 0
        for k, st in enumerate(steps):
            if a not in st.truths or b not in st.truths:
                run = 0
                continue
            near = {tid for tid, x in st.tracks.items()
                    if min(np.linalg.norm(x[:3] - st.truths[a][:3]), np.linalg.norm(x[:3] - st.truths[b][:3])) <= radius}
            if near and first is None:
                first = k
            merged = len(near) == 1 and first is not None and k >= first + grace
            run = run + 1 if merged else 0
            longest = max(longest, run)
        out[f"{a}/{b}"] = longest
    return out


def gospa_parts(scores, c: float = GOSPA_CUTOFF, startup_s: float = STARTUP_S) -> dict:
    """GOSPA (p = 2) of a method's runs split into its parts, over the whole run and over
    its start-up (``t < startup_s``) and steady state: per step
    ``d² = loc + c²/2 · n_missed + c²/2 · n_false`` (``loc``: the assigned pairs' ``Σ‖x − y‖²``).

    Per window: ``gospa`` the mean per-step GOSPA; ``loc``, ``missed``, ``false`` the
    mean of each part of ``d²`` (m²), whose sum is the mean ``d²``; ``n_missed``,
    ``n_false`` the mean counts per step; ``gospa_no_false`` the mean GOSPA with the false
    part taken out of every step (what the false tracks cost: ``gospa − gospa_no_false``).
    ``scores``: :class:`fusion.mtt_metrics.TrackScore` s with one series point per step."""
    half = c**2 / 2.0
    t = np.concatenate([np.asarray(s.t, dtype=float) for s in scores])
    g2 = np.concatenate([np.asarray(s.gospa, dtype=float) for s in scores]) ** 2
    missed = np.concatenate([np.asarray(s.n_missed, dtype=float) for s in scores])
    false = np.concatenate([np.asarray(s.n_false, dtype=float) for s in scores])
    loc = np.maximum(g2 - half * (missed + false), 0.0)
    out = {"startup_s": startup_s}
    for name, keep in (("all", np.ones_like(t, dtype=bool)), ("startup", t < startup_s), ("steady", t >= startup_s)):
        if not keep.any():
            continue
        out[name] = {"steps": int(keep.sum()), "gospa": float(np.mean(np.sqrt(g2[keep]))),
                     "loc": float(np.mean(loc[keep])), "missed": float(np.mean(half * missed[keep])),
                     "false": float(np.mean(half * false[keep])), "n_missed": float(np.mean(missed[keep])),
                     "n_false": float(np.mean(false[keep])),
                     "gospa_no_false": float(np.mean(np.sqrt(loc[keep] + half * missed[keep])))}
    return out


def _one_run(scenario, r: int) -> dict:
    """Run ``r`` with each association on the same plots: its score, the tracker's CPU
    seconds and the formation merges, per association."""
    pairs = formation_pairs(scenario)
    plots = merged_measurements(scenario, r)
    out = {}
    for a in ASSOCIATIONS:
        t0 = time.process_time()
        estimates = run_method(scenario, METHOD, {"association": a}, r, plots)
        cpu = time.process_time() - t0
        steps = track_steps(scenario, estimates, r)
        out[a] = (score_tracks(steps, GOSPA_CUTOFF), cpu, formation_merges(steps, pairs))
    return out


def _runs(scenario, runs: int, jobs: int = 1, progress=None) -> dict:
    """Per association: the scores, CPU seconds and merges of runs ``0..runs-1``
    (``jobs`` processes, one run a task; the result does not depend on ``jobs``)."""
    jobs = max(1, min(int(jobs), runs))
    per_run: dict[int, dict] = {}
    if jobs == 1:
        for r in range(runs):
            per_run[r] = _one_run(scenario, r)
            if progress:
                progress(r + 1, runs)
    else:
        ctx = multiprocessing.get_context("fork" if "fork" in multiprocessing.get_all_start_methods() else "spawn")
        with ProcessPoolExecutor(jobs, mp_context=ctx) as pool:
            futures = {pool.submit(_one_run, scenario, r): r for r in range(runs)}
            for fut in as_completed(futures):
                per_run[futures[fut]] = fut.result()
                if progress:
                    progress(len(per_run), runs)
    methods = {}
    for a in ASSOCIATIONS:
        scores, cpu, merges = zip(*(per_run[r][a] for r in range(runs)))
        m = tracks_summary(scores)
        m.update(variant={"method": METHOD, "overrides": {"association": a}}, cpu_s_per_run=list(cpu),
                 merges_per_run=list(merges), gospa_per_run=[s.mean_gospa for s in scores],
                 false_tracks_per_run=[s.false_tracks for s in scores], gospa_parts=gospa_parts(scores))
        methods[f"{METHOD}-{a}"] = m
    return summary(scenario, "in-process", None, scenario.seed, runs, methods) | {"gospa_cutoff": GOSPA_CUTOFF}


def build_dense(runs: int, jobs: int = 1, progress=None, duration_s: float | None = None) -> dict:
    """Both scenarios, ``runs`` runs each (``duration_s``: shortened, for a first look),
    in ``jobs`` processes."""
    docs = {}
    for name in (DENSE, "air-picture"):
        sc = load_scenario(name)
        if duration_s is not None:
            sc = dataclasses.replace(sc, duration=float(duration_s))
        docs[name] = _runs(sc, runs, jobs, progress if name == DENSE else None)  # air-picture's runs take seconds
    command = f"python -m services.report {DENSE} --runs {runs}" + (f" --duration-s {duration_s:g}" if duration_s else "")
    return {"report": DENSE, "runs": runs, "duration_s": duration_s, "command": command, "criteria": CRITERIA,
            "evaluation": docs}


def dense_verdicts(bundle: dict) -> list[str]:
    """One line per criterion, computed from the numbers."""
    spec, runs = bundle["criteria"], bundle["runs"]
    dense, air = (bundle["evaluation"][n]["methods"] for n in (DENSE, "air-picture"))
    g, j = dense[f"{METHOD}-gnn"], dense[f"{METHOD}-jipda"]
    r = j["gospa"] / g["gospa"]
    worst = max((max(m.values(), default=0) for m in j["merges_per_run"]), default=0)
    ra = air[f"{METHOD}-jipda"]["gospa"] / air[f"{METHOD}-gnn"]["gospa"]
    cpu = np.mean(j["cpu_s_per_run"]) / np.mean(g["cpu_s_per_run"])
    checks = [
        (r <= spec["gospa_factor"], f"`{DENSE}`: mean GOSPA with jipda {j['gospa']:.1f} m, {r:.3f}× gnn's "
                                    f"{g['gospa']:.1f} m (limit {spec['gospa_factor']:g}×)"),
        (j["false_tracks"] <= g["false_tracks"], f"`{DENSE}`: false tracks {j['false_tracks']} with jipda, "
                                                 f"{g['false_tracks']} with gnn (no more allowed)"),
        (worst <= spec["max_merge"], f"`{DENSE}`: longest formation merge with jipda {worst} steps over {runs} runs "
                                     f"(limit {spec['max_merge']}; gnn's "
                                     f"{max((max(m.values(), default=0) for m in g['merges_per_run']), default=0)})"),
        (ra <= spec["air_picture_factor"], f"`air-picture`: mean GOSPA with jipda {ra:.3f}× gnn's "
                                           f"(limit {spec['air_picture_factor']:g}×)"),
    ]
    out = [f"* **{'meets' if ok else 'misses'}** — {text}." for ok, text in checks]
    out.append(f"* (not a criterion) CPU per run of the tracker: jipda {np.mean(j['cpu_s_per_run']):.1f} s, "
               f"{cpu:.2f}× gnn's {np.mean(g['cpu_s_per_run']):.1f} s.")
    return out


def _parts_rows(bundle: dict) -> list[list[str]]:
    rows = []
    for name, doc in bundle["evaluation"].items():
        for v in doc["methods"].values():
            parts = v.get("gospa_parts", {})
            for window in ("all", "startup", "steady"):
                if window in parts:
                    w = parts[window]
                    rows.append([f"`{name}`", f"`{v['variant']['overrides']['association']}`", window,
                                 fmt(w["gospa"], 1), fmt(w["loc"] / 1e6, 3), fmt(w["missed"] / 1e6, 3),
                                 fmt(w["false"] / 1e6, 3), fmt(w["n_missed"], 2), fmt(w["n_false"], 2),
                                 fmt(w["gospa_no_false"], 1)])
    return rows


def write_dense_report(bundle: dict, out_dir: Path) -> Path:
    out_dir = Path(out_dir)
    runs = bundle["runs"]
    headers = ["scenario", "association", "GOSPA (m)", "held", "breaks", "purity", "tracks", "false", "ghost",
               "all found", "longest merge", "CPU s/run"]
    rows = []
    for name, doc in bundle["evaluation"].items():
        for label, v in doc["methods"].items():
            rows.append([f"`{name}`", f"`{v['variant']['overrides']['association']}`", fmt(v["gospa"], 1),
                         fmt(v["held"], 4), str(v["breaks"]), fmt(v["purity"], 4), str(v["tracks"]),
                         str(v["false_tracks"]), str(v["longest_ghost"]), f"{v['all_found_runs']}/{runs}",
                         str(max((max(m.values(), default=0) for m in v["merges_per_run"]), default=0)),
                         fmt(float(np.mean(v["cpu_s_per_run"])), 1)])
    doc = bundle["evaluation"][DENSE]
    curves = {label: (v["series"]["t"], v["series"]["gospa"]) for label, v in doc["methods"].items()}
    png = plot_series(curves, out_dir / DENSE / "gospa.png", "mean GOSPA (m)",
                      f"{DENSE}: GOSPA against time ({runs} runs)", logy=True)
    short = f", each shortened to {bundle['duration_s']:g} s" if bundle.get("duration_s") else ""
    text = [
        f"# Dense clutter: `{DENSE}`, JIPDA against GNN over {runs} Monte Carlo runs{short}",
        "",
        f"Regenerate: `{bundle['command']}` (writes `{DENSE}.md`, `{DENSE}.json`, `{DENSE}/gospa.png`). "
        f"Method {METHOD}, `[tracker]` of each scenario file with `association` set; both associations run on "
        f"the same plots in every run. Every number below is read from `{DENSE}.json`.",
        "",
        "Columns as in [air-picture.md](air-picture.md); *longest merge*: the most consecutive steps in which one "
        f"track alone lay within {MERGE_RADIUS:g} m of the two aircraft of a formation pair (any pair, any run), "
        f"counted from {MERGE_GRACE} steps after the pair was first held; *CPU s/run*: the tracker's process time "
        "per run (the plots' simulation and the scoring excluded).",
        "",
        md_table(headers, rows),
        "",
        "## Where the GOSPA comes from",
        "",
        f"Each step's squared GOSPA is the assigned pairs' squared distances (*loc*) plus c²/2 for each "
        f"missed aircraft and each false track (c = {GOSPA_CUTOFF:g} m); the columns are their means over the "
        f"steps, in km² (they add up to the mean squared GOSPA), the mean missed and false counts a step, and "
        f"the mean GOSPA with every false track taken out. *Start-up*: t < {STARTUP_S:g} s.",
        "",
        md_table(["scenario", "association", "window", "GOSPA (m)", "loc (km²)", "missed (km²)", "false (km²)",
                  "missed/step", "false/step", "GOSPA without false (m)"], _parts_rows(bundle)),
        "",
        "## Against the acceptance criteria",
        "",
        *dense_verdicts(bundle),
        "",
        "The comparisons with the true-association reference (`benchmarks/oracle_dense.py`: each aircraft's own "
        "plots through its own tracker) and with the Stone Soup JPDA tracker (`benchmarks/stonesoup_jpda.py`) are "
        "not part of this command; see docs/algorithms.md, \"JIPDA: association with track existence\".",
        "",
        "## GOSPA against time",
        "",
        f"![GOSPA against time]({DENSE}/{png})",
        "",
    ]
    return write_report(out_dir, DENSE, bundle, text)
