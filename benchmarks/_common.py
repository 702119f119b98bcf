"""Shared helpers of the benchmark scripts: where the repository is, what machine and
load a figure was measured under, medians of interleaved repeats, tables."""

from __future__ import annotations

import os
import platform
import statistics
import sys
import time
from pathlib import Path
from typing import Callable, Sequence

REPO = Path(__file__).resolve().parent.parent
if str(REPO) not in sys.path:  # run from a checkout without installing the package too
    sys.path.insert(0, str(REPO))


def cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown CPU"


def machine_line() -> str:
    import numpy as np

    la = os.getloadavg()
    blas = os.environ.get("OPENBLAS_NUM_THREADS", "default")
    return (f"{cpu_model()}, {os.cpu_count()} cores; Python {platform.python_version()}, numpy {np.__version__}; "
            f"OPENBLAS_NUM_THREADS={blas}; load average {la[0]:.2f} {la[1]:.2f} {la[2]:.2f} (1/5/15 min)")


def load_now() -> float:
    return os.getloadavg()[0]


def calibrate(fn: Callable[[], object], target_s: float = 0.02) -> int:
    """How many calls of ``fn`` take about ``target_s``."""
    fn()
    n = 1
    while True:
        t0 = time.perf_counter()
        for _ in range(n):
            fn()
        dt = time.perf_counter() - t0
        if dt >= target_s / 4 or n >= 1 << 20:
            return max(1, int(n * target_s / max(dt, 1e-9)))
        n *= 4


def interleaved(cands: dict[str, Callable[[], object]], repeats: int, target_s: float = 0.02,
                numbers: dict[str, int] | None = None) -> dict[str, dict[str, float]]:
    """Time every candidate ``repeats`` times, round-robin (so that whatever else loads the
    machine meanwhile loads every candidate alike). Per call, in µs: median and min of the
    wall-clock time, and median of this thread's CPU time (robust to other load)."""
    numbers = dict(numbers or {})
    for k, f in cands.items():
        numbers.setdefault(k, calibrate(f, target_s))
    wall: dict[str, list[float]] = {k: [] for k in cands}
    cpu: dict[str, list[float]] = {k: [] for k in cands}
    for _ in range(repeats):
        for k, f in cands.items():
            n = numbers[k]
            c0, t0 = time.thread_time(), time.perf_counter()
            for _ in range(n):
                f()
            t1, c1 = time.perf_counter(), time.thread_time()
            wall[k].append((t1 - t0) / n * 1e6)
            cpu[k].append((c1 - c0) / n * 1e6)
    return {k: {"median_us": statistics.median(wall[k]), "min_us": min(wall[k]),
                "cpu_median_us": statistics.median(cpu[k]), "calls": numbers[k], "repeats": repeats}
            for k in cands}


def percentile(values: Sequence[float], q: float) -> float:
    import numpy as np

    return float(np.percentile(np.asarray(values, dtype=float), q)) if len(values) else float("nan")


def table(headers: Sequence[str], rows: Sequence[Sequence[object]]) -> str:
    """A GitHub-flavoured markdown table (also readable on a terminal)."""
    cells = [[str(h) for h in headers]] + [[str(c) for c in r] for r in rows]
    widths = [max(len(r[i]) for r in cells) for i in range(len(headers))]
    fmt = lambda r: "| " + " | ".join(c.ljust(w) for c, w in zip(r, widths)) + " |"  # noqa: E731
    sep = "|" + "|".join("-" * (w + 2) for w in widths) + "|"
    return "\n".join([fmt(cells[0]), sep] + [fmt(r) for r in cells[1:]])


def fmt_us(v: float) -> str:
    if v != v:
        return "—"
    if v >= 100:
        return f"{v:.0f}"
    if v >= 10:
        return f"{v:.1f}"
    return f"{v:.2f}"
