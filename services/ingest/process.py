"""The gateway processes: ``zfusion ingest krakensdr``, ``jsonl`` and ``asterix``.

Thin: they move bytes between a device and Zenoh. Parsing and checking are sans-I/O
(:mod:`.krakensdr`, :mod:`.jsonl`, :mod:`.gateway`). Lifetimes are explicit: the Zenoh
session is the :class:`services.node.Node` context; the HTTP server, sockets and
reader threads are closed before it. SIGINT/SIGTERM set the node's stop flag; every
loop waits on it, so the process exits within one poll or 0.2 s.

Inputs: ``krakensdr --url`` polls ``/DOA_value.html`` or ``/doa.xml`` every ``--poll-s``
(the ``--timeout-s`` bounds the whole answer, not each read: :func:`fetch`; an HTTP
error or timeout doubles the wait up to :data:`MAX_BACKOFF_S`, counted as
``http_errors`` and said once per cause in the status events; never a crash; no
heartbeat watermark while it lasts, so the reading fetched after it is not late);
``krakensdr --listen`` takes "Kraken Pro" JSON and "Full POST" form POSTs on any path;
``jsonl --input`` reads lines from stdin, UDP datagrams or TCP connections. Every input
lands in one bounded queue (:data:`QUEUE_SIZE` items; a POST that finds it full gets
503 and is counted as ``dropped``), read by the main loop, which owns the gateway.
"""

from __future__ import annotations

import http.client
import logging
import math
import os
import queue
import socket
import stat
import sys
import threading
import time
import urllib.error
import urllib.parse
import urllib.request
from dataclasses import dataclass
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import Callable

from schemas import KeySpace, SchemaError, decode
from sensors_sim import ScenarioError
from sensors_sim import load_site as load_site_file

from ..errors import UserError
from ..logs import chatty, utc_text
from ..node import Node, Stopped
from .adsb import AdsbReceiver, PositionReport, SbsClock, position_reading
from .asterix import AsterixFeed, AsterixIngest, CaptureError, pcap_datagrams, radars, stations
from .gateway import Gateway, Reading, Rejected, local_frame, sensor_sites
from .jsonl import MAX_LINE, LineSplitter, reading
from .krakensdr import MAX_BODY, Bearing, KrakenOptions, KrakenStation, Skipped

log = logging.getLogger("zfusion")

QUEUE_SIZE = 1024
TICK_S = 0.1  # heartbeat watermarks at most this often
MAX_CONNECTIONS = 64  # TCP connections a jsonl gateway reads at once
IDLE_S = 300.0  # a TCP connection silent this long is closed
MAX_BACKOFF_S = 30.0
WAIT_S = 60.0  # how long a gateway waits for the processes of --wait-for (as a sensor does)
PATHS = {"csv": "/DOA_value.html", "auto": "/DOA_value.html", "xml": "/doa.xml"}


@dataclass
class Backoff:
    """Wait between polls: ``base`` while the device answers, doubled after each failure
    up to ``cap``."""

    base: float
    cap: float = MAX_BACKOFF_S
    failures: int = 0

    def delay(self) -> float:
        return min(self.cap, self.base * 2.0 ** self.failures) if self.failures else self.base

    def failed(self) -> float:
        self.failures += 1
        return self.delay()

    def succeeded(self) -> None:
        self.failures = 0


# ------------------------------------------------------------------ shared plumbing


def gateway_cache(period: float, recovery: float) -> int:
    """Samples in ``recovery`` seconds (the site's ``recovery_s``) of a gateway's stream
    of one sensor, twice over: a reading and its watermark per nominal ``period``, and a
    heartbeat watermark per :data:`TICK_S` at most (:meth:`Outlet.tick`)."""
    return math.ceil(2.0 * recovery * (2.0 / period + 1.0 / TICK_S))


class NotHeard(Exception):
    """A process the gateway was told to wait for never announced itself."""


