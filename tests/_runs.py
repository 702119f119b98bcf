"""Helpers for tests that run ``zfusion run`` and disturb its processes from outside."""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np
import psutil
import zenoh

from schemas import KeySpace, decode
from services.launcher import free_port
from services.node import ZenohOptions
from services.evaluation import run_method
from services.summary import method_summary, truth_function
from sensors_sim import load_scenario


def run_cmd(tmp_path: Path, scenario: str, deployment: str, *extra: str) -> list[str]:
    """``zfusion run`` writing ``out.rrd`` and ``out.json`` into ``tmp_path``."""
    return [sys.executable, "-m", "services.cli", "run", "--scenario", scenario, "--deployment", deployment,
            "--rrd", str(tmp_path / "out.rrd"), "--json", str(tmp_path / "out.json"), *extra]


def in_process(scenario: str, method: str) -> dict:
    """The in-process evaluation of the same scenario: what an undisturbed run gives."""
    sc = load_scenario(scenario)
    return method_summary([run_method(sc, method)], truth_function(sc))


def same_series(got: dict, ref: dict) -> None:
    """A run's method summary equals the reference's, step by step, to 1e-9."""
    assert got["n_updates"] == ref["n_updates"] > 0
    assert got["series"]["t"] == ref["series"]["t"]
    for key in ("rmse_pos", "anees"):
        np.testing.assert_allclose(got["series"][key], ref["series"][key], rtol=0, atol=1e-9)


def child(launcher: psutil.Process, command: str, ident: str, timeout: float = 30,
          exclude: tuple[int, ...] = ()) -> psutil.Process:
    """The launcher's child ``zfusion COMMAND`` for process ``ident`` (``--id``, or a
    tracker's ``--sensor``); ``exclude`` skips pids (a killed incarnation)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        for c in launcher.children(recursive=True):
            try:
                cmd = c.cmdline()
            except psutil.Error:
                continue
            if c.pid in exclude or "services.cli" not in cmd or cmd[cmd.index("services.cli") + 1] != command:
                continue
            if any(cmd[i + 1] == ident for i, a in enumerate(cmd[:-1]) if a in ("--id", "--sensor")):
                return c
        time.sleep(0.1)
    raise AssertionError(f"no {command} {ident} process")


class FusedWatch:
    """A Zenoh session of the test that the run's processes dial (``--connect``, or the
    router's endpoint): it follows the fused output, so a test disturbs a run at a point
    of its *output* (under load, sources may start late and catch up in a burst; the
    wall clock says little about how far the run is)."""

    def __init__(self, deployment: str, connect: str | None = None):
        self.endpoint = f"tcp/127.0.0.1:{free_port()}"
        opts = ZenohOptions(connect=[connect], mode="client") if connect else ZenohOptions(listen=[self.endpoint])
        self.session = zenoh.open(opts.to_config())
        self.t = -1.0
        self._sub = self.session.declare_subscriber(KeySpace(deployment).fused(), self._on_fused)

    def _on_fused(self, sample) -> None:
        self.t = max(self.t, decode(sample.payload.to_bytes()).t)

    def wait_until(self, t: float, proc, timeout: float = 60) -> None:
        """Until the fused output has reached scenario time ``t``."""
        deadline = time.monotonic() + timeout
        while self.t < t:
            assert proc.poll() is None, "the run ended early"
            assert time.monotonic() < deadline, f"no fused estimate at t >= {t} (last {self.t})"
            time.sleep(0.02)

    def close(self) -> None:
        self._sub.undeclare()
        self.session.close()
