"""Helpers for tests that run ``zfusion run`` and disturb its processes from outside."""

from __future__ import annotations

import json
import math
import signal
import subprocess
import sys
import time
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import psutil
import zenoh

from schemas import KeySpace, Message, decode
from services.launcher import FUSER_ID, free_port
from services.node import ZenohOptions
from services.evaluation import run_method
from services.scoring import truth_function
from services.summary import method_summary
from sensors_sim import load_scenario

from _wire import SCENARIO
from conftest import zfusion


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


def child(launcher: psutil.Process, command: str, ident: str, timeout: float = 120,
          exclude: tuple[int, ...] = ()) -> psutil.Process:
    """The launcher's child ``zfusion COMMAND`` for process ``ident`` (``--id``, else a
    tracker's ``--sensor``, a regional fuser's ``--region``: a regional standby's is its
    ``--id``); ``exclude`` skips pids (a killed incarnation). A loaded
    machine can take over 30 s to bring a run's processes up (the launcher starts the
    recorder and the fuser before the sources)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        for c in launcher.children(recursive=True):
            try:
                cmd = c.cmdline()
            except psutil.Error:
                continue
            if c.pid in exclude or "services.cli" not in cmd or cmd[cmd.index("services.cli") + 1] != command:
                continue
            named = {a: cmd[i + 1] for i, a in enumerate(cmd[:-1]) if a in ("--id", "--sensor", "--region")}
            if named.get("--id", named.get("--sensor", named.get("--region"))) == ident:
                return c
        time.sleep(0.1)
    raise AssertionError(f"no {command} {ident} process")


@dataclass(frozen=True)
class Hold:
    """Stop a process (SIGSTOP) once the fused output reaches ``at`` (None: right after
    the last kill), until it reaches ``until`` or for at most ``max_s`` seconds of wall
    time, or else until the process ``exit_of`` (command, id) has exited and for at
    least ``min_s`` seconds; then let it go on (SIGCONT). Zenoh's lease is 10 s: a
    process stopped longer loses its links (and what was sent on them meanwhile)."""

    command: str
    ident: str
    until: float = math.inf
    at: float | None = None
    max_s: float = math.inf
    exit_of: tuple[str, str] | None = None
    min_s: float = 0.0


def disturb(tmp_path, scenario, deployment, speed, kills, *extra, timeout=120, killed_at=None,
            hold: Hold | None = None):
    """Run the scenario; once the fused output reaches each scenario time of ``kills``
    (t, command, id), kill -9 that process (its monotonic time appended to ``killed_at``);
    then :class:`Hold` ``hold``. Returns the summary and the launcher's stderr."""
    watch = FusedWatch(deployment)
    proc = subprocess.Popen(run_cmd(tmp_path, scenario, deployment, "--speed", str(speed),
                                    "--connect", watch.endpoint, *extra),
                            stdout=subprocess.DEVNULL, stderr=(tmp_path / "run.log").open("w"))
    try:
        launcher = psutil.Process(proc.pid)
        for t, command, ident in kills:
            victim = child(launcher, command, ident)
            watch.wait_until(t - 1.0, proc)  # the fused output lags the sensors by about a scan
            victim.kill()
            if killed_at is not None:
                killed_at.append(time.monotonic())
        if hold is not None:
            held = child(launcher, hold.command, hold.ident)
            awaited = child(launcher, *hold.exit_of) if hold.exit_of else None
            if hold.at is not None:
                watch.wait_until(hold.at, proc)
            held.suspend()
            since = time.monotonic()
            try:
                if awaited is None:
                    watch.wait_until(hold.until, proc, timeout=min(hold.max_s, 60.0), expire=hold.max_s < math.inf)
                else:
                    awaited.wait(60)  # (psutil: raises TimeoutExpired past the deadline)
                time.sleep(max(0.0, since + hold.min_s - time.monotonic()))  # the fault's own length
            finally:
                held.resume()
        proc.wait(timeout)
    finally:
        stop_run(proc, watch)
    err = run_log(proc, tmp_path)
    return json.loads((tmp_path / "out.json").read_text()), err


