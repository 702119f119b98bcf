"""Score estimates against truth and build the ``--json`` summary of DESIGN.md.

Shared by ``zfusion run`` (one run, estimates received over Zenoh) and ``zfusion eval``
(many in-process Monte Carlo runs), so both report the same numbers the same way.
"""

from __future__ import annotations

import math
from collections import defaultdict
from typing import Callable, Sequence

import numpy as np

from fusion.types import Estimate

TruthFn = Callable[[int, str, float], np.ndarray]  # (run, track, t) -> true state


def truth_function(scenario) -> TruthFn:
    """Truth of the scenario's targets, evaluated from the scenario itself (the scorer may
    see truth; trackers and fusers never do)."""
    from sensors_sim import truth_trajectory

    cache: dict[tuple[int, str], object] = {}
    targets = list(scenario.targets)

    def truth(run: int, track: str, t: float) -> np.ndarray:
        target = track if track in scenario.targets else (targets[0] if len(targets) == 1 else None)
        if target is None:
            raise KeyError(f"track {track!r} matches no target of {scenario.name}")
        traj = cache.get((run, target))
        if traj is None:
            traj = cache[(run, target)] = truth_trajectory(scenario, target, run=run)
        return np.asarray(traj.state(t), dtype=float)

    return truth


def _errors(e: Estimate, xt: np.ndarray) -> dict[str, float | None]:
    n = e.x.size
    xt = np.asarray(xt, dtype=float)[:n] if xt.size >= n else np.pad(xt, (0, n - xt.size))
    err = e.x - xt
    d = 3 if n >= 6 else n  # position block: 3D track or 2D emitter fix
    out: dict[str, float | None] = {"pos2": float(err[:d] @ err[:d]), "vel2": None, "acc2": None}
    if n >= 6:
        out["vel2"] = float(err[3:6] @ err[3:6])
    if n >= 9:
        out["acc2"] = float(err[6:9] @ err[6:9])
    try:
        out["nees"] = float(err @ np.linalg.solve(e.P, err))
    except np.linalg.LinAlgError:
        out["nees"] = math.nan
    out["horiz"] = float(np.hypot(err[0], err[1]))
    return out


def _rms(values: Sequence[float | None]) -> float | None:
    vals = [v for v in values if v is not None]
    return float(math.sqrt(sum(vals) / len(vals))) if vals else None


def method_summary(runs: Sequence[Sequence[Estimate]], truth: TruthFn, node: str = "centre") -> dict:
    """Metrics of one method over Monte Carlo runs (each a list of its fused estimates)."""
    per_t: dict[float, list[dict]] = defaultdict(list)
    all_err: list[dict] = []
    finals: list[dict] = []
    is_fix = False
    for r, estimates in enumerate(runs):
        mine = [e for e in estimates if e.node == node]
        for e in mine:
            er = _errors(e, truth(r, e.track, e.t))
            per_t[e.t].append(er)
            all_err.append(er)
            is_fix = e.x.size < 6
        if mine:
            finals.append(all_err[-1])
    ts = sorted(per_t)
    return {
        "rmse_pos": _rms([e["pos2"] for e in all_err]),
        "rmse_vel": _rms([e["vel2"] for e in all_err]),
        "rmse_acc": _rms([e["acc2"] for e in all_err]),
        # CEP50 of the final fixes (median horizontal miss distance), for emitter fixes only.
        "cep50": float(np.median([f["horiz"] for f in finals])) if is_fix and finals else None,
        "anees": float(np.mean([e["nees"] for e in all_err])) if all_err else None,
        "n_updates": len(all_err),
        "series": {
            "t": ts,
            "rmse_pos": [_rms([e["pos2"] for e in per_t[t]]) for t in ts],
            "anees": [float(np.mean([e["nees"] for e in per_t[t]])) for t in ts],
        },
    }


def summary(scenario, topology: str, fusion_rule: str | None, seed: int, runs: int,
            methods: dict[str, dict], sources: dict | None = None, crb: dict | None = None) -> dict:
    return {
        "scenario": scenario.name,
        "topology": topology,
        "fusion_rule": fusion_rule,
        "seed": seed,
        "runs": runs,
        "methods": methods,
        "crb": crb or {"t": [], "rmse_pos": []},
        "sources": sources or {},
    }


def format_table(doc: dict) -> str:
    """The summary as a fixed-width table for the terminal."""
    def f(v: float | None, w: int = 10) -> str:
        return f"{'—':>{w}}" if v is None else f"{v:>{w}.4f}"

    lines = [f"scenario {doc['scenario']} · topology {doc['topology']} · fusion rule {doc['fusion_rule']} · "
             f"seed {doc['seed']} · runs {doc['runs']}",
             f"{'method':<10}{'rmse_pos':>10}{'rmse_vel':>10}{'rmse_acc':>10}{'cep50':>10}{'anees':>10}{'updates':>9}"]
    for name, m in doc["methods"].items():
        lines.append(f"{name:<10}{f(m['rmse_pos'])}{f(m['rmse_vel'])}{f(m['rmse_acc'])}{f(m['cep50'])}"
                     f"{f(m['anees'])}{m['n_updates']:>9d}")
    for src, s in doc.get("sources", {}).items():
        if s.get("dead_intervals") or s.get("rejected"):
            lines.append(f"source {src}: dead {s.get('dead_intervals')}, rejected {s.get('rejected', 0)}")
    return "\n".join(lines)