class Outlet:
    """Publishes what the gateway returns and reports status once a second.

    Each sensor's stream goes out on the advanced publisher emulated sensors use
    (:meth:`services.node.Node.recoverable_publisher`): a fuser cut off from the gateway
    (a router restarting) gets back the last :func:`gateway_cache` samples, the site's
    ``recovery`` seconds of it twice over, and counts them ``recovered``; what the cache no
    longer held, ``missed``."""

    def __init__(self, node: Node, gateway: Gateway, recovery: float, extra: Callable[[], dict] | None = None):
        self.node = node
        self.gateway = gateway
        self.extra = extra or dict
        self.pubs = {gateway.keys.meas(s): node.recoverable_publisher(gateway.keys.meas(s),
                                                                      gateway_cache(site.period, recovery))
                     for s, site in gateway.sensors.items()}
        self.skipped: dict[str, int] = {}
        self.adsb_sensor = next(iter(gateway.sensors), "")  # the receiver's id (an ADS-B gateway has one)
        self.t_last = 0.0
        self._last_status = 0.0
        self._last_beat = -math.inf
        self._said: set[str] = set()

    def put(self, out: list[tuple[str, bytes]]) -> None:
        for key, data in out:
            self.pubs[key].put(data)

    def offer(self, item, now: float) -> None:
        """A parsed item: a reading (or bearing) to check and publish, or a refusal."""
        if isinstance(item, Bearing):
            item = item.reading()
        elif isinstance(item, PositionReport):
            item = position_reading(item, self.adsb_sensor)
        if isinstance(item, Rejected):
            self.node.reject(self.node.id, item.cause, item.detail)
        elif isinstance(item, Skipped):
            self.skipped[item.cause] = self.skipped.get(item.cause, 0) + 1
        else:
            out = self.gateway.offer(item, now)
            self.put(out)
            self.t_last = max(self.t_last, item.t)
            if out and log.isEnabledFor(logging.DEBUG):  # -v: each reading published
                log.debug("%s: published %s of %s", self.node.id, item.kind, utc_text(item.t))

    def ready(self, wait_for: list[str], timeout: float = WAIT_S) -> None:
        """Announce the gateway, wait until each process of ``wait_for`` has announced
        itself, then say it is ready. A replay (``--pcap``, a file) publishes at once: what
        goes out before its consumers' subscribers are known to this session is lost to
        them. Raises :class:`NotHeard` (the status says stopped) if one never comes."""
        self.node.announce()
        if wait_for:
            self.status("starting", force=True)  # (as a sensor that waits says)
        try:
            self.node.wait_for(wait_for, timeout)
        except Stopped:  # the caller's loop ends at once
            return
        except TimeoutError as e:
            self.node.events.append(str(e))  # in the status; the line on stderr is main's
            self.status("stopped", force=True)
            raise NotHeard(str(e)) from None
        self.status("ready", force=True)

    def say_once(self, cause: str, text: str) -> None:
        if cause not in self._said:
            self._said.add(cause)
            self.node.event(text)

    def tick(self, now: float, heartbeat: bool = True, read_until: float = math.inf) -> None:
        """Heartbeat watermarks, at most every :data:`TICK_S`, at ``min(now, read_until) −
        lag``: never past what the input may still hold unread (``read_until``: when the
        reader last found it drained), nor while the device is unreachable (what it
        measures meanwhile may still be fetched); and the status once a second."""
        if heartbeat and now - self._last_beat >= TICK_S:
            self._last_beat = now
            self.put(self.gateway.tick(min(now, read_until)))
        self.status()

    def status(self, state: str = "running", force: bool = False) -> None:
        if force or time.monotonic() - self._last_status >= 1.0:
            self._last_status = time.monotonic()
            self.node.counters.update(self.gateway.counters)
            self.node.counters.update({f"skipped.{c}": n for c, n in self.skipped.items()})
            self.node.counters.update(self.extra())
            self.node.publish_status(state, self.t_last)
def _site_sensors(args, ids: list[str]):
    """The site's frame, these sensors and its recovery window (before any session is
    opened)."""
    for flag in ("max_skew", "max_age", "watermark_lag", "poll_s", "timeout_s"):
        v = getattr(args, flag, 1.0)
        if not (v >= 0 if flag == "watermark_lag" else v > 0) or v == float("inf"):
            raise UserError(f"--{flag.replace('_', '-')} must be a positive number of seconds, not {v}")
    site = load_site(args.site)
    try:
        return local_frame(site), sensor_sites(site, ids), site.recovery
    except ValueError as e:
        raise UserError(str(e)) from None


def _gateway(node: Node, args, frame, sensors) -> Gateway:
    return Gateway(sensors, frame, node.keys, node.reject, max_skew=args.max_skew, max_age=args.max_age,
                   lag=args.watermark_lag)


def load_site(path: str):
    """The site file (any scenario file is a site too)."""
    try:
        return load_site_file(path)
    except (ScenarioError, OSError, ValueError) as e:
        raise UserError(f"cannot read the site file: {e}") from None


# ------------------------------------------------------------------ krakensdr


def kraken_options(args) -> KrakenOptions:
    try:
        heading = args.heading if args.heading in ("message", "none") else float(args.heading)
    except ValueError:
        raise UserError(f"--heading {args.heading!r}: 'message', 'none' or a heading in degrees") from None
    vfos = tuple(f * 1e6 for f in args.vfo or ())
    return KrakenOptions(convention=args.doa, heading=heading, vfos=vfos, vfo_tol_hz=args.vfo_tol_khz * 1e3,
                         min_conf=args.min_conf, station=args.station)


def poll_url(url: str, fmt: str) -> str:
    u = urllib.parse.urlsplit(url)
    if u.scheme not in ("http", "https") or not u.netloc:
        raise UserError(f"--url {url!r}: expected http://HOST:PORT (the KrakenSDR's web server, port 8081)")
    if u.path in ("", "/"):
        if fmt not in PATHS:
            raise UserError(f"--format {fmt} is pushed, not polled: use --listen HOST:PORT")
        return urllib.parse.urlunsplit((u.scheme, u.netloc, PATHS[fmt], u.query, ""))
    return url


