"""The supervisor of a run's processes: it starts a :class:`~services.plan.RunPlan`,
relays what the children say, and restarts what may be restarted.

Start: every process once the processes it waits for are up (announced on the fabric),
stage by stage (the fuser, recorder and exporters; then the local trackers); the
sources last, together, with a common start time (``--start-at``) as far ahead as the
first stage took to come up, so that they are running by then even under load.

Watch: a child killed from outside (a signal the supervisor did not send) is an
*outage*. The restartable processes (fuser, trackers, recorder, exporters) are started
again with the same command line (``--restart``, at most :data:`MAX_RESTARTS` times
each, :data:`RESTART_DELAY` s later); sources never (they stand for the sensors). A
child that fails on its own (positive exit code) is reported with its last line on
stderr. Children get ``PR_SET_PDEATHSIG``, so even a supervisor killed with SIGKILL
leaves none behind. What each outage does and what the summary reports:
docs/reliability.md ("Faults").
"""

from __future__ import annotations

import ctypes
import logging
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from types import MappingProxyType
from typing import Iterable, Mapping

from .plan import RunPlan

log = logging.getLogger("zfusion")

RESTART_DELAY = 0.5  # s: lets the fabric see the dead process's token go before the new one appears
MAX_RESTARTS = 3  # per process: a process killed again and again is not coming back
UP_TIMEOUT = 60.0  # s a stage of processes has to come up


def die_with_parent() -> None:  # runs in the child between fork and exec
    try:
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
    except OSError:
        pass


@dataclass
class Children:
    """The run's child processes. Each child's stderr is relayed line by line to ours by a
    thread that keeps only its last non-blank line (what a failed child said last)."""

    procs: dict[str, subprocess.Popen] = field(default_factory=dict)
    argv: dict[str, list[str]] = field(default_factory=dict)  # each child's command line, to restart it
    last_line: dict[str, str] = field(default_factory=dict)  # each child's last line on stderr
    relays: list[threading.Thread] = field(default_factory=list)
    forced: set[str] = field(default_factory=set)  # killed by us at the end: no exit within the grace

    def start(self, name: str, argv: list[str]) -> None:
        """Start ``zfusion ARGV`` as the child ``name``."""
        cmd = [sys.executable, "-m", "services.cli", *argv]
        log.debug("starting %s: %s", name, " ".join(cmd))
        self.argv[name] = argv
        # Its own process group: a Ctrl-C at the terminal reaches the launcher alone, which
        # stops the children in order (one still importing would print a traceback).
        proc = subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stderr=subprocess.PIPE, preexec_fn=die_with_parent,
                                process_group=0)
        self.procs[name] = proc
        relay = threading.Thread(target=self._relay, args=(name, proc.stderr), daemon=True, name=f"stderr-{name}")
        relay.start()
        self.relays.append(relay)

    def _relay(self, name: str, stream) -> None:
        out = getattr(sys.stderr, "buffer", None)
        for line in iter(stream.readline, b""):
            if line.strip():
                self.last_line[name] = line.decode(errors="replace").strip()
            try:
                if out is not None:
                    out.write(line)
                    out.flush()
                else:
                    sys.stderr.write(line.decode(errors="replace"))
            except (OSError, ValueError):  # our stderr closed: keep draining the child's
                pass
        stream.close()

    def exited(self, names: Iterable[str]) -> str | None:
        """Which of ``names`` have exited, with their exit codes (None if none has)."""
        dead = [f"{n} exited with code {self.procs[n].poll()}" for n in names
                if n in self.procs and self.procs[n].poll() is not None]
        return "; ".join(dead) + " (its error is above)" if dead else None

    def failed(self) -> str | None:
        """The first child that failed on its own (a positive exit code), with what it said
        last; None while none has. A kill (negative code) is an outage, not a failure."""
        for name, proc in self.procs.items():
            code = proc.poll()
            if code is not None and code > 0:
                time.sleep(0.05)  # its last line may still be in the relay
                said = self.last_line.get(name)
                return f"{name} failed (exit {code})" + (f": {said}" if said else "")
        return None

    def wait(self, name: str, timeout: float) -> int | None:
        try:
            return self.procs[name].wait(timeout)
        except subprocess.TimeoutExpired:
            return None

    def terminate(self, names: Iterable[str], drain, grace: float = 10.0) -> None:
        """SIGTERM to ``names``, calling ``drain`` while they stop (their last status); a
        child still there after ``grace`` seconds is killed."""
        live = [self.procs[n] for n in names if n in self.procs and self.procs[n].poll() is None]
        for p in live:
            p.send_signal(signal.SIGTERM)
        deadline = time.monotonic() + grace
        while any(p.poll() is None for p in live) and time.monotonic() < deadline:
            drain(0.1)
        for name in names:
            p = self.procs.get(name)
            if p is not None and p in live and p.poll() is None:
                self.forced.add(name)
                p.kill()
                p.wait()

    def stop_all(self, grace: float = 5.0, longer: Mapping[str, float] = MappingProxyType({})) -> None:
        """SIGTERM to every child still running; one still there ``grace`` seconds later
        (``longer[name]`` for the named ones) is killed."""
        live = {n: p for n, p in self.procs.items() if p.poll() is None}
        for p in live.values():
            p.send_signal(signal.SIGTERM)
        start = time.monotonic()
        for name, p in live.items():
            try:
                p.wait(max(0.0, start + longer.get(name, grace) - time.monotonic()))
            except subprocess.TimeoutExpired:
                self.forced.add(name)
                p.kill()
                p.wait()
        for relay in self.relays:  # their last words before ours
            relay.join(timeout=1.0)


