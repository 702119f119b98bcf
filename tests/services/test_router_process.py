"""``zfusion router`` stops on a signal within a second, whichever of its threads the
kernel hands the signal to, and even if Zenoh does not close its session."""

from __future__ import annotations

import ctypes
import platform
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from services.launcher import free_port
from services.router import CLOSE_WAIT_S

SYS_TGKILL = {"x86_64": 234, "aarch64": 131}.get(platform.machine())
ZENOH_THREADS = {"app-0", "net-0", "acc-0"}  # its runtime's threads, by name


def _status(task: Path, field: str) -> str:
    return next((line for line in (task / "status").read_text().splitlines() if line.startswith(field)), "")


def _router(*prelude: str) -> subprocess.Popen:
    """``zfusion router`` on a free loopback port (``prelude``: Python run before it),
    once it says it listens."""
    ep = f"tcp/127.0.0.1:{free_port()}"
    code = "\n".join([*prelude, "from services.cli import main",
                      f"sys.exit(main(['router', '--listen', {ep!r}]))"])
    r = subprocess.Popen([sys.executable, "-c", "import sys\n" + code], stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True)
    assert "listening" in r.stdout.readline()
    return r


def _exit_within(r: subprocess.Popen, seconds: float) -> tuple[float, str]:
    t = time.monotonic()
    try:
        _, err = r.communicate(timeout=seconds)
    except subprocess.TimeoutExpired:
        r.kill()
        r.communicate()
        pytest.fail(f"the router had not exited {seconds} s after the signal")
    return time.monotonic() - t, err


@pytest.mark.skipif(SYS_TGKILL is None or sys.platform != "linux", reason="tgkill: Linux on x86_64 or aarch64")
@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_a_signal_taken_by_one_of_zenohs_threads_stops_the_router(sig):
    """A signal sent to the process may be taken by any thread that does not block it;
    here it is sent to one of Zenoh's runtime threads once the main thread sleeps. The
    main thread, waiting without a timeout, was never woken to run the handler: the
    router ran on for ever."""
    r = _router()
    try:
        task = Path(f"/proc/{r.pid}/task")
        deadline = time.monotonic() + 10
        while "\tS" not in _status(task / str(r.pid), "State") and time.monotonic() < deadline:
            time.sleep(0.01)  # the main thread is past its start, waiting
        zenoh_threads = [int(t.name) for t in task.iterdir() if (t / "comm").read_text().strip() in ZENOH_THREADS]
        assert zenoh_threads, [(t / "comm").read_text() for t in task.iterdir()]
        libc = ctypes.CDLL(None, use_errno=True)
        assert libc.syscall(SYS_TGKILL, r.pid, zenoh_threads[0], int(sig)) == 0, ctypes.get_errno()
        took, _ = _exit_within(r, 5.0)
    finally:
        if r.poll() is None:
            r.kill()
            r.wait()
    assert r.returncode == 0
    assert took < 1.0


def test_a_router_whose_session_does_not_close_still_exits():
    """Zenoh's close may wait on a peer (its own timeout is 10 s); the router leaves it
    after CLOSE_WAIT_S and says so on stderr, in one line."""
    hang = ["import threading, zenoh",
            "_open = zenoh.open",
            "class Stuck:",
            "    def __init__(self, s): self.s = s",
            "    def close(self): threading.Event().wait()",
            "zenoh.open = lambda conf: Stuck(_open(conf))"]
    r = _router(*hang)
    r.send_signal(signal.SIGINT)
    took, err = _exit_within(r, CLOSE_WAIT_S + 5.0)
    assert r.returncode == 0
    assert CLOSE_WAIT_S <= took < CLOSE_WAIT_S + 1.0
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "had not closed" in lines[0], err
