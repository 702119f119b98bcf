"""What every zfusion process has: a Zenoh session, a liveliness token, a status
publisher, a stop flag wired to SIGINT/SIGTERM, and counted, rate-limited rejections.

Lifetimes are explicit, as in the zenoh-python examples: a :class:`Node` is a context
manager; leaving it undeclares everything and closes the session (an open session can
hang the interpreter at exit).
"""

from __future__ import annotations

import json
import logging
import queue
import signal
import struct
import tempfile
import threading
import time
import math
from collections import Counter, deque
from dataclasses import dataclass, field
from typing import Any, Callable, Iterable

import zenoh
import zenoh.ext as zx

from schemas import KeySpace, encode

from .commands.options import split_override
from .logs import chatty, setup_logging  # noqa: F401  (setup_logging: where the benchmarks' rig takes it from)
from .resources import own_usage

log = logging.getLogger("zfusion")

LOOPBACK_LISTEN = "tcp/127.0.0.1:0"
HEARTBEAT_S = 0.5  # a recoverable publisher's heartbeat: how soon a subscriber sees what it missed
RECOVERED_LAG_S = 1.5  # a sample this much later than its source's usual lag was given back after a cut-off
KEYS_MAX = 4096  # distinct keys a ListenerInbox shares one string for (then it starts again)
SPILL_READ = 256  # samples a ListenerInbox reads back from its file at a time (held in memory meanwhile)
INBOX_BYTES = 64 * 2**20  # payload an Inbox holds at most (class docstring)
SPILL_HEADER = struct.Struct("<HI")  # a spilled sample: key length, payload length, then both
LINK_WARN_S = 5.0  # a process whose endpoints none answers says so after this long
STATUS_LINE_S = 60.0  # a chatty process's one-line status (logs.chatty), at most this often


@dataclass
class ZenohOptions:
    """How a process joins the fabric.

    Default: a Zenoh *peer* on loopback with multicast scouting off, so that test runs
    on one machine never see each other. ``connect`` lists endpoints to dial (the
    launcher's hub, a router, another peer); ``config_file`` starts from a Zenoh JSON5
    configuration instead (TLS, access control, client mode, ...; see ``deploy/zenoh/``),
    in which ``connect`` and ``mode``, when given, replace the file's values.
    ``overrides`` (``KEY=JSON5``, e.g. a process's own TLS certificate) are applied last,
    so that one file serves every process of a site.
    """

    connect: list[str] = field(default_factory=list)
    listen: list[str] = field(default_factory=lambda: [LOOPBACK_LISTEN])
    config_file: str | None = None
    mode: str | None = None  # None: the config file's, else "peer"
    overrides: list[str] = field(default_factory=list)

    def to_config(self) -> zenoh.Config:
        if self.config_file:
            c = zenoh.Config.from_file(self.config_file)
            if self.mode:
                c.insert_json5("mode", json.dumps(self.mode))
            if self.connect:
                c.insert_json5("connect/endpoints", json.dumps(self.connect))
        else:
            mode = self.mode or "peer"
            c = zenoh.Config()
            c.insert_json5("mode", json.dumps(mode))
            # A client only dials out: everything it says goes through its router.
            c.insert_json5("listen/endpoints", json.dumps(self.listen if mode != "client" else []))
            c.insert_json5("connect/endpoints", json.dumps(self.connect))
            c.insert_json5("scouting/multicast/enabled", "false")
        for item in self.overrides:
            key, value = split_override(item)
            try:
                c.insert_json5(key, value)
            except zenoh.ZError:  # not JSON5: a bare word, e.g. a file path, is meant as a string
                try:
                    c.insert_json5(key, json.dumps(value))
                except zenoh.ZError as e:
                    raise ValueError(f"Zenoh config: cannot set {key} to {value}: {e}") from None
        return c

    def to_args(self) -> list[str]:
        """Command-line form, for the launcher to hand down to its children."""
        args = ["--zenoh-config", self.config_file] if self.config_file else []
        args += [a for e in self.connect for a in ("--connect", e)]
        args += ["--zenoh-mode", self.mode] if self.mode else []
        return args + [a for o in self.overrides for a in ("--zenoh-set", o)]


class Stopped(Exception):
    """The process was told to stop (SIGINT/SIGTERM) while it waited (:meth:`Node.wait_for`):
    a clean end, not a failure."""


