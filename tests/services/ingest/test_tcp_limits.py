"""A TCP jsonl input holds at most MAX_CONNECTIONS connections at once (more are closed
at once and counted) and closes one silent for IDLE_S (counted): 200 idle connections
once held 211 threads. Driven on the reader itself, on a loopback port."""

from __future__ import annotations

import queue
import socket
import threading
import time

import pytest

from services.ingest import process
from services.launcher import free_port

from conftest import wait_for


@pytest.fixture
def reader():
    stop = threading.Event()
    port = free_port()
    r = process._Reader("tcp", ("127.0.0.1", port), queue.Queue(1000), stop)
    r.start()
    yield r, port
    stop.set()
    r.close()
    r.thread.join(5)


def _closed_by_peer(s: socket.socket, timeout: float = 10.0) -> bool:
    s.settimeout(timeout)
    try:
        return s.recv(1) == b""
    except ConnectionResetError:
        return True
    except socket.timeout:
        return False


def test_connections_beyond_the_cap_are_closed_and_counted(reader):
    r, port = reader
    held = []
    try:
        for _ in range(process.MAX_CONNECTIONS):
            held.append(socket.create_connection(("127.0.0.1", port)))
        wait_for(lambda: r.counts["connections"] == process.MAX_CONNECTIONS, "every connection up to the cap taken")
        extra = socket.create_connection(("127.0.0.1", port))
        assert _closed_by_peer(extra)
        assert r.counts["refused_connections"] == 1
        extra.close()
        held.pop().close()  # one leaves: a new one is taken again, and its lines are read
        wait_for(lambda: len(r._drained) == process.MAX_CONNECTIONS - 1, "the closed connection forgotten")
        late = socket.create_connection(("127.0.0.1", port))
        held.append(late)
        late.sendall(b'{"a": 1}\n')
        assert r.inbox.get(timeout=10) == b'{"a": 1}'
        assert r.counts == {"connections": process.MAX_CONNECTIONS + 1, "refused_connections": 1, "idle_closed": 0}
        assert threading.active_count() < process.MAX_CONNECTIONS + 20  # a thread per connection held, no more
    finally:
        for s in held:
            s.close()


def test_a_silent_connection_is_closed_after_idle_s(reader, monkeypatch):
    monkeypatch.setattr(process, "IDLE_S", 0.5)
    r, port = reader
    with socket.create_connection(("127.0.0.1", port)) as quiet, socket.create_connection(("127.0.0.1", port)) as chatty:
        deadline = time.monotonic() + 2.0
        while time.monotonic() < deadline:  # one keeps talking, one says nothing
            chatty.sendall(b"{}\n")
            time.sleep(0.1)
        assert _closed_by_peer(quiet, 5.0)
        assert r.counts["idle_closed"] == 1
        chatty.sendall(b'{"still": true}\n')
        wait_for(lambda: b'{"still": true}' in list(r.inbox.queue), "the talking connection still read")


def test_a_udp_input_closed_as_its_read_times_out_ends_quietly():
    """The stop's race, made certain: the gateway's stop closes the UDP socket just as the
    reader's ``recv`` times out, and the reader then reads the kernel's drop count of a
    closed socket. It ended its thread with ``OSError: Bad file descriptor`` and a traceback
    on stderr (ci26: two gateway tests); now the count read before stands and it ends."""
    stop = threading.Event()
    r = process._Reader("udp", ("127.0.0.1", free_port()), queue.Queue(10), stop)
    real = r.sock
    r.counts["udp_dropped"] = 7

    class ClosedOnTimeout:  # recv: the stop closes the socket, then the read times out
        family = real.family

        def recv(self, n):
            stop.set()
            real.close()
            raise socket.timeout

        def fileno(self):
            return real.fileno()

    r.sock = ClosedOnTimeout()
    r._udp()  # on this thread: an exception would fail the test
    assert r.counts["udp_dropped"] == 7
