"""Report figures (matplotlib, headless): curves against time with their χ² bands, emitter
fixes with error ellipses, and the curves an evaluation summary holds.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Sequence

import numpy as np

from fusion.metrics import chi2_bounds, error_ellipse


def pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save_figure(fig, path: Path) -> str:
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110, bbox_inches="tight", metadata={"Software": None})
    pyplot().close(fig)
    return path.name


def nis_bands(dofs, runs: int, prob: float = 0.95) -> list[tuple[float, float, str]]:
    """χ² intervals of the per-step average NIS / dof over ``runs`` runs, one per dof."""
    out = []
    for d in sorted({int(round(d)) for d in dofs if d}):
        lo, hi = chi2_bounds(d, runs, prob)
        out.append((lo / d, hi / d, f"95 % χ² interval, dof {d}"))
    return out


def dofs_of(series: dict) -> list:
    return [d for d in series.get("nis_dof", []) if d is not None and float(d).is_integer()]


def plot_series(curves: dict[str, tuple[list, list]], path: Path, ylabel: str, title: str,
                bound: tuple[list, list] | None = None, band: tuple[float, float] | None = None,
                logy: bool = True, bands: Sequence[tuple[float, float, str]] = ()) -> str:
    """Lines ``label -> (t, y)``, an optional CRB curve and optional horizontal χ² bands."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(7.5, 4.2))
    for label, (t, y) in curves.items():
        pts = [(a, b) for a, b in zip(t, y) if b is not None]
        if pts:
            ax.plot(*zip(*pts), label=label, lw=1.4)
    if bound is not None:
        pts = [(a, b) for a, b in zip(*bound) if b is not None and math.isfinite(b)]
        if pts:
            ax.plot(*zip(*pts), "k--", lw=1.6, label="Cramér–Rao bound")
    if band is not None:
        bands = [(band[0], band[1], "95 % χ² interval"), *bands]
    for i, (lo, hi, label) in enumerate(bands):
        ax.axhspan(lo, hi, color=str(0.85 - 0.08 * i), alpha=0.6, zorder=0, label=label)
    if logy:
        ax.set_yscale("log")
    ax.set_xlabel("t (s)")
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    return save_figure(fig, path)


def _ellipse_xy(P, prob=0.95, n=100):
    e = error_ellipse(np.asarray(P, dtype=float), prob)
    th = np.linspace(0, 2 * np.pi, n)
    c, s = math.cos(e.angle), math.sin(e.angle)
    x, y = e.a * np.cos(th), e.b * np.sin(th)
    return c * x - s * y, s * x + c * y


def plot_fixes(doc: dict, methods: Sequence[str], path: Path, title: str) -> str:
    """Final-fix errors per method: scatter, the filter's mean 95 % ellipse, the CRB's
    95 % ellipse, the textbook CEP50 circle and the median point (the thesis's statistic)."""
    plt = pyplot()
    methods = [m for m in methods if m in doc["methods"] and (doc["methods"][m].get("final") or {}).get("err")]
    n = len(methods)
    cols = min(3, n) or 1
    rows = max(1, math.ceil(n / cols))
    fig, axes = plt.subplots(rows, cols, figsize=(4.2 * cols, 4.0 * rows + 0.6), squeeze=False,
                             layout="constrained")
    crb = doc.get("crb") or {}
    for ax, name in zip(axes.flat, methods):
        m = doc["methods"][name]
        err = np.asarray(m["final"]["err"])
        ax.plot(err[:, 0], err[:, 1], ".", ms=3, alpha=0.6, label="final fixes")
        ax.plot(*_ellipse_xy(m["final"]["P_mean"]), "C1-", lw=1.2, label="filter's mean P, 95 %")
        if crb.get("final_P"):
            ax.plot(*_ellipse_xy(crb["final_P"]), "k--", lw=1.2, label="CRB, 95 %")
        if m.get("cep50") is not None:
            th = np.linspace(0, 2 * np.pi, 100)
            ax.plot(m["cep50"] * np.cos(th), m["cep50"] * np.sin(th), "C2:", lw=1.2, label="CEP50 (median miss)")
        med = np.median(err, axis=0)
        ax.plot(*med, "r+", ms=12, mew=2, label="median point (thesis)")
        ax.plot(0, 0, "kx")
        ax.set_title(name, fontsize=10)
        ax.set_aspect("equal", adjustable="datalim")
        ax.grid(True, alpha=0.3)
        ax.set_xlabel("east error (m)")
        ax.set_ylabel("north error (m)")
    for ax in list(axes.flat)[n:]:
        ax.axis("off")
    if n:
        handles, labels = axes.flat[0].get_legend_handles_labels()
        fig.legend(handles, labels, loc="outside lower center", ncol=5, fontsize=8)
    fig.suptitle(title)
    return save_figure(fig, path)


# The curves of an evaluation summary ------------------------------------------------------
def series_of(doc: dict, key: str) -> dict[str, tuple[list, list]]:
    return {name: (m["series"]["t"], m["series"].get(key, [])) for name, m in doc["methods"].items()}


def has_series(doc: dict, key: str) -> bool:
    """Whether any method has a value of series ``key`` (many-target runs have GOSPA, no RMSE)."""
    return any(v is not None for m in doc["methods"].values() for v in m["series"].get(key, []))


def nees_band(doc: dict) -> tuple[float, float] | None:
    b = {tuple(m["anees_bounds"]) for m in doc["methods"].values() if m.get("anees_bounds")}
    return b.pop() if len(b) == 1 else None


def nis_normalised(doc: dict) -> dict[str, tuple[list, list]]:
    out = {}
    for name, m in doc["methods"].items():
        s = m["series"]
        y = [None if a is None or not d else a / d for a, d in zip(s.get("anis", []), s.get("nis_dof", []))]
        out[name] = (s["t"], y)
    return out
