"""services.node's listener inbox: a backlog beyond what it holds in memory waits in a
file, handed out in arrival order, nothing lost up to its bound, its memory bounded."""

from __future__ import annotations

import queue
import threading
import time
import tracemalloc

import pytest

from schemas import KeySpace
from services.launcher import free_port
from services.node import ListenerInbox, Node, Stopped, ZenohOptions

PAYLOAD = 1_000


def _samples(n: int) -> list[tuple[str, bytes]]:
    return [(f"zf/test/meas/s{k % 5}", k.to_bytes(4, "little") * (PAYLOAD // 4 + k % 3)) for k in range(n)]


def _drain(inbox: ListenerInbox, producer: threading.Thread) -> list[tuple[str, bytes]]:
    out = []
    while producer.is_alive() or not inbox.empty():
        try:
            out.append(inbox.get(0.01))
        except queue.Empty:
            pass
    return out


def test_a_backlog_beyond_memory_waits_on_disk_in_order_and_memory_stays_bounded():
    n, extra, in_memory = 20_000, 5_000, 64  # 20 MB of samples queued at once, 64 of them in memory
    samples = _samples(n)
    inbox = ListenerInbox(n + extra, in_memory)  # room for all: the producer may outrun the reader
    tracemalloc.start()
    base = tracemalloc.get_traced_memory()[0]
    for s in samples:  # all of it before the listener reads anything (a recorder far behind)
        inbox.put(s)
    held = tracemalloc.get_traced_memory()[1] - base
    assert inbox.qsize() == n and inbox.dropped == 0
    assert held < n * PAYLOAD / 20  # in memory: a few hundred samples' worth, not the backlog
    # then read while a producer keeps putting (Zenoh's thread): memory first, then the file, then memory again
    more = _samples(n + extra)[n:]
    producer = threading.Thread(target=lambda: [inbox.put(s) for s in more])
    first = [inbox.get(0.0) for _ in range(100)]
    producer.start()
    got = first + _drain(inbox, producer)
    tracemalloc.stop()
    inbox.close()
    assert inbox.dropped == 0
    assert got == samples + more


def test_beyond_its_bound_the_inbox_drops_and_counts_what_it_cannot_hold():
    samples = _samples(500)
    for in_memory in (None, 16):  # in memory only, and with a file
        inbox = ListenerInbox(300, in_memory)
        for s in samples:
            inbox.put(s)
        assert inbox.dropped == 200 and inbox.qsize() == 300
        assert [inbox.get(0.0) for _ in range(300)] == samples[:300]
        assert inbox.empty()
        try:
            inbox.get(0.0)
        except queue.Empty:
            pass
        else:
            raise AssertionError("an empty inbox handed out a sample")
        inbox.close()


def test_a_wait_told_to_stop_raises_stopped_and_one_that_times_out_timeout_error():
    """``Node.wait_for``: a stop (SIGINT/SIGTERM) while it waits is ``Stopped``, a clean
    end its callers do not report as a failure; past its timeout, ``TimeoutError``. (Both
    were TimeoutError, and each caller asked the stop event which one it was.)"""
    with Node("waiter", "test", KeySpace("twait"), ZenohOptions(listen=[f"tcp/127.0.0.1:{free_port()}"])) as node:
        t0 = time.monotonic()
        with pytest.raises(TimeoutError, match="gave up after"):
            node.wait_for(["nobody"], 0.3)
        assert 0.3 <= time.monotonic() - t0 < 5.0
        threading.Timer(0.2, node.stop.set).start()
        t0 = time.monotonic()
        with pytest.raises(Stopped):
            node.wait_for(["nobody"], 60.0)
        assert time.monotonic() - t0 < 5.0