def stop_run(proc: subprocess.Popen, watch: "FusedWatch") -> None:
    """A run's end in a test's ``finally``: SIGINT if it still runs, then the watch closed."""
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
        proc.wait(30)
    watch.close()


def run_log(proc: subprocess.Popen, tmp_path) -> str:
    """The launcher's stderr (``run.log``), once it has exited 0."""
    err = (tmp_path / "run.log").read_text()
    assert proc.returncode == 0, err[-3000:]
    return err


class FusedWatch:
    """A Zenoh session of the test that the run's processes dial (``--connect``, or the
    router's endpoint): it follows the fused output, so a test disturbs a run at a point
    of its *output* (under load, sources may start late and catch up in a burst; the
    wall clock says little about how far the run is). ``got``: every message, with its
    arrival (monotonic)."""

    def __init__(self, deployment: str, connect: str | None = None):
        self.endpoint = f"tcp/127.0.0.1:{free_port()}"
        opts = ZenohOptions(connect=[connect], mode="client") if connect else ZenohOptions(listen=[self.endpoint])
        self.session = zenoh.open(opts.to_config())
        self.t = -1.0
        self.got: list[tuple[float, Message]] = []
        self._sub = self.session.declare_subscriber(KeySpace(deployment).fused("fuser"), self._on_fused)

    def _on_fused(self, sample) -> None:
        msg = decode(sample.payload.to_bytes())
        self.got.append((time.monotonic(), msg))
        self.t = max(self.t, msg.t)

    def wait_until(self, t: float, proc, timeout: float = 60, expire: bool = False) -> None:
        """Until the fused output has reached scenario time ``t``; at most ``timeout``
        seconds (then a failure, or with ``expire`` the end of the wait), and while the
        run goes on (or with ``expire`` until it ends)."""
        deadline = time.monotonic() + timeout
        while self.t < t:
            if expire and (time.monotonic() >= deadline or proc.poll() is not None):
                return
            assert proc.poll() is None, "the run ended early"
            assert time.monotonic() < deadline, f"no fused estimate at t >= {t} (last {self.t})"
            time.sleep(0.02)

    def close(self) -> None:
        self._sub.undeclare()
        self.session.close()


