"""``free_port``: the loopback ports the launcher and the tests listen on are drawn below
the kernel's ephemeral range, where no outgoing connection can take them between the
pick and the bind."""

from __future__ import annotations

import socket
from pathlib import Path

import services.launcher as launcher
from services.launcher import PORTS_FROM, free_port


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