def run_krakensdr(args, keys: KeySpace, zopts) -> int:
    options = kraken_options(args)
    url = poll_url(args.url, args.format) if args.url else None
    listen = _host_port(args.listen, "--listen") if args.listen else None
    frame, sensors, recovery = _site_sensors(args, options.channel_ids(args.id))
    with Node(args.id, "ingest", keys, zopts, live=True) as node:
        gateway = _gateway(node, args, frame, sensors)
        station = KrakenStation(args.id, options)
        if url:
            fmt = "auto" if args.format == "auto" else args.format
            # The page is served as text/html whatever it holds: the content decides.
            return _poll(node, gateway, recovery, url, args,
                         lambda data, ctype: station.receive(data, fmt, None if "html" in (ctype or "") else ctype))
        return _listen(node, gateway, recovery, station, listen, args)


def _poll(node: Node, gateway: Gateway, recovery: float, url: str, args,
          receive: Callable[[bytes, str | None], list]) -> int:
    """Poll ``url`` every ``--poll-s``; ``receive(body, content_type)`` parses each answer
    into readings (or bearings, position reports) and refusals."""
    counts = {"polls": 0, "http_errors": 0}
    outlet = Outlet(node, gateway, recovery, lambda: counts)
    backoff = Backoff(args.poll_s)
    outlet.ready(args.wait_for)
    failing = False
    while not node.stop.is_set():
        counts["polls"] += 1
        try:
            got = fetch(url, args.timeout_s, node.stop)
            if got is None:  # told to stop mid-request
                break
            data, ctype = got
        except (urllib.error.URLError, http.client.HTTPException, OSError, ValueError) as e:
            counts["http_errors"] += 1
            cause = _http_cause(e)
            delay = backoff.failed()
            outlet.say_once(cause, f"{url}: {cause}; retrying with backoff (now {delay:g} s)")
            failing = True
        else:
            if failing:
                node.event(f"{url} answers again")
                failing = False
            backoff.succeeded()
            now = time.time()
            for item in receive(data, ctype):
                outlet.offer(item, now)
            delay = backoff.delay()
        outlet.tick(time.time(), heartbeat=not failing)
        node.stop.wait(delay)
    outlet.status("stopped", force=True)
    return 0


def fetch(url: str, timeout: float, stop: threading.Event) -> tuple[bytes, str | None] | None:
    """GET ``url``: its body (at most ``MAX_BODY + 1`` bytes) and Content-Type, whole
    within ``timeout`` seconds from the connect to the last byte; None if ``stop`` is set
    first. A device that trickles its answer (headers or body, a byte a second) is a
    ``timeout``, not a frozen gateway: a socket timeout bounds each read, not the whole.

    The request runs on a worker thread while this one waits on the deadline and the stop
    flag every 0.1 s; either closes the connection's socket, which ends the worker's
    read at once (so SIGTERM ends a gateway within a second whatever it is reading).
    Raises ``urllib.error.HTTPError`` on an HTTP error status, ``TimeoutError`` past the
    deadline, ``OSError`` or ``ValueError`` (a bad URL) otherwise."""
    parts = urllib.parse.urlsplit(url)
    if parts.scheme not in ("http", "https") or not parts.hostname:
        raise ValueError(f"not an http(s) URL: {url}")
    cls = http.client.HTTPSConnection if parts.scheme == "https" else http.client.HTTPConnection
    conn = cls(parts.hostname, parts.port, timeout=timeout)
    path = urllib.parse.urlunsplit(("", "", parts.path or "/", parts.query, ""))
    out: dict[str, object] = {}

    def work() -> None:
        try:
            conn.request("GET", path, headers={"User-Agent": "zfusion-ingest"})
            resp = conn.getresponse()
            if resp.status >= 400:
                raise urllib.error.HTTPError(url, resp.status, resp.reason, resp.headers, None)
            out["body"] = (resp.read(MAX_BODY + 1), resp.headers.get("Content-Type"))
        except Exception as e:  # handed to the caller, which counts it by cause
            out["error"] = e

    worker = threading.Thread(target=work, name="zfusion-fetch", daemon=True)
    deadline = time.monotonic() + timeout
    worker.start()
    while worker.is_alive() and not stop.is_set() and time.monotonic() < deadline:
        worker.join(0.1)
    if worker.is_alive():  # past the deadline, or stopping: cut the connection under the worker
        sock = conn.sock
        if sock is not None:
            try:
                sock.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
        conn.close()
        worker.join(1.0)
        if stop.is_set():
            return None
        raise TimeoutError(f"no whole answer within {timeout:g} s")
    conn.close()
    if "error" in out:
        raise out["error"]  # type: ignore[misc]
    return out["body"]  # type: ignore[return-value]