class LiveRun:
    """A ``zfusion run`` of the scenario that also dials a Zenoh session of the test's own,
    through which the test publishes on the run's keys and watches its ``fused`` output
    (``fused_t``: the latest time fused) and the fuser's ``status`` (``statuses``)."""

    def __init__(self, tmp_path, deployment: str, speed: str):
        self.keys = KeySpace(deployment)
        ep = f"tcp/127.0.0.1:{free_port()}"
        self.session = zenoh.open(ZenohOptions(listen=[ep]).to_config())
        self.json = tmp_path / "run.json"
        self.launcher = zfusion("run", "--scenario", SCENARIO, "--speed", speed, "--rrd", str(tmp_path / "run.rrd"),
                                "--json", str(self.json), "--deployment", deployment, "--connect", ep,
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE)
        self.fused_t = -math.inf
        self.statuses: list[dict] = []
        self._pubs: dict[str, zenoh.Publisher] = {}
        self._subs = [self.session.declare_subscriber(self.keys.fused("fuser"), self._on_fused),
                      self.session.declare_subscriber(self.keys.status(FUSER_ID), self._on_status)]
        self.fuser = self._child(FUSER_ID)

    def _on_fused(self, sample) -> None:
        self.fused_t = max(self.fused_t, decode(sample.payload.to_bytes()).t)

    def _on_status(self, sample) -> None:
        msg = decode(sample.payload.to_bytes())
        self.statuses.append({"seq": msg.seq, **msg.body})

    def _child(self, role: str) -> psutil.Process:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            for p in psutil.Process(self.launcher.pid).children(recursive=True):
                try:
                    cmd = p.cmdline()
                except psutil.NoSuchProcess:
                    continue
                if "services.cli" in cmd and cmd[cmd.index("services.cli") + 1] == role:
                    return p
            time.sleep(0.05)
        raise AssertionError(f"no {role} process under the launcher")

    def put(self, key_id: str, data: bytes) -> None:
        """Publish on ``meas/<key_id>`` as a sensor does: reliable, blocking when congested,
        so everything sent is delivered."""
        if key_id not in self._pubs:
            self._pubs[key_id] = self.session.declare_publisher(
                self.keys.meas(key_id), congestion_control=zenoh.CongestionControl.BLOCK,
                reliability=zenoh.Reliability.RELIABLE)
        self._pubs[key_id].put(data)

    def wait_fused(self, t: float, timeout: float = 60.0) -> None:
        deadline = time.monotonic() + timeout
        while self.fused_t < t:
            assert self.launcher.poll() is None, "the run ended early"
            assert time.monotonic() < deadline, f"no fused output at {t} s within {timeout} s"
            time.sleep(0.01)

    def wait_status(self, condition, timeout: float = 60.0) -> dict:
        """Until the fuser's latest status has counters satisfying ``condition``
        (statuses come once a second); those counters."""
        deadline = time.monotonic() + timeout
        while True:
            last = max(self.statuses, key=lambda s: s["seq"]) if self.statuses else None
            if last is not None and condition(last["counters"]):
                return last["counters"]
            assert self.launcher.poll() is None, "the run ended early"
            assert time.monotonic() < deadline, f"no such fuser status within {timeout} s (last: {last})"
            time.sleep(0.02)

    def finish(self, timeout: float = 90.0) -> tuple[dict, dict]:
        """Wait for the run to end; its JSON summary and the fuser's last status."""
        _, err = self.launcher.communicate(timeout=timeout)
        assert self.launcher.returncode == 0, err[-3000:].decode(errors="replace")
        last = max(self.statuses, key=lambda s: s["seq"])
        return json.loads(self.json.read_text()), last

    def close(self) -> None:
        if self.launcher.poll() is None:
            self.launcher.kill()
            self.launcher.wait()
        for s in self._subs:
            s.undeclare()
        self.session.close()


@contextmanager
def live_run(tmp_path, deployment: str, speed: str):
    run = LiveRun(tmp_path, deployment, speed)
    try:
        yield run
    finally:
        run.close()


def assert_equals_in_process(doc: dict, until: float = math.inf) -> None:
    """The run's fused series (up to ``until``) equal the clean in-process evaluation to 1e-9."""
    ref, got = in_process(SCENARIO, "SS"), doc["methods"]["SS"]
    n = sum(1 for t in ref["series"]["t"] if t <= until)
    assert n and got["series"]["t"][:n] == ref["series"]["t"][:n]
    for key in ("rmse_pos", "anees"):
        np.testing.assert_allclose(got["series"][key][:n], ref["series"][key][:n], rtol=0, atol=1e-9)


def sensor_stream(deployment: str, scenario: str, sensor: str, *extra: str, timeout: float = 120) -> list[bytes]:
    """Every sample ``zfusion sensor --id SENSOR`` of ``scenario`` publishes at
    ``--speed max`` (``extra``: more of its options), captured by a peer it dials, which
    it waits for (``--wait-for``: a liveliness token of this session)."""
    ep = f"tcp/127.0.0.1:{free_port()}"
    keys = KeySpace(deployment)
    got: list[bytes] = []
    session = zenoh.open(ZenohOptions(listen=[ep]).to_config())
    try:
        sub = session.declare_subscriber(keys.meas(sensor), lambda smp: got.append(smp.payload.to_bytes()))
        token = session.liveliness().declare_token(keys.alive("probe", "test"))
        p = subprocess.run([sys.executable, "-m", "services.cli", "sensor", "--scenario", scenario, "--id", sensor,
                            "--speed", "max", *extra, "--wait-for", "probe", "--deployment", deployment,
                            "--connect", ep], capture_output=True, text=True, timeout=timeout)
        assert p.returncode == 0, p.stderr[-2000:]
        token.undeclare()
        sub.undeclare()
    finally:
        session.close()
    return got
