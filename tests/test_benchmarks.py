"""The in-process benchmark scripts run from a checkout, each with its one documented
command (here with tiny arguments), and print the tables benchmarks/README.md quotes.
They measure speed; this only checks that they still run and report. The
Zenoh benchmarks (bench_fuser, bench_scaling, bench_memory) start a process set per
level and take minutes even with tiny arguments; they are left to their own commands."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

CASES = {
    "bench_asterix.py": (["--repeats", "1", "--seconds", "0.5"],
                         ["## Per record", "decode", "gateway", "CAT062 encode", "## Paced"]),
    "bench_gateway.py": (["--lines", "2000", "--rates", "500", "--seconds", "0.5"],
                         ["## TCP", "sans-I/O path", "Python sink", "## UDP", "Sustained"]),
    "bench_ekf.py": (["--repeats", "1", "--tracks", "50", "--loop-tracks", "5"],
                     ["FilterPy", "Stone Soup", "batch.ekf_step", "## Targets"]),
    "bench_montecarlo.py": (["--runs", "4"], ["vectorised", "run by run"]),
    "profile_fuser.py": (["--measurements", "400", "--repeats", "1", "--top", "5"], ["encode_estimate"]),
    "bench_region.py": (["--aircraft", "20", "--duration", "3", "--layout", "rotating", "--against", str(ROOT)],
                        ["## rotating: CPU seconds", "## Against"]),
    "bench_regional.py": (["--scenario", "region-400", "--duration-s", "3", "--repeats", "1"],
                          ["# Regional scale-out: region-400", "busiest ÷ single", "| 0 |"]),
}


@pytest.mark.slow
@pytest.mark.parametrize("script", sorted(CASES))
def test_benchmark_runs_and_prints_its_tables(script):
    args, expected = CASES[script]
    p = subprocess.run([sys.executable, str(ROOT / "benchmarks" / script), *args], cwd=ROOT,
                       capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, (p.stdout[-2000:], p.stderr[-3000:])
    for text in expected:
        assert text in p.stdout, (text, p.stdout[-3000:])