def _http_cause(e: Exception) -> str:
    if isinstance(e, urllib.error.HTTPError):
        return f"HTTP {e.code}"
    reason = getattr(e, "reason", e)
    if isinstance(reason, (TimeoutError, socket.timeout)):
        return "timeout"
    return type(reason).__name__ if not isinstance(reason, str) else reason


def _host_port(text: str, flag: str) -> tuple[str, int]:
    """``HOST:PORT``; ``:PORT`` is loopback (127.0.0.1): a gateway is reachable from other
    machines only when told so, e.g. ``0.0.0.0:PORT`` for every interface."""
    host, sep, port = text.rpartition(":")
    if not sep or not port.isdigit() or not 0 <= int(port) < 65536:
        raise UserError(f"{flag} {text!r}: expected HOST:PORT, e.g. 127.0.0.1:8042 (0.0.0.0:8042: every interface)")
    return host.strip("[]") or "127.0.0.1", int(port)


class _PostHandler(BaseHTTPRequestHandler):
    """POSTs into the inbox (bounded); GET answers that the gateway is up."""

    inbox: queue.Queue
    counts: dict
    timeout = 5.0

    def do_POST(self) -> None:  # noqa: N802 (http.server's name)
        length = self.headers.get("Content-Length")
        if length is None or not length.isdigit():
            return self._reply(411, "Content-Length required")
        if int(length) > MAX_BODY:
            return self._reply(413, f"at most {MAX_BODY} bytes")
        data = self.rfile.read(int(length))
        try:
            self.inbox.put_nowait((data, self.headers.get("Content-Type")))
        except queue.Full:
            self.counts["dropped"] += 1
            return self._reply(503, "busy")
        self._reply(200, "ok")

    def do_GET(self) -> None:  # noqa: N802
        self._reply(200, "zfusion ingest: POST KrakenSDR readings here")

    def _reply(self, code: int, text: str) -> None:
        body = (text + "\n").encode()
        self.send_response(code)
        self.send_header("Content-Type", "text/plain")
        self.send_header("Content-Length", str(len(body)))
        self.end_headers()
        self.wfile.write(body)

    def log_message(self, *args) -> None:  # the process's status says what matters
        pass


def _listen(node: Node, gateway: Gateway, recovery: float, station: KrakenStation, where: tuple[str, int],
            args) -> int:
    inbox: queue.Queue = queue.Queue(QUEUE_SIZE)
    counts = {"posts": 0, "dropped": 0}
    handler = type("Handler", (_PostHandler,), {"inbox": inbox, "counts": counts})
    try:
        server = ThreadingHTTPServer(where, handler)
    except OSError as e:
        raise UserError(f"cannot listen on {where[0]}:{where[1]} ({e.strerror or e}); choose a free port") from None
    server.daemon_threads = True
    thread = threading.Thread(target=server.serve_forever, kwargs={"poll_interval": 0.2}, daemon=True)
    thread.start()
    fmt = "auto" if args.format == "auto" else args.format
    try:
        outlet = Outlet(node, gateway, recovery, lambda: counts)
        outlet.ready(args.wait_for)
        node.event(f"listening on http://{where[0]}:{server.server_address[1]}/")
        while not node.stop.is_set():
            try:
                data, ctype = inbox.get(timeout=0.2)
            except queue.Empty:
                pass
            else:
                counts["posts"] += 1
                now = time.time()
                for item in station.receive(data, fmt, ctype):
                    outlet.offer(item, now)
            outlet.tick(time.time())
        outlet.status("stopped", force=True)
    finally:
        server.shutdown()
        server.server_close()
        thread.join(timeout=2.0)
    return 0


# ------------------------------------------------------------------ adsb


def run_adsb(args, keys: KeySpace, zopts) -> int:
    """``zfusion ingest adsb``: a receiver's ``aircraft.json`` polled (``--url``) or its
    BaseStation feed read (``--sbs HOST:PORT``, a TCP client, reconnecting with backoff)."""
    frame, sensors, recovery = _site_sensors(args, [args.id])
    if sensors[args.id].kind != "position":
        raise UserError(f"[sensors.{args.id}] is a {sensors[args.id].kind} sensor: an ADS-B receiver is kind = \"adsb\"")
    try:
        receiver = AdsbReceiver(clock=SbsClock(args.sbs_timezone), sources=frozenset(args.sources.split(",")),
                                sbs_mlat=args.sbs_mlat)
    except (ValueError, KeyError) as e:
        raise UserError(f"ingest adsb: {e}") from None
    where = _host_port(args.sbs, "--sbs") if args.sbs else None
    with Node(args.id, "ingest", keys, zopts, live=True) as node:
        gateway = _gateway(node, args, frame, sensors)
        if args.url:
            return _poll(node, gateway, recovery, args.url, args, lambda data, ctype: receiver.receive_json(data))
        return _sbs(node, gateway, recovery, receiver, where, args)


