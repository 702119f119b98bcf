"""Helpers of the gateway process tests: a KrakenSDR-like web server, a Zenoh capture,
a set of processes dialling it, and KrakenSDR documents for a given time and bearing."""

from __future__ import annotations

import json
import math
import signal
import socket
import subprocess
import sys
import threading
import time
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

import zenoh

from schemas import KeySpace, decode
from services.launcher import free_port
from services.node import ZenohOptions


def gateway(*args: str, capture: "Capture", **kw) -> subprocess.Popen:
    """``zfusion ingest ARGS`` on ``capture``'s deployment, dialling it; stderr piped."""
    return subprocess.Popen([sys.executable, "-m", "services.cli", "ingest", *args, "--deployment",
                             capture.keys.deployment, "--connect", capture.endpoint],
                            stderr=subprocess.PIPE, text=True, **kw)


def stop(p: subprocess.Popen) -> str:
    """SIGTERM: the gateway exits 0 without a traceback; its stderr."""
    p.send_signal(signal.SIGTERM)
    _, err = p.communicate(timeout=15)
    assert p.returncode == 0, err[-3000:]
    assert "Traceback" not in err
    return err


class DocServer:
    """``http.server`` on loopback serving ``docs[path]``; ``fail`` > 0 answers that many
    requests with HTTP 500 (a station whose web server is restarting)."""

    def __init__(self):
        self.docs: dict[str, bytes] = {}
        self.fail = 0
        self.requests = 0
        outer = self

        class Handler(BaseHTTPRequestHandler):
            def do_GET(self):  # noqa: N802
                outer.requests += 1
                body = outer.docs.get(self.path)
                if outer.fail > 0:
                    outer.fail -= 1
                    code, body = 500, b"busy"
                else:
                    code = 200 if body is not None else 404
                    body = body if body is not None else b"not found"
                self.send_response(code)
                self.send_header("Content-Type", "text/html")  # what the KrakenSDR's server says
                self.send_header("Content-Length", str(len(body)))
                self.end_headers()
                self.wfile.write(body)

            def log_message(self, *a):
                pass

        self.server = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.url = f"http://127.0.0.1:{self.server.server_address[1]}"
        self.thread = threading.Thread(target=self.server.serve_forever, kwargs={"poll_interval": 0.1}, daemon=True)

    def __enter__(self):
        self.thread.start()
        return self

    def __exit__(self, *exc):
        self.server.shutdown()
        self.server.server_close()


class TcpServer:
    """A TCP server on a free loopback port: each connection is handed to
    :meth:`handle` on its own thread (``n`` its number, from 1); ``closing`` is set when
    the server stops. ``port``, ``connections``."""

    def __init__(self):
        self.sock = socket.create_server(("127.0.0.1", 0))
        self.port = self.sock.getsockname()[1]
        self.connections = 0
        self.closing = threading.Event()
        self.thread = threading.Thread(target=self._serve, daemon=True)

    def handle(self, conn: socket.socket, n: int) -> None:
        raise NotImplementedError

    def _serve(self):
        self.sock.settimeout(0.1)
        while not self.closing.is_set():
            try:
                conn, _ = self.sock.accept()
            except OSError:
                continue
            self.connections += 1
            threading.Thread(target=self._handle, args=(conn, self.connections), daemon=True).start()

    def _handle(self, conn: socket.socket, n: int) -> None:
        try:
            with conn:
                self.handle(conn, n)
        except OSError:
            pass

    def __enter__(self):
        self.thread.start()
        return self

    def __exit__(self, *exc):
        self.closing.set()
        self.sock.close()


class Capture:
    """A Zenoh peer listening on a free loopback port; collects every sample of the
    deployment as ``(key, decoded message)``."""

    def __init__(self, deployment: str):
        self.keys = KeySpace(deployment)
        self.endpoint = f"tcp/127.0.0.1:{free_port()}"
        self.samples: list = []
        self._lock = threading.Lock()

    def __enter__(self):
        self.session = zenoh.open(ZenohOptions(listen=[self.endpoint]).to_config())
        self.sub = self.session.declare_subscriber(self.keys.all(), self._on)
        return self

    def _on(self, sample) -> None:
        with self._lock:
            self.samples.append((str(sample.key_expr), decode(sample.payload.to_bytes())))

    def __exit__(self, *exc):
        self.sub.undeclare()
        self.session.close()

    def of(self, kind: str, src: str | None = None) -> list:
        with self._lock:
            return [m for _, m in self.samples if m.kind == kind and (src is None or m.src == src)]

    def wait(self, predicate, timeout: float = 30.0) -> bool:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if predicate():
                return True
            time.sleep(0.05)
        return False

    def status(self, src: str) -> dict:
        st = self.of("status", src)
        return st[-1].body if st else {}


