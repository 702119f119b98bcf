"""What a new user meets: a report on every scenario, prompt failure instead of a hang,
one line instead of a traceback, and no silent nonsense run (each fails on the old bug)."""

from __future__ import annotations

import subprocess
import sys

import pytest


def zf(*args: str, timeout: float = 120) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "services.cli", *args], capture_output=True, text=True,
                          timeout=timeout, stdin=subprocess.DEVNULL)


# 1. eval --report on the many-target scenarios ---------------------------------------------
@pytest.mark.parametrize("args", [("--scenario", "df-multi", "--methods", "EKF"),
                                  ("--scenario", "air-picture", "--methods", "SS", "--duration-s", "8")])
def test_report_of_a_many_target_evaluation(tmp_path, args):
    pytest.importorskip("matplotlib")
    p = zf("eval", *args, "--runs", "1", "--report", str(tmp_path))
    assert p.returncode == 0, p.stderr
    assert "Traceback" not in p.stderr
    text = (tmp_path / "report.md").read_text()
    assert "gospa.png" in text and (tmp_path / "gospa.png").stat().st_size > 1000
    assert "rmse_pos.png" not in text  # no empty RMSE panel for a run that has none


# 2. a child that fails ends the run ---------------------------------------------------------
FAILING_SENSOR = """
import sys
import services.launcher as launcher
start = launcher.Children.start
def failing(self, name, argv):  # the radar's emulator fails at its first scan, as with a bad seed
    if name == "radar2d":
        argv = [*argv, "--seed", "-1"]
    start(self, name, argv)
launcher.Children.start = failing
from services.cli import main
sys.exit(main(sys.argv[1:]))
"""


def test_a_failing_child_ends_the_run_promptly_with_its_message(tmp_path):
    import time

    t0 = time.monotonic()
    p = subprocess.run([sys.executable, "-c", FAILING_SENSOR, "run", "--scenario", "patent-3d", "--speed", "max",
                        "--rrd", str(tmp_path / "r.rrd")], capture_output=True, text=True, timeout=120,
                       stdin=subprocess.DEVNULL)
    assert time.monotonic() - t0 < 60  # it hung for ever before
    assert p.returncode == 1, p.stderr[-2000:]
    last = p.stderr.strip().splitlines()[-1]
    assert last.startswith("zfusion run: radar2d failed (exit ") and "seed" in last, last
