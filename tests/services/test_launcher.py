"""``free_port``: the loopback ports the launcher and the tests listen on are drawn below
the kernel's ephemeral range, where no outgoing connection can take them between the
pick and the bind."""

from __future__ import annotations

import signal
import socket
import subprocess
import sys
from pathlib import Path

import services.launcher as launcher
from services.launcher import PORTS_FROM, free_port
from services.supervisor import Children


def _ephemeral() -> tuple[int, int]:
    low, high = Path("/proc/sys/net/ipv4/ip_local_port_range").read_text().split()
    return int(low), int(high)


def test_free_ports_are_free_spread_and_below_the_ephemeral_range():
    low, _ = _ephemeral()
    ports = [free_port() for _ in range(300)]
    assert all(PORTS_FROM <= p < low for p in ports), sorted(ports)[:5]
    assert len(set(ports)) >= 280  # at random, not the same few: two pickers at once rarely meet
    for p in ports[:20]:
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
            s.bind(("127.0.0.1", p))  # free indeed


def test_where_the_ephemeral_range_leaves_no_room_the_kernel_picks(monkeypatch):
    monkeypatch.setattr(launcher, "_ephemeral_low", lambda: PORTS_FROM + 10)
    low, high = _ephemeral()
    assert all(low <= free_port() <= high for _ in range(20))


def test_the_final_stop_gives_the_named_child_its_longer_grace():
    """The run's final stop: SIGTERM to every child; the recorder (its file's end at stake)
    may take the longer grace it is given, another child is killed after the common one.
    Both take 1 s and 5 s to stop; the recorder's 1 s is within its 10 s, the other's 5 s
    beyond the common 0.3 s."""
    slow = ("import signal, sys, time\n"
            "signal.signal(signal.SIGTERM, lambda *a: (time.sleep(float(sys.argv[1])), sys.exit(0)))\n"
            "print('ready', flush=True)\n"
            "time.sleep(60)\n")
    children = Children()
    for name, takes in (("recorder", "1.0"), ("other", "5.0")):
        children.procs[name] = subprocess.Popen([sys.executable, "-c", slow, takes], stdout=subprocess.PIPE, text=True)
    try:
        assert all(p.stdout.readline().strip() == "ready" for p in children.procs.values())
        children.stop_all(grace=0.3, longer={"recorder": 10.0})
    finally:
        for p in children.procs.values():
            if p.poll() is None:
                p.kill()
            p.wait()
            p.stdout.close()
    assert children.forced == {"other"}
    assert children.procs["recorder"].returncode == 0 and children.procs["other"].returncode == -signal.SIGKILL