def _sbs(node: Node, gateway: Gateway, recovery: float, receiver: AdsbReceiver, where: tuple[str, int],
         args) -> int:
    counts = {"connections": 0, "connection_errors": 0, "lines": 0}
    outlet = Outlet(node, gateway, recovery, lambda: counts)
    backoff = Backoff(args.poll_s)
    outlet.ready(args.wait_for)
    while not node.stop.is_set():
        try:
            sock = socket.create_connection(where, timeout=args.timeout_s)
        except OSError as e:
            counts["connection_errors"] += 1
            delay = backoff.failed()
            outlet.say_once(f"connect:{type(e).__name__}", f"{where[0]}:{where[1]}: {e.strerror or e}; "
                                                            f"retrying with backoff (now {delay:g} s)")
            outlet.tick(time.time(), heartbeat=False)
            node.stop.wait(delay)
            continue
        counts["connections"] += 1
        backoff.succeeded()
        node.event(f"connected to the BaseStation feed at {where[0]}:{where[1]}")
        split = LineSplitter()
        with sock:
            sock.settimeout(0.2)
            while not node.stop.is_set():
                try:
                    data = sock.recv(65_536)
                except (TimeoutError, socket.timeout):
                    outlet.tick(time.time())  # drained: heartbeats may promise up to now
                    continue
                except OSError:
                    break
                if not data:  # the receiver closed the feed: connect again
                    break
                now = time.time()
                for line in split.feed(data):
                    if isinstance(line, Rejected):
                        outlet.offer(line, now)
                        continue
                    counts["lines"] += 1
                    for item in receiver.receive_sbs(line, now):
                        outlet.offer(item, now)
                outlet.tick(now, heartbeat=False)
        if not node.stop.is_set():
            outlet.say_once("closed", f"{where[0]}:{where[1]} closed the feed; connecting again")
            node.stop.wait(backoff.failed())
    outlet.status("stopped", force=True)
    return 0


# ------------------------------------------------------------------ jsonl


def run_jsonl(args, keys: KeySpace, zopts) -> int:
    source = _input(args.input)
    if replays(source):  # the watermark follows the file, not the wall clock: no heartbeats
        args.watermark_lag = 0.0
    frame, sensors, recovery = _site_sensors(args, [args.id])
    with Node(args.id, "ingest", keys, zopts, live=True) as node:
        gateway = _gateway(node, args, frame, sensors)
        return _jsonl(node, gateway, recovery, source, args)


def _input(text: str) -> tuple[str, tuple[str, int] | str | None]:
    """``("stdin", None)``, ``("file", path)`` or ``("udp"|"tcp", (host, port))``."""
    if text == "-":
        return "stdin", None
    u = urllib.parse.urlsplit(text)
    if u.scheme in ("udp", "tcp"):
        if not u.hostname or u.port is None:
            raise UserError(f"--input {text!r}: expected udp://HOST:PORT or tcp://HOST:PORT")
        return u.scheme, (u.hostname, u.port)
    try:
        with open(text, "rb"):
            return "file", text
    except OSError as e:
        raise UserError(f"--input {text!r}: cannot read it ({e.strerror or e}); expected -, a file of JSON "
                        f"lines, udp://HOST:PORT or tcp://HOST:PORT") from None


def replays(source: tuple[str, object]) -> bool:
    """Whether the input is a file of past readings (``--input FILE``, or stdin redirected
    from a file): replayed on the file's clock. Its watermarks follow the file (no
    heartbeats: a reading is late only if the file goes back in time) and a reading's age
    is measured from the newest reading read so far, not from now. A pipe is live."""
    if source[0] == "file":
        return True
    if source[0] == "stdin":
        try:
            return stat.S_ISREG(os.fstat(sys.stdin.fileno()).st_mode)
        except (OSError, ValueError):
            return False
    return False


def udp_drops(sock: socket.socket) -> int:
    """Datagrams the kernel dropped for ``sock`` (its receive buffer full), from the
    ``drops`` column of ``/proc/net/udp`` (or ``udp6``) on the socket's inode: Linux's
    per-socket count, exact and readable at any time (``SO_RXQ_OVFL`` delivers it only
    with a later datagram, so a burst's last drops would go unseen). 0 where there is no
    such file. Raises ``OSError`` if the socket is closed."""
    inode = str(os.fstat(sock.fileno()).st_ino)
    name = "/proc/net/udp6" if sock.family == socket.AF_INET6 else "/proc/net/udp"
    try:
        with open(name) as f:
            for line in f:
                cols = line.split()
                if len(cols) > 12 and cols[9] == inode:
                    return int(cols[12])
    except (OSError, ValueError):
        pass
    return 0


