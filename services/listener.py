"""A process that only listens: the recorder and every exporter are sinks of one loop.

:func:`run_listener` is the whole process around a :class:`Sink`: it joins Zenoh
(:class:`~services.node.Node`), subscribes to its keys into a bounded inbox that never
pushes back on a publisher (:class:`~services.node.ListenerInbox`: overflow is counted
as ``dropped``), and, live, through a recovering subscriber that gets back what the
fuser's and sources' publishers sent while it was cut off (``recovered``, ``missed``:
:class:`~services.node.Recovery`). A listener that starts (or restarts) mid-session
begins with the fuser's current picture (:class:`services.picture.Request`, ``picture``
tracks), which it stops asking for once ``fused`` itself arrives. The loop hands each
sample to the sink (up to ``BURST_MAX`` between two ticks, so a sustained stream still
gets its periodic work done), lets the sink do that work, says what the sink's clock
guard said, and publishes the status once a second (the sink's counters, ``dropped``,
``backlog``, ``picture``, recovery). It ends when the sink is done (the recorder's
``--expect``) or on SIGINT/SIGTERM, after handing the sink what is still queued (for at
most ``STOP_DRAIN_S``) and a last tick; the status then says ``done`` or ``stopped``,
and the session closes.
"""

from __future__ import annotations

import queue
import time
from typing import Callable, Protocol

from schemas import KeySpace, Message

from .node import ListenerInbox, Node, Recovery, ZenohOptions
from .picture import Request

BURST_MAX = 1_000  # samples handled between two ticks
STATUS_PERIOD_S = 1.0
STOP_DRAIN_S = 0.5  # what is queued at a stop is still handed to the sink, for at most this long


class Sink(Protocol):
    """What a listener does with what it hears."""

    events: list[str]  # what it has to say (a source's clock), said and cleared by the loop

    def offer(self, key: str, data: bytes, utc: float | None) -> Message | None:
        """A sample off the wire; the message if it was taken (never raises)."""

    def tick(self, final: bool = False) -> None:
        """Periodic work (``final``: the process is stopping)."""

    def done(self) -> bool:
        """Whether it has heard all it waits for (then the process ends once its inbox is empty)."""

    def now(self) -> float:
        """The time its status is stamped with."""

    def counters(self) -> dict[str, float]:
        """What its status says beside the listener's own counters."""

    def close(self) -> None:
        """Release what it holds (a file, a socket): called once, last."""


def run_listener(process_id: str, role: str, keys: KeySpace, zopts: ZenohOptions, make_sink: Callable[[Node], Sink],
                 *, subscribe: str, fuser: str, live: bool, backlog: int, in_memory: int | None = None,
                 counted: str = "taken") -> int:
    """Run the listener ``process_id`` until its sink is done or it is told to stop.

    Args:
        make_sink: builds the sink once the session is open and SIGINT/SIGTERM are handled
            (so a stop at any time leaves its output whole, and a sink that cannot be
            built is an error at start).
        subscribe: the key expression it listens to.
        fuser: the fuser whose tracks it takes (and whose picture it asks for at the start).
        live: a live session: a recovering subscriber, and its clock is UTC.
        backlog, in_memory: the inbox's bounds (:class:`~services.node.ListenerInbox`).
        counted: the status counter of the samples the sink took.
    """
    inbox = ListenerInbox(backlog, in_memory)
    utc = time.time if live else (lambda: None)
    try:
        with Node(process_id, role, keys, zopts, live=live) as node:
            sink = make_sink(node)
            try:
                recovery = Recovery(node.processes_by_session()) if live else None
                if recovery is not None:
                    node.recovering_subscriber(subscribe, inbox, recovery.on_miss)
                else:
                    node.subscribe(subscribe, inbox)
                fused = keys.fused(fuser)
                late_join = Request(node.session, keys, fuser, lambda data: inbox.put((fused, data)))

                def handle(key: str, data: bytes) -> None:
                    if key == fused:
                        late_join.cancel()  # the fuser's own stream: its picture is coming anyway
                    msg = sink.offer(key, data, utc())
                    if msg is not None:
                        node.count(counted)
                        if recovery is not None and msg.kind != "status":
                            recovery.arrived(msg.src, msg.t, utc())

                def status(state: str) -> None:
                    for ev in sink.events:
                        node.event(ev)
                    sink.events.clear()
                    node.counters.update(sink.counters(), dropped=inbox.dropped, backlog=inbox.qsize(),
                                         picture=late_join.tracks,
                                         **(recovery.counters() if recovery is not None else {}))
                    node.publish_status(state, sink.now())

                node.announce()
                node.publish_status("ready")
                last_status = time.monotonic()
                while not node.stop.is_set():
                    try:
                        handle(*inbox.get(timeout=0.1))
                        for _ in range(BURST_MAX):  # the rest of a burst, then one tick
                            handle(*inbox.get_nowait())
                    except queue.Empty:
                        pass
                    late_join.poll()
                    sink.tick()
                    if sink.done() and inbox.empty():
                        break
                    if time.monotonic() - last_status >= STATUS_PERIOD_S:
                        status("running")
                        last_status = time.monotonic()
                finished = not node.stop.is_set()
                until = time.monotonic() + STOP_DRAIN_S
                while not finished and time.monotonic() < until:  # stopping: what is queued is still heard
                    try:
                        handle(*inbox.get_nowait())
                    except queue.Empty:
                        break
                sink.tick(final=True)
                status("done" if finished else "stopped")
            finally:
                sink.close()
    finally:
        inbox.close()
    return 0
