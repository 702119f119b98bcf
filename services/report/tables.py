"""Report text: number formatting, Markdown tables, ratios, and writing a report's Markdown
with the JSON bundle its numbers come from.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Sequence

import numpy as np

from fusion.metrics import chi2_bounds


def fmt(v, digits: int = 2) -> str:
    """A table cell: fixed point with ``digits`` decimals, scientific beyond 1e5, '—' for None."""
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "—"
    v = float(v)
    if v != 0.0 and (abs(v) >= 1e5 or abs(v) < 10.0 ** -digits):
        return f"{v:.3e}"
    return f"{v:.{digits}f}"


def md_table(headers: Sequence[str], rows: Sequence[Sequence[str]]) -> str:
    out = ["| " + " | ".join(headers) + " |", "|" + "|".join("---" for _ in headers) + "|"]
    out += ["| " + " | ".join(str(c) for c in r) + " |" for r in rows]
    return "\n".join(out)


def ratio(a, b) -> float | None:
    return None if a is None or b is None or b == 0 else float(a) / float(b)


def inside_fraction(series: dict, dof: int, runs: int, key: str = "anees") -> float | None:
    """Fraction of output steps whose average (over the runs) lies in the per-step 95 % χ² interval."""
    vals = [v for v in series.get(key, []) if v is not None]
    if not vals or not dof:
        return None
    lo, hi = chi2_bounds(dof, runs)
    return float(np.mean([(lo <= v <= hi) for v in vals]))


def dumps(obj, indent: int = 0) -> str:
    """JSON with one key per line but lists of numbers on one line (diff-friendly, compact)."""
    pad, pad1 = " " * indent, " " * (indent + 1)
    if isinstance(obj, dict):
        if not obj:
            return "{}"
        items = [f"{pad1}{json.dumps(str(k))}: {dumps(v, indent + 1)}" for k, v in obj.items()]
        return "{\n" + ",\n".join(items) + "\n" + pad + "}"
    if isinstance(obj, (list, tuple)):
        if all(not isinstance(x, (dict, list, tuple)) for x in obj):
            return json.dumps(list(obj), ensure_ascii=False, allow_nan=False)
        return "[\n" + ",\n".join(pad1 + dumps(x, indent + 1) for x in obj) + "\n" + pad + "]"
    return json.dumps(obj, ensure_ascii=False, allow_nan=False)


def write_report(out_dir: Path, name: str, bundle: dict, text: list[str]) -> Path:
    """A report's ``NAME.json`` (every number it shows) and ``NAME.md``; the path of the latter."""
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / f"{name}.json").write_text(dumps(bundle) + "\n")
    path = out_dir / f"{name}.md"
    path.write_text("\n".join(text))
    return path


def pct(a, b) -> str:
    r = ratio(a, b)
    return "—" if r is None else f"{100.0 * r:.1f} %"


def rank_values(values: dict[str, float]) -> dict[str, float]:
    order = sorted(values, key=lambda k: values[k])
    return {k: float(i + 1) for i, k in enumerate(order)}


def rms_from(values: Sequence, k0: int) -> float | None:
    """``√mean(v²)`` of a per-epoch RMSE series from its ``k0``-th entry (0-based) on:
    the RMS over every run's estimates of those epochs when each run has one per epoch."""
    vals = [v for v in values[k0:] if v is not None]
    return float(np.sqrt(np.mean(np.square(vals)))) if vals else None