class _Reader:
    """A thread that reads one input and puts its lines (or refusals) into ``inbox``;
    ``None`` at the end of stdin. Closed by :meth:`close` (sockets) or the stop flag.

    It waits while ``inbox`` is full (back-pressure: a TCP sender is slowed, a UDP burst
    beyond the socket's buffer is dropped by the kernel, and counted: ``udp_dropped``,
    the socket's own drop counter, read from ``/proc/net/udp`` (:func:`udp_drops`) when
    the input goes quiet and at most once a second meanwhile). :meth:`read_until` says up to when the input is known to hold
    nothing unread: the last time every open input was found drained (a read that timed
    out); the heartbeats never promise past it. TCP: at most :data:`MAX_CONNECTIONS`
    at once (more are closed at once, ``refused_connections``), each closed after
    :data:`IDLE_S` without a byte (``idle_closed``)."""

    def __init__(self, kind: str, where: tuple[str, int] | None, inbox: queue.Queue, stop: threading.Event):
        self.kind, self.inbox, self.stop = kind, inbox, stop
        self.path = where if kind == "file" else None
        self.sock: socket.socket | None = None
        self.counts = {"udp_dropped": 0} if kind == "udp" else {"connections": 0, "refused_connections": 0,
                                                                "idle_closed": 0} if kind == "tcp" else {}
        self._drained: dict[object, float] = {}  # input -> when it was last found drained
        self._lock = threading.Lock()
        if kind in ("udp", "tcp"):
            family = socket.AF_INET6 if ":" in where[0] else socket.AF_INET
            self.sock = socket.socket(family, socket.SOCK_DGRAM if kind == "udp" else socket.SOCK_STREAM)
            self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            try:
                self.sock.bind(where)
            except OSError as e:
                self.sock.close()
                raise UserError(f"cannot bind {kind}://{where[0]}:{where[1]} ({e.strerror or e}); "
                                 f"choose a free port") from None
            self.sock.settimeout(0.2)
            if kind == "tcp":
                self.sock.listen(8)
        self.thread = threading.Thread(target=getattr(self, f"_{kind}"), daemon=True)

    def start(self) -> None:
        self.thread.start()

    def read_until(self) -> float:
        """UTC time up to which every open input is known drained (``inf``: stdin or a file, whose
        pending bytes cannot be told; the heartbeats then follow the inbox alone)."""
        with self._lock:
            return min(self._drained.values(), default=math.inf if self.kind in ("stdin", "file") else time.time())

    def _mark(self, which: object, drained: bool) -> None:
        """``which`` (an input) found drained now, or just opened (not drained yet)."""
        with self._lock:
            self._drained[which] = time.time() if drained else -math.inf

    def _emit(self, items) -> None:
        for it in items:
            while not self.stop.is_set():
                try:
                    self.inbox.put(it, timeout=0.2)  # back-pressure: the reader waits
                    break
                except queue.Full:
                    continue

    def _stdin(self) -> None:
        self._read(sys.stdin.fileno())

    def _file(self) -> None:
        fd = os.open(self.path, os.O_RDONLY)
        try:
            self._read(fd)
        finally:
            os.close(fd)

    def _read(self, fd: int) -> None:
        split = LineSplitter()
        while not self.stop.is_set():
            data = os.read(fd, MAX_LINE)
            if not data:
                self._emit(split.feed(b"\n"))
                self._emit([None])
                return
            self._emit(split.feed(data))

    def _udp(self) -> None:
        self._mark("udp", False)
        counted = time.monotonic()
        while not self.stop.is_set():
            try:
                data = self.sock.recv(MAX_LINE)
            except (TimeoutError, socket.timeout):
                self._count_udp_drops()
                self._mark("udp", True)
                continue
            except OSError:
                return
            if time.monotonic() - counted >= 1.0:
                counted = time.monotonic()
                self._count_udp_drops()
            self._emit(LineSplitter().feed(data + b"\n"))  # a datagram holds whole lines

    def _count_udp_drops(self) -> None:
        """The kernel's drop count, unless :meth:`close` has closed the socket meanwhile
        (a stop: the count read before stands)."""
        try:
            self.counts["udp_dropped"] = udp_drops(self.sock)
        except OSError:  # (EBADF: closed between the read's timeout and this)
            pass

    def _tcp(self) -> None:
        while not self.stop.is_set():
            try:
                conn, _ = self.sock.accept()
            except (TimeoutError, socket.timeout):
                continue
            except OSError:
                return
            with self._lock:
                full = len(self._drained) >= MAX_CONNECTIONS
            if full:
                self.counts["refused_connections"] += 1
                conn.close()
                continue
            self.counts["connections"] += 1
            self._mark(conn, False)
            threading.Thread(target=self._tcp_conn, args=(conn,), daemon=True).start()

    def _tcp_conn(self, conn: socket.socket) -> None:
        split = LineSplitter()
        conn.settimeout(0.2)
        idle = time.monotonic()
        try:
            with conn:
                while not self.stop.is_set():
                    try:
                        data = conn.recv(MAX_LINE)
                    except (TimeoutError, socket.timeout):
                        self._mark(conn, True)
                        if time.monotonic() - idle > IDLE_S:
                            self.counts["idle_closed"] += 1
                            return
                        continue
                    except OSError:
                        return
                    if not data:
                        self._emit(split.feed(b"\n"))
                        return
                    idle = time.monotonic()
                    self._emit(split.feed(data))
        finally:
            with self._lock:
                self._drained.pop(conn, None)

    def close(self) -> None:
        if self.sock is not None:
            self.sock.close()