class Supervisor:
    """Starts the processes of a run and watches them: records every death, restarts
    what the policy allows (module docstring), and says when a restarted process is back.

    Args:
        children: the run's children.
        plan: the run's processes.
        restart: the ``--restart`` policy.
        clock: scenario time now (``None`` before the sources have started).
        event: where to say what happened (the launcher's status events).
        fuser_grace: ``--start-grace`` for a restarted fuser.
    """

    def __init__(self, children: Children, plan: RunPlan, restart: bool, clock, event, fuser_grace: float):
        self.children = children
        self.plan = plan
        self.restartable: set[str] = set()  # none until every consumer is up (start_consumers)
        self.restart = restart
        self.clock = clock
        self.event = event
        self.fuser_grace = fuser_grace
        self.codes: dict[str, list[int]] = {}  # exit codes of every incarnation, in order
        self.outages: dict[str, list[dict]] = {}
        self.recordings: list[str] = []
        self.restarts: dict[str, int] = {}
        self._due: dict[str, float] = {}  # monotonic time of each pending restart
        self._restarted: dict[str, float] = {}  # monotonic time of each process's latest restart
        self._handled: set[int] = set()  # pids whose exit has been dealt with

    def start_consumers(self, node) -> float:
        """Start every process but the sources (and a router), stage by stage: a process
        once those it waits for are up; returns the seconds the first stage took to come
        up (what starting processes takes on this machine now). Raises ``TimeoutError``
        if a stage does not come up (or a process of it exits first), ``Stopped`` on Ctrl-C."""
        pending = [s for s in self.plan if s.role not in ("source", "router")]
        up: set[str] = set()
        startup: float | None = None
        since = time.monotonic()
        while pending:
            stage = [s for s in pending if set(s.waits_for) <= up]
            if not stage:
                raise ValueError(f"the plan cannot start {[s.id for s in pending]}: they wait for each other "
                                 f"or for a process it does not have")
            for spec in stage:
                self.children.start(spec.id, list(spec.argv))
            ids = [s.id for s in stage]
            node.wait_for(ids, timeout=UP_TIMEOUT, gone=lambda: self.children.exited(ids))
            if startup is None:
                startup = time.monotonic() - since
            up.update(ids)
            pending = [s for s in pending if s.id not in up]
        self.restartable = {s.id for s in self.plan if s.restartable}
        return startup or 0.0

    def start_sources(self, start_at: float) -> None:
        """Start every source, their scenario time 0 at the UTC epoch ``start_at``."""
        for spec in self.plan.of_role("source"):
            self.children.start(spec.id, [*spec.argv, "--start-at", repr(start_at)])

    def poll(self) -> None:
        """Deal with the children that have exited and the restarts that are due."""
        for name, proc in list(self.children.procs.items()):
            if proc.pid in self._handled or proc.poll() is None:
                continue
            self._handled.add(proc.pid)
            code = proc.returncode
            self.codes.setdefault(name, []).append(code)
            if code >= 0:
                continue
            self.outages.setdefault(name, []).append({"t_down": self.clock(), "t_up": None, "exit_code": code})
            if self.restart and name in self.restartable and self.restarts.get(name, 0) < MAX_RESTARTS:
                self._due[name] = time.monotonic() + RESTART_DELAY
                self.event(f"{name} killed (signal {-code}): restarting it")
            else:
                self.event(f"{name} killed (signal {-code})")
        now = time.monotonic()
        for name, due in list(self._due.items()):
            if now >= due:
                del self._due[name]
                self.restarts[name] = self.restarts.get(name, 0) + 1
                self.children.start(name, self._argv(name, self.restarts[name] + 1))
                self._restarted[name] = time.monotonic()

    def pending(self, name: str) -> bool:
        return name in self._due

    def _argv(self, name: str, incarnation: int) -> list[str]:
        argv = list(self.children.argv[name])
        if self.plan[name].role == "fuser":  # its sources are running: one not heard within the timeout is dead
            argv += ["--start-grace", str(self.fuser_grace)]
        if "--rrd" in argv:  # never overwrite what the killed recorder wrote
            i = argv.index("--rrd") + 1
            if not self.recordings:
                self.recordings.append(argv[i])
            argv[i] = str(Path(self.recordings[0]).with_suffix(f".{incarnation}.rrd"))
            self.recordings.append(argv[i])
        return argv

    def heard(self, name: str, state: str) -> None:
        """A status from ``name``: the first one of a new incarnation ends its outage. One
        from a process restarted by someone else says "starting" or "ready"; any status
        after our restart is new (the dead one's last was delivered long before)."""
        out = self.outages.get(name)
        if out and out[-1]["t_up"] is None and (state in ("starting", "ready") or name in self._restarted):
            out[-1]["t_up"] = self.clock()
            self.event(f"{name} is back")

    def finish(self) -> dict[str, int]:
        """After the children are stopped: each process's first non-zero exit code, else 0."""
        for name, proc in self.children.procs.items():
            if proc.pid not in self._handled and proc.returncode is not None:
                self._handled.add(proc.pid)
                self.codes.setdefault(name, []).append(proc.returncode)
        return {n: next((c for c in cs if c != 0), cs[-1]) for n, cs in self.codes.items()}