class Processes:
    """A :class:`Capture` hub and ``zfusion`` processes dialling it (stderr piped); on
    exit each still running gets SIGTERM, must stop within 20 s, and (unless the block
    raised) must have exited 0 without a traceback."""

    def __init__(self, deployment: str):
        self.cap = Capture(deployment)
        self.procs: dict[str, subprocess.Popen] = {}

    def __enter__(self):
        self.cap.__enter__()
        return self

    def start(self, name: str, *args: str) -> subprocess.Popen:
        self.procs[name] = subprocess.Popen(
            [sys.executable, "-m", "services.cli", *args, "--deployment", self.cap.keys.deployment,
             "--connect", self.cap.endpoint], stderr=subprocess.PIPE, text=True)
        return self.procs[name]

    def ready(self, ids, timeout: float = 60.0) -> None:
        """Until each of ``ids`` has reported a status; fails if a process died first."""
        ok = self.cap.wait(lambda: all(self.cap.of("status", i) for i in ids)
                           or any(p.poll() is not None for p in self.procs.values()), timeout=timeout)
        dead = {n: p.stderr.read()[-2000:] for n, p in self.procs.items() if p.poll() is not None}
        assert ok and not dead, dead

    def __exit__(self, *exc):
        errs = {}
        for p in self.procs.values():
            if p.poll() is None:
                p.send_signal(signal.SIGTERM)
        for name, p in self.procs.items():
            try:
                _, errs[name] = p.communicate(timeout=20)
            except subprocess.TimeoutExpired:
                p.kill()
                _, errs[name] = p.communicate()
                raise AssertionError(f"{name} did not stop on SIGTERM")
        self.cap.__exit__(*exc)
        if exc[0] is None:
            for name, p in self.procs.items():
                assert p.returncode == 0 and "Traceback" not in errs[name], (name, errs[name][-3000:])


def kraken_csv(t: float, bearings_deg: list[float], heading: float = 90.0, lat: float = 21.0285,
               lon: float = 105.8542, freqs: list[float] | None = None) -> bytes:
    """A Kraken App document: one line per VFO with compass bearing ``b`` from a station
    whose array points at ``heading`` (field 2 = 360 − θ = b − heading)."""
    freqs = freqs or [433.92e6 + 1e6 * k for k in range(len(bearings_deg))]
    spectrum = ", ".join(["0.00"] * 360)
    out = ""
    for b, f in zip(bearings_deg, freqs):
        out += (f"{round(t * 1000)}, {(b - heading) % 360}, 3.0, -40.0, {int(f)}, UCA, 100, KRK, {lat}, {lon}, "
                f"{heading}, {heading}, GPS, R, R, R, R, {spectrum} \n")
    return out.encode()


def kraken_xml(t: float, bearing_deg: float, heading: float = 90.0, lat: float = 21.0285,
               lon: float = 105.8542) -> bytes:
    theta = (heading - bearing_deg) % 360  # counter-clockwise from the array reference
    return (f"<DATA><STATION_ID>KRK</STATION_ID><TIME>{round(t * 1000)}</TIME><FREQUENCY>433.92</FREQUENCY>"
            f"<LOCATION><LATITUDE>{lat}</LATITUDE><LONGITUDE>{lon}</LONGITUDE><HEADING>{heading}</HEADING>"
            f"</LOCATION><DOA>{theta}</DOA><PWR>60.0</PWR><CONF>300</CONF></DATA>").encode()


def kraken_json(t: float, bearing_deg: float, heading: float = 90.0, lat: float = 21.0285,
                lon: float = 105.8542) -> bytes:
    theta = (heading - bearing_deg) % 360
    return json.dumps({"station_id": "KRK", "tStamp": round(t * 1000), "latitude": str(lat), "longitude": str(lon),
                       "gpsBearing": str(heading), "radioBearing": f"{theta}", "conf": "3.00", "power": "-40.0",
                       "freq": 433920000, "antType": "UCA", "latency": 100}).encode()


def adsb_site_toml(origin, sensor: dict[str, object], tracker: dict[str, object] | None = None,
                   description: str = "an ADS-B receiver") -> str:
    """A site file with one receiver ``rx`` (``sensor``: its keys, ``kind`` included) at
    ``origin`` (lat, lon in degrees, alt in m), SS centralised, ``[tracker]`` keys as given."""
    def table(keys):
        return [f"{k} = {v!r}" if not isinstance(v, str) else f'{k} = "{v}"' for k, v in keys.items()]
    return "\n".join([f'description = "{description}"', "[origin]", f"lat_deg = {origin[0]}", f"lon_deg = {origin[1]}",
                      f"alt_m = {origin[2]}", "[defaults]", 'topology = "centralised"', 'method = "SS"',
                      "[tracker]", *table(tracker or {}), "[sensors.rx]", *table(sensor), ""])


def site_toml(sensors: dict[str, dict], origin=(21.0285, 105.8542, 0.0), sigma_deg: float = 1.0) -> str:
    """A site file with DF stations ``{id: {"pos_m": [...]}}``, or ``{id: {}}``: a mobile
    station whose site is in its messages."""
    lines = ['description = "ingest test site"', "", "[origin]", f"lat_deg = {origin[0]}",
             f"lon_deg = {origin[1]}", f"alt_m = {origin[2]}", "", "[defaults]", 'topology = "centralised"',
             'method = "EKF"', "", "[tracker]", f"sigma = {math.radians(sigma_deg)!r}", ""]
    for sid, spec in sensors.items():
        lines += [f"[sensors.{sid}]", 'kind = "df"', "period_s = 1.0", f"std_az_deg = {sigma_deg}",
                  f"pos_m = {list(spec['pos_m'])}" if "pos_m" in spec else 'site = "messages"', ""]
    return "\n".join(lines)