def _beat(outlet: Outlet, reader: _Reader, inbox: queue.Queue) -> None:
    """Heartbeats only with everything read processed: the reader's drained time taken
    first (it emits before it marks), then the inbox found empty. A burst the gateway is
    behind on is then never ``late``: its readings arrive before any promise past them."""
    until = reader.read_until()
    outlet.tick(time.time(), heartbeat=inbox.empty(), read_until=until)


def _jsonl(node: Node, gateway: Gateway, recovery: float, source: tuple[str, tuple[str, int] | None],
           args) -> int:
    inbox: queue.Queue = queue.Queue(QUEUE_SIZE)
    reader = _Reader(source[0], source[1], inbox, node.stop)
    counts = {"lines": 0}
    outlet = Outlet(node, gateway, recovery, lambda: {**counts, **reader.counts})
    outlet.ready(args.wait_for)
    reader.start()
    where = {"stdin": "stdin", "file": str(source[1])}.get(source[0]) or f"{source[0]}://{source[1][0]}:{source[1][1]}"
    replay = replays(source)
    if chatty():
        log.info("%s: reading JSON lines from %s%s, publishing on %s", node.id, where,
                 " (a replay on the file's clock)" if replay else "", gateway.keys.meas(args.id))
    file_now = -math.inf  # a replay's clock: the newest reading so far
    hinted = False
    state = "stopped"
    try:
        while not node.stop.is_set():
            try:
                item = inbox.get(timeout=0.2)
            except queue.Empty:
                _beat(outlet, reader, inbox)
                continue
            if item is None:  # end of stdin: promise what was sent, and finish
                outlet.put(gateway.flush())
                state = "done"
                break
            if isinstance(item, bytes):
                counts["lines"] += 1
                item = reading(item, args.id)
            if replay and isinstance(item, Reading) and math.isfinite(item.t):
                file_now = max(file_now, item.t)
            outlet.offer(item, file_now if replay else time.time())
            if not (replay or hinted) and source[0] == "stdin" and node.reject.by_cause.keys() & {"late", "stale"}:
                hinted = True
                log.warning("%s: readings from stdin are checked against this clock; a file of past readings "
                            "replays on its own clock with --input FILE (or < FILE)", node.id)
            _beat(outlet, reader, inbox)
        outlet.status(state, force=True)
    finally:
        reader.close()
    if source[0] in ("stdin", "file"):
        node.settle_link()  # its "connected" line, if any, comes before the summary
        log.info("%s: %s", node.id, summary(state, where, counts["lines"], gateway.counters, node.reject.by_cause))
    return 0


def summary(state: str, where: str, lines: int, counters: dict, refused: dict[str, int]) -> str:
    """The line a gateway reading a file or stdin ends with: ``end of stdin: 10 lines,
    published 8, refused 2 (late 2), repeats 0``."""
    causes = ", ".join(f"{c} {n}" for c, n in sorted(refused.items()) if n)
    return (f"{'end of' if state == 'done' else 'stopped reading'} {where}: {lines} lines, published "
            f"{counters['published']}, refused {sum(refused.values())}{f' ({causes})' if causes else ''}, "
            f"repeats {counters['repeats']}")


# ------------------------------------------------------------------ asterix


def run_asterix(args, keys: KeySpace, zopts) -> int:
    """``zfusion ingest asterix``: UDP datagrams (or a pcap replay) through
    :class:`~services.ingest.asterix.AsterixIngest`, which decides everything."""
    site = load_site(args.site)
    frame = local_frame(site)
    try:
        rs = radars(site, frame)
        feed = AsterixFeed(rs, args.sector_lag)
    except ValueError as e:
        raise UserError(str(e)) from None
    adsb_stations = stations(site)
    _, sensors, recovery = _site_sensors(args, [r.sensor for r in rs.values()] + list(adsb_stations.values()))
    senders = [s for s in (args.scenario_run or "").split(",") if s]
    if args.scenario_run is not None and (args.pcap or not senders):
        raise UserError("--scenario-run SENDERS: the process ids of the scenario's senders, with --udp")
    if args.pcap:
        speed = _speed(args.speed)
        try:
            with open(args.pcap, "rb") as f:
                packets = list(pcap_datagrams(f.read()))
        except (OSError, CaptureError) as e:
            raise UserError(f"--pcap {args.pcap}: {getattr(e, 'strerror', None) or e}") from None
    else:
        sock = _udp_socket(args.udp)
    with Node(args.id, "ingest", keys, zopts, live=not senders) as node:
        gateway = Gateway(sensors, frame, node.keys, node.reject, max_skew=math.inf, max_age=math.inf, lag=0.0) \
            if senders else _gateway(node, args, frame, sensors)
        ingest = AsterixIngest(feed, gateway, node.reject, src=args.id, stations=adsb_stations)
        outlet = Outlet(node, ingest.gateway, recovery, ingest.counters)
        done = _done_of(node, senders)
        outlet.ready(args.wait_for)
        if args.pcap:
            return _replay(node, ingest, outlet, packets, speed)
        try:
            return _scenario_run(node, ingest, outlet, sock, done) if senders else _receive(node, ingest, outlet, sock)
        finally:
            sock.close()