class Inbox:
    """The bounded hand-over from Zenoh's callbacks to a process's loop: ``(key, bytes)``,
    at most ``maxsize`` samples and ``max_bytes`` of payload (a sample larger than that
    alone is let into an empty inbox, for the loop to refuse).

    When it is full the callback waits (until there is room, or the process stops)
    instead of dropping: Zenoh then stops reading that link, and publishers with
    blocking congestion control slow down, so data on the fusion path is never lost to
    a burst and memory stays bounded. ``waits`` counts the times a callback had to wait.
    The byte bound matters for hostile input only: 65,536 real measurements are ~20 MB,
    65,536 messages just under the schema's 1 MiB limit would be 64 GiB.
    (Zenoh's own ``handlers.FifoChannel`` blocks the same way, but it is one channel per
    subscriber and counts samples only: a process's loop waits on all its subscriptions
    at once, in arrival order, and must wake when the process is told to stop.)
    """

    def __init__(self, stop: threading.Event, maxsize: int = 65_536, max_bytes: int = INBOX_BYTES):
        self._items: deque[tuple[str, bytes]] = deque()
        self._bytes = 0
        self._ready = threading.Condition()
        self._stop = stop
        self.maxsize = maxsize
        self.max_bytes = max_bytes
        self.waits = 0

    def __call__(self, sample: zenoh.Sample) -> None:
        item = (str(sample.key_expr), sample.payload.to_bytes())
        with self._ready:
            while len(self._items) >= self.maxsize or (self._items and self._bytes + len(item[1]) > self.max_bytes):
                if self._stop.is_set():
                    return
                self.waits += 1
                self._ready.wait(0.1)
            if self._stop.is_set():
                return
            self._items.append(item)
            self._bytes += len(item[1])
            self._ready.notify_all()

    def get(self, timeout: float) -> tuple[str, bytes]:
        deadline = time.monotonic() + timeout
        with self._ready:
            while not self._items:
                left = deadline - time.monotonic()
                if left <= 0:
                    raise queue.Empty
                self._ready.wait(left)
            return self._pop()

    def get_nowait(self) -> tuple[str, bytes]:
        with self._ready:
            if not self._items:
                raise queue.Empty
            return self._pop()

    def _pop(self) -> tuple[str, bytes]:
        item = self._items.popleft()
        self._bytes -= len(item[1])
        self._ready.notify_all()
        return item

    def qsize(self) -> int:
        return len(self._items)


