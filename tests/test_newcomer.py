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