def _done_of(node: Node, senders: list[str]) -> Callable[[], bool]:
    """Whether each of ``senders`` has reported its state done (its status on Zenoh)."""
    said: set[str] = set()

    def heard(sample) -> None:
        try:
            msg = decode(sample.payload.to_bytes())
        except SchemaError:  # not a status this process can read: not a done one
            return
        if msg.kind == "status" and msg.body.get("state") == "done":
            said.add(msg.src)

    for sid in senders:
        node.subscribe(node.keys.status(sid), heard)
    return lambda: said >= set(senders)


def _scenario_run(node: Node, ingest, outlet: Outlet, sock: socket.socket, done: Callable[[], bool]) -> int:
    """A scenario run's datagrams: their times of day are scenario seconds, placed next
    to the latest time read (so a run may pass midnight of day 0). Once every sender has
    said it is done (after its last datagram was queued on this loopback socket), what is
    queued is read, and every stream ends with a final watermark."""
    state = "stopped"
    while not node.stop.is_set():
        ending = done()
        try:
            data = sock.recv(65_535)
        except (TimeoutError, socket.timeout):
            data = None
        if data is not None:
            outlet.put(ingest.receive(data, ingest.t_last))
            outlet.t_last = ingest.t_last
        elif ending:  # nothing left on the socket
            outlet.put(ingest.gateway.end(ingest.t_last))
            state = "done"
            break
        outlet.status()
    outlet.status(state, force=True)
    return 0


def _speed(text: str) -> float:
    try:
        speed = math.inf if text == "max" else float(text)
    except ValueError:
        speed = -1.0
    if not speed > 0:
        raise UserError(f"--speed {text!r}: a positive factor, or max")
    return speed


def _udp_socket(text: str) -> socket.socket:
    """A bound UDP socket for ``[GROUP@]HOST:PORT`` (GROUP: an IPv4 multicast group joined
    on the interface of HOST)."""
    group, _, where = text.rpartition("@")
    host, port = _host_port(where, "--udp")
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    sock = socket.socket(family, socket.SOCK_DGRAM)
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4 << 20)
        sock.bind((group or host, port))
        if group:
            sock.setsockopt(socket.IPPROTO_IP, socket.IP_ADD_MEMBERSHIP,
                            socket.inet_aton(group) + socket.inet_aton(host))
    except OSError as e:
        sock.close()
        raise UserError(f"--udp {text}: {e.strerror or e}; choose a free port (and a multicast group "
                         f"and an interface address for GROUP@HOST)") from None
    sock.settimeout(0.2)
    return sock


def _receive(node: Node, ingest, outlet: Outlet, sock: socket.socket) -> int:
    ticked = 0.0
    while not node.stop.is_set():
        try:
            data = sock.recv(65_535)
        except (TimeoutError, socket.timeout):
            data = None
        now = time.time()
        if data is not None:
            outlet.put(ingest.receive(data, now))
            outlet.t_last = ingest.t_last
        if now - ticked >= TICK_S:  # heartbeats ten times a second, not per datagram
            ticked = now
            outlet.tick(now)
    outlet.status("stopped", force=True)
    return 0


def _replay(node: Node, ingest, outlet: Outlet, packets: list[tuple[float, bytes]], speed: float) -> int:
    """A capture at ``speed`` times its pace; its own times are the receiver's clock."""
    state, ticked = "stopped", -math.inf
    w0 = time.monotonic()
    t0 = packets[0][0] if packets else 0.0
    for t, data in packets:
        if node.stop.is_set():
            break
        if math.isfinite(speed):
            node.stop.wait(max(0.0, w0 + (t - t0) / speed - time.monotonic()))
        outlet.put(ingest.receive(data, t))
        outlet.t_last = ingest.t_last
        if t - ticked >= TICK_S:
            ticked = t
            outlet.tick(t)
    else:
        outlet.put(ingest.gateway.flush())
        state = "done"
    outlet.status(state, force=True)
    return 0


def main(args, keys: KeySpace, zopts) -> int:
    """``zfusion ingest GATEWAY`` (:mod:`services.commands.ingest` parses its options).
    Exit 2 if a process of ``--wait-for`` never announced itself."""
    try:
        return _gateway_main(args, keys, zopts)
    except NotHeard as e:
        log.error("%s", e)
        return 2


def _gateway_main(args, keys: KeySpace, zopts) -> int:
    if args.gateway == "krakensdr":
        return run_krakensdr(args, keys, zopts)
    if args.gateway == "asterix":
        return run_asterix(args, keys, zopts)
    if args.gateway == "adsb":
        return run_adsb(args, keys, zopts)
    return run_jsonl(args, keys, zopts)