class ListenerInbox:
    """The hand-over from Zenoh's callbacks to a listener's loop (recorder, exporters):
    ``(key, bytes)``, at most ``maxsize`` queued. Unlike :class:`Inbox` it never waits:
    when full, a sample is dropped and counted in :attr:`dropped`, so a listener that
    falls behind never slows a publisher.

    With ``in_memory``, at most that many samples are held in memory: the rest of the
    backlog waits in an unnamed temporary file (:func:`tempfile.TemporaryFile`), in
    arrival order, and is read back ``SPILL_READ`` samples at a time. A listener far
    behind (a recorder at ``--speed max``) then holds its backlog on disk, not in its
    resident memory, and still loses nothing up to ``maxsize``. Order: the samples in
    memory are older than the spilled ones (a sample is spilled only once memory is full,
    and every later one too until the file is read to its end).
    """

    def __init__(self, maxsize: int, in_memory: int | None = None):
        self._queue: queue.Queue[tuple[str, bytes]] = queue.Queue(in_memory or maxsize)
        self._lock = threading.Lock()
        self._keys: dict[str, str] = {}  # one string per key: a backlog holds a key per sample
        self.maxsize = maxsize
        self.in_memory = in_memory
        self._spill: Any = None  # the temporary file, opened on the first spill
        self._spilled = 0  # samples in the file not read back yet
        self._wpos = self._rpos = 0
        self._out: deque[tuple[str, bytes]] = deque()  # read back from the file, not handed out yet
        self.dropped = 0

    def put(self, item: tuple[str, bytes]) -> None:  # Zenoh's thread: never blocks, never raises
        with self._lock:
            if not self._spilled:
                try:
                    self._queue.put_nowait(item)
                    return
                except queue.Full:
                    pass
            if self.in_memory is None or self.qsize() >= self.maxsize:
                self.dropped += 1
                return
            try:
                key = item[0].encode()
                if self._spill is None:
                    self._spill = tempfile.TemporaryFile()
                self._spill.seek(self._wpos)
                self._spill.write(SPILL_HEADER.pack(len(key), len(item[1])) + key + item[1])
                self._wpos = self._spill.tell()
                self._spilled += 1
            except OSError:  # no room on disk: counted as dropped, like a full inbox
                self.dropped += 1

    def _read_back(self) -> None:
        with self._lock:
            if not self._spilled:
                return
            self._spill.seek(self._rpos)
            for _ in range(min(SPILL_READ, self._spilled)):
                nk, nd = SPILL_HEADER.unpack(self._spill.read(SPILL_HEADER.size))
                body = self._spill.read(nk + nd)
                key = body[:nk].decode()
                self._out.append((self._keys.setdefault(key, key), body[nk:]))
                self._spilled -= 1
            self._rpos = self._spill.tell()
            if not self._spilled:  # read to its end: the file starts again (and gives its blocks back)
                self._rpos = self._wpos = 0
                self._spill.truncate(0)

    def __call__(self, sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        if len(self._keys) >= KEYS_MAX:
            self._keys.clear()
        self.put((self._keys.setdefault(key, key), sample.payload.to_bytes()))

    def get(self, timeout: float) -> tuple[str, bytes]:
        if self._out:  # (older than anything in memory now: see the class docstring)
            return self._out.popleft()
        try:
            return self._queue.get(timeout=0.0 if self._spilled else timeout)
        except queue.Empty:
            self._read_back()
            if not self._out:
                raise
            return self._out.popleft()

    def get_nowait(self) -> tuple[str, bytes]:
        return self.get(0.0)

    def empty(self) -> bool:
        return self.qsize() == 0

    def qsize(self) -> int:
        return self._queue.qsize() + self._spilled + len(self._out)

    def close(self) -> None:
        if self._spill is not None:
            self._spill.close()


class Recovery:
    """Per source, what a :meth:`Node.recovering_subscriber` got back after a cut-off
    (``recovered``) and what the publisher's cache no longer held (``missed``, told by
    Zenoh through :meth:`on_miss`). A sample is taken for recovered when it arrives
    more than ``RECOVERED_LAG_S`` later than the least lag (``utc`` of arrival minus
    its time of validity) of its source so far: given back on reconnection, it was held
    for the outage. ``sessions``: Zenoh session id -> process id (liveliness), to name
    the source of a miss. Bounded: one entry per source, at most 1,024 misses queued."""

    def __init__(self, sessions: dict[str, str], margin: float = RECOVERED_LAG_S):
        self.sessions = sessions
        self.margin = margin
        self._misses: deque[tuple[str, int]] = deque(maxlen=1024)
        self._least: dict[str, float] = {}
        self.recovered: Counter[str] = Counter()
        self.missed: Counter[str] = Counter()

    def on_miss(self, zid: str, n: int) -> None:  # Zenoh's thread
        self._misses.append((zid, n))

    def arrived(self, src: str, t: float, utc: float) -> None:
        lag = utc - t
        least = self._least.get(src, math.inf)
        if lag > least + self.margin:
            self.recovered[src] += 1
        self._least[src] = min(least, lag)

    def take_misses(self) -> list[tuple[str, int]]:
        """The misses told since the last call, as (source, samples), counted in ``missed``;
        a source is named by its process id, or its session id if liveliness has not
        named it yet."""
        out = []
        while self._misses:
            zid, n = self._misses.popleft()
            src = self.sessions.get(zid, zid)
            self.missed[src] += n
            out.append((src, n))
        return out

    def counters(self) -> dict[str, float]:
        """``recovered``, ``missed`` and the same per source (``recovered.<src>``), for a status."""
        self.take_misses()
        out: dict[str, float] = {"recovered": sum(self.recovered.values()), "missed": sum(self.missed.values())}
        out.update({f"recovered.{s}": n for s, n in self.recovered.items()})
        out.update({f"missed.{s}": n for s, n in self.missed.items()})
        return out


def _endpoints(config: zenoh.Config) -> list[str]:
    """The endpoints a session dials (its configuration's ``connect/endpoints``)."""
    try:
        endpoints = json.loads(config.get_json("connect/endpoints"))
    except (zenoh.ZError, ValueError, TypeError):
        return []
    if isinstance(endpoints, dict):  # per mode: {"router": [...], "peer": [...], "client": [...]}
        endpoints = [e for es in endpoints.values() for e in es]
    return [str(e) for e in endpoints]


STATUS_SHOWN = ("received", "processed", "published", "recorded", "late", "rejected", "dropped")


def status_line(state: str, counters: dict[str, float]) -> str:
    """``running: received 1200, published 1187, rejected 13 (late 9, stale 4)``."""
    shown = [f"{name} {counters[name]:g}" for name in STATUS_SHOWN if counters.get(name)]
    causes = {k.split(".", 1)[1]: n for k, n in counters.items() if k.startswith("rejected.") and n}
    if causes and counters.get("rejected"):
        i = next(i for i, text in enumerate(shown) if text.startswith("rejected "))
        shown[i] += " (" + ", ".join(f"{c} {n:g}" for c, n in sorted(causes.items())) + ")"
    return f"{state}: " + (", ".join(shown) if shown else "nothing yet")


class RejectLog:
    """Counts rejected messages by (source, cause); logs the first of each pair, then
    at most one summary line per ``interval`` seconds, so garbage cannot flood logs.

    Source names come off the wire (a key's last segment), so an attacker can invent any
    number of them: beyond ``max_sources`` distinct names, further ones are counted
    together under :attr:`OTHER`, and memory stays bounded."""

    OTHER = "(other sources)"

    def __init__(self, process: str, interval: float = 10.0, clock: Callable[[], float] = time.monotonic,
                 max_sources: int = 256):
        self.process = process
        self.max_sources = max_sources
        self._sources: set[str] = set()
        self.by_cause: Counter[str] = Counter()
        self.by_pair: Counter[tuple[str, str]] = Counter()
        self._interval = interval
        self._clock = clock
        self._last_summary = clock()
        self._since_summary = 0

    def __call__(self, src: str, cause: str, detail: str) -> None:
        if src not in self._sources:
            if len(self._sources) >= self.max_sources:
                src = self.OTHER
            else:
                self._sources.add(src)
        self.by_cause[cause] += 1
        self.by_pair[(src, cause)] += 1
        if self.by_pair[(src, cause)] == 1:
            log.warning("%s: dropped message from %s: %s", self.process, src, detail)
            return
        log.debug("%s: dropped message from %s: %s", self.process, src, detail)
        self._since_summary += 1
        now = self._clock()
        if now - self._last_summary >= self._interval:
            log.warning("%s: %d more messages dropped in the last %.0f s (totals by cause: %s)", self.process,
                        self._since_summary, now - self._last_summary, dict(self.by_cause))
            self._since_summary = 0
            self._last_summary = now

    @property
    def total(self) -> int:
        return sum(self.by_cause.values())

    def rejected_by_source(self) -> dict[str, int]:
        out: Counter[str] = Counter()
        for (src, _), n in self.by_pair.items():
            out[src] += n
        return dict(out)


class Node:
    """A zfusion process on the fabric. ``live``: a process of a live session (or a
    gateway), whose time base is UTC (:meth:`publish_status`)."""

    def __init__(self, process_id: str, role: str, keys: KeySpace, zopts: ZenohOptions, live: bool = False):
        self.id = process_id
        self.role = role
        self.keys = keys
        self.zopts = zopts
        self.live = live
        self.stop = threading.Event()
        self.counters: dict[str, float] = {}
        self.events: list[str] = []
        self.reject = RejectLog(process_id)
        self._status_seq = 0
        self._declared: list[Any] = []
        self.session: zenoh.Session | None = None
        self._status_line_at = time.monotonic()
        self._link_lock = threading.Lock()
        self._link_told = False  # whether the link's line was printed (or is no more to be)
        self._link_where: str | None = None  # the endpoints it dials or listens on, if any

    # -- lifetime ---------------------------------------------------------------------

    def __enter__(self) -> "Node":
        self.install_signal_handlers()
        config = self.zopts.to_config()
        self.session = zenoh.open(config)
        self._status_pub = self.publisher(self.keys.status(self.id), reliable=False)
        endpoints = _endpoints(config)
        if endpoints:
            self._link_where = ", ".join(endpoints)
            threading.Thread(target=self._watch_link, args=(self.session, self._link_where), daemon=True,
                             name=f"link-{self.id}").start()
        return self

    def _watch_link(self, session: zenoh.Session, where: str) -> None:
        """One line once the session reaches a peer or router (on a terminal or with
        ``-v``), a warning if none has answered after ``LINK_WARN_S``; Zenoh keeps
        dialling meanwhile, so the process goes on and says when it connects."""
        deadline = time.monotonic() + LINK_WARN_S
        warned = False
        while not self.stop.wait(0.1):
            linked = self._tell_link(session, where, warned)
            if linked is None or linked:
                return
            if not warned and time.monotonic() >= deadline:
                log.warning("%s: cannot reach %s: nothing answered in %.0f s (is a zfusion session or a Zenoh "
                            "router listening there?); still trying", self.id, where, LINK_WARN_S)
                warned = True

    def _tell_link(self, session: zenoh.Session, where: str, warned: bool = False) -> bool | None:
        """Print the link's line once it is up (True), not yet (False); None: no more to tell."""
        with self._link_lock:
            if self._link_told or self.session is not session:
                return None
            try:
                linked = any(True for _ in session.info.routers_zid()) or any(True for _ in session.info.peers_zid())
            except Exception:  # closed meanwhile: nothing left to watch
                return None
            if linked:
                self._link_told = True
                if warned or chatty():
                    log.log(logging.WARNING if warned else logging.INFO, "%s: connected to %s", self.id, where)
            return linked

    def settle_link(self) -> None:
        """Before a process's last words: its link's line now if it is up, else never —
        never after them."""
        if self.session is not None and self._link_where is not None:
            self._tell_link(self.session, self._link_where)
        with self._link_lock:
            self._link_told = True

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        if self.session is None:
            return
        for d in reversed(self._declared):
            try:
                d.undeclare()
            except Exception:  # already gone with a broken session: nothing left to free
                pass
        self._declared.clear()
        self.session.close()
        self.session = None

    def install_signal_handlers(self) -> None:
        if threading.current_thread() is not threading.main_thread():
            return

        def on_signal(signum: int, _frame: object) -> None:
            if self.stop.is_set():  # second signal: the user means it
                raise KeyboardInterrupt
            log.info("%s: %s received, stopping", self.id, signal.Signals(signum).name)
            self.stop.set()

        signal.signal(signal.SIGINT, on_signal)
        signal.signal(signal.SIGTERM, on_signal)

    # -- declarations -------------------------------------------------------------------

    def publisher(self, key: str, reliable: bool = True) -> zenoh.Publisher:
        """Fusion-path publishers are reliable and block under congestion (nothing is lost
        silently); status and recording traffic may be dropped under load."""
        if reliable:
            pub = self.session.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK,
                                                 reliability=zenoh.Reliability.RELIABLE)
        else:
            pub = self.session.declare_publisher(key, congestion_control=zenoh.CongestionControl.DROP)
        self._declared.append(pub)
        return pub

    def recoverable_publisher(self, key: str, cache: int) -> Any:
        """A fusion-path publisher whose last ``cache`` samples a subscriber that missed
        them (a router down or restarting) gets back once it hears the publisher's
        heartbeat again (Zenoh's advanced publisher: cache, sample-miss detection)."""
        pub = zx.declare_advanced_publisher(
            self.session, key, congestion_control=zenoh.CongestionControl.BLOCK,
            reliability=zenoh.Reliability.RELIABLE, cache=zx.CacheConfig(cache),
            sample_miss_detection=zx.MissDetectionConfig(heartbeat=HEARTBEAT_S, sporadic_heartbeat=None),
            publisher_detection=True)
        self._declared.append(pub)
        return pub

    def recovering_subscriber(self, key: str, callback: Callable[[zenoh.Sample], None],
                              on_miss: Callable[[str, int], None], history: bool = False) -> Any:
        """A subscriber that recovers what a :meth:`recoverable_publisher` sent while the
        two were cut off (delivered in order, through ``callback``), and calls
        ``on_miss(zid, n)`` on Zenoh's thread for ``n`` samples of the publisher of
        session ``zid`` that its cache no longer held. ``history``: first get what the
        publishers' caches hold now (a process joining a stream mid-way, which needs what
        was sent just before it subscribed)."""
        sub = zx.declare_advanced_subscriber(self.session, key, callback,
                                             history=zx.HistoryConfig() if history else None,
                                             recovery=zx.RecoveryConfig(periodic_queries=None, heartbeat=True))
        self._declared.append(sub)
        self._declared.append(sub.sample_miss_listener(lambda m: on_miss(str(m.source.zid), int(m.nb))))
        return sub

    def processes_by_session(self) -> dict[str, str]:
        """Session id -> process id of every process alive, kept up to date (liveliness)."""
        out: dict[str, str] = {}

        def on_token(sample: zenoh.Sample) -> None:
            try:
                process, zid = self.keys.alive_process(str(sample.key_expr))
            except ValueError:
                return
            if sample.kind == zenoh.SampleKind.PUT and len(out) < 4096:
                out[zid] = process

        self._declared.append(self.session.liveliness().declare_subscriber(self.keys.all("alive"), on_token,
                                                                           history=True))
        return out

    def keep(self, declaration: Any) -> Any:
        """Undeclare ``declaration`` (a queryable, ...) with the rest when the node closes."""
        self._declared.append(declaration)
        return declaration

    def subscribe(self, key: str, callback: Callable[[zenoh.Sample], None]) -> zenoh.Subscriber:
        sub = self.session.declare_subscriber(key, callback)
        self._declared.append(sub)
        return sub

    def announce(self) -> None:
        """Declare this process alive (after its subscribers, so a peer that sees the
        token knows they are declared)."""
        self._declared.append(self.session.liveliness().declare_token(
            self.keys.alive(self.id, str(self.session.zid()))))

    def wait_for(self, process_ids: Iterable[str], timeout: float,
                 gone: Callable[[], str | None] | None = None) -> None:
        """Block until every named process has announced itself. Raises
        :class:`Stopped` if the process is told to stop meanwhile, ``TimeoutError`` past
        ``timeout`` or when ``gone``, asked as it waits, gives a text saying that a process
        it waits for has exited (it will not announce itself)."""
        wanted = set(process_ids)
        if not wanted:
            return
        seen: set[str] = set()
        cond = threading.Condition()

        def on_token(sample: zenoh.Sample) -> None:
            if sample.kind == zenoh.SampleKind.PUT:
                with cond:
                    seen.add(self.keys.alive_process(str(sample.key_expr))[0])
                    cond.notify_all()

        sub = self.session.liveliness().declare_subscriber(self.keys.all("alive"), on_token, history=True)
        try:
            deadline = time.monotonic() + timeout
            with cond:
                while not wanted <= seen:
                    left = deadline - time.monotonic()
                    if self.stop.is_set():
                        raise Stopped(f"{self.id}: stopped while waiting for {', '.join(sorted(wanted - seen))}")
                    if left <= 0:
                        raise TimeoutError(f"{self.id}: gave up after {timeout:.0f} s waiting for "
                                           f"{', '.join(sorted(wanted - seen))}")
                    why = gone() if gone is not None else None
                    if why:
                        raise TimeoutError(f"{self.id}: stopped waiting for {', '.join(sorted(wanted - seen))}: {why}")
                    cond.wait(min(left, 0.1))
        finally:
            sub.undeclare()

    # -- status ---------------------------------------------------------------------------

    def count(self, name: str, n: int = 1) -> None:
        self.counters[name] = self.counters.get(name, 0) + n

    def event(self, text: str) -> None:
        log.info("%s: %s", self.id, text)
        self.events.append(text)

    def publish_status(self, state: str, t: float = 0.0, extra: dict[str, float] | None = None,
                       sources: dict | None = None) -> None:
        """The process's state and counters on ``status/<id>``, stamped with ``t``, the
        scenario time it has reached (0: none yet); a live process's with this host's UTC
        clock, when it is said (``t`` is 0 there too before any data: 1970 on a live
        recording's timeline)."""
        if self.live:
            t = time.time()
        counters = {**self.counters, **{f"rejected.{c}": n for c, n in self.reject.by_cause.items()}}
        counters["rejected"] = self.reject.total
        counters.update(own_usage())  # cpu_s, max_rss_mb: for the run summary's processes
        if extra:
            counters.update(extra)
        events, self.events = self.events, []
        self._status_seq += 1
        if chatty() and time.monotonic() - self._status_line_at >= STATUS_LINE_S:
            self._status_line_at = time.monotonic()
            log.info("%s: %s", self.id, status_line(state, counters))
        self._status_pub.put(encode("status", self.id, self._status_seq, t, state=state, role=self.role,
                                    counters=counters, events=events, sources=sources or {}))

