"""The JSON lines gateway's sustained rate: what ``zfusion ingest jsonl`` takes in
before it slows its sender (TCP) or loses datagrams (UDP), as whole processes on loopback.

    python benchmarks/bench_gateway.py [--lines 20000] [--rates 2000,4000,8000,16000] [--seconds 3]

Rows, each beside a peer measured in the same run:

* ``decode``: in this process, a line through the gateway's sans-I/O path (the line
  parser, :class:`services.ingest.gateway.Gateway`'s checks and the msgpack of the
  measurement): the rate one core could sustain with no I/O at all;
* ``tcp``: ``--lines`` bearing lines written to one TCP connection as fast as the
  gateway reads them (TCP's flow control slows the writer when the gateway's queue is
  full: nothing is shed, the rate is the gateway's), from the first byte written to the
  last measurement heard on ``meas/<id>`` by this driver; the peer is a Python process
  that reads the same connection and drops the lines (the transport's ceiling in the
  same language);
* ``udp``: lines paced at each of ``--rates`` lines/s for ``--seconds``: published and
  counted as dropped by the kernel (``udp_dropped``); the sustained rate is the highest
  with none dropped. The peer is a Python process that only receives the datagrams.

A gateway's losses are all counted (docs/reliability.md): over TCP it slows the sender,
over UDP the kernel drops what the socket's buffer cannot hold and the gateway counts
them. The driver takes CPU too (pacing, decoding what it hears): on two cores the
figures are a floor.
"""

from __future__ import annotations

import argparse
import json
import math
import signal
import socket
import subprocess
import sys
import tempfile
import time
import uuid
from pathlib import Path

import _common as C
import zenoh

from schemas import KeySpace, decode
from services.ingest.gateway import Gateway, local_frame, sensor_sites
from services.ingest.jsonl import reading
from services.launcher import free_port
from services.node import ZenohOptions
from services.scenario import load_site

SITE = """description = "gateway benchmark site"
[origin]
lat_deg = 21.0
lon_deg = 105.8
alt_m = 0.0
[defaults]
topology = "centralised"
method = "EKF"
[sensors.df1]
kind = "df"
period_s = 1.0
std_az_deg = 1.0
pos_m = [0.0, 0.0, 0.0]
"""

SINK = r"""
import signal, socket, sys
kind, port = sys.argv[1], int(sys.argv[2])
lines = 0
stop = False
def on_term(*_):
    global stop
    stop = True
signal.signal(signal.SIGTERM, on_term)
if kind == "tcp":
    srv = socket.create_server(("127.0.0.1", port))
    print("ready", flush=True)
    conn, _ = srv.accept()
    while True:
        data = conn.recv(1 << 16)
        if not data:
            break
        lines += data.count(b"\n")
else:
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", port))
    s.settimeout(0.2)
    print("ready", flush=True)
    while not stop:
        try:
            s.recv(1 << 16)
            lines += 1
        except socket.timeout:
            pass
print(lines, flush=True)
"""


def line(t: float) -> bytes:
    return json.dumps({"t": t, "kind": "bearing", "az_deg": 123.4}).encode() + b"\n"


def decode_rate(n: int) -> float:
    """Lines/s of the sans-I/O path in this process (median of 3); every line published."""
    site = load_site(str(SITE_PATH))
    t0 = time.time()
    lines = [line(t0 + 1e-5 * k).rstrip(b"\n") for k in range(n)]

    def once() -> float:
        gw = Gateway(sensor_sites(site, ["df1"]), local_frame(site), KeySpace("bench"), lambda *a: None, lag=0.0)
        start = time.perf_counter()
        for raw in lines:
            gw.offer(reading(raw, "df1"), t0)
        elapsed = time.perf_counter() - start
        assert gw.counters["published"] == n, gw.counters
        return n / elapsed
    return sorted(once() for _ in range(3))[1]


class Driver:
    """A Zenoh peer the gateway dials: counts the measurements it publishes (their
    arrival times) and keeps its latest status counters."""

    def __init__(self):
        self.keys = KeySpace(f"b{uuid.uuid4().hex[:8]}")
        self.endpoint = f"tcp/127.0.0.1:{free_port()}"
        self.session = zenoh.open(ZenohOptions(listen=[self.endpoint]).to_config())
        self.arrivals: list[float] = []
        self.counters: dict = {}
        self._subs = [self.session.declare_subscriber(self.keys.meas("df1"), self._meas),
                      self.session.declare_subscriber(self.keys.status("df1"), self._status)]

    def _meas(self, sample) -> None:
        if decode(sample.payload.to_bytes()).kind != "watermark":
            self.arrivals.append(time.monotonic())

    def _status(self, sample) -> None:
        self.counters = decode(sample.payload.to_bytes()).body.get("counters", {})

    def gateway(self, scheme: str, port: int) -> subprocess.Popen:
        """A gateway reading ``scheme``://127.0.0.1:``port``, once it has reported (its
        input open: a gateway opens it before its first status)."""
        self.counters = {}
        p = subprocess.Popen([sys.executable, "-m", "services.cli", "ingest", "jsonl", "--id", "df1", "--site",
                              str(SITE_PATH), "--input", f"{scheme}://127.0.0.1:{port}", "--max-skew", "60",
                              "--deployment", self.keys.deployment, "--connect", self.endpoint],
                             stderr=subprocess.PIPE, text=True)
        self.wait(lambda: self.counters or p.poll() is not None, 60)
        if p.poll() is not None:
            raise SystemExit(f"the gateway exited: {p.stderr.read()[-2000:]}")
        return p

    @staticmethod
    def wait(predicate, timeout: float) -> bool:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if predicate():
                return True
            time.sleep(0.01)
        return False

    def close(self) -> None:
        for s in self._subs:
            s.undeclare()
        self.session.close()


def stop(p: subprocess.Popen) -> str:
    p.send_signal(signal.SIGTERM)
    out, _ = p.communicate(timeout=20)
    return out or ""


def sink(kind: str) -> tuple[subprocess.Popen, int]:
    port = free_port()
    p = subprocess.Popen([sys.executable, "-c", SINK, kind, str(port)], stdout=subprocess.PIPE, text=True)
    assert p.stdout.readline().strip() == "ready"
    return p, port


def tcp_rates(driver: Driver, n: int) -> tuple[float, float]:
    """(gateway, sink peer) lines/s for ``n`` lines over one connection."""
    t0 = time.time()
    data = b"".join(line(t0 + 1e-5 * k) for k in range(n))
    peer, port = sink("tcp")
    start = time.monotonic()
    with socket.create_connection(("127.0.0.1", port)) as s:
        s.sendall(data)
    got = int(peer.communicate(timeout=60)[0].strip())
    peer_rate = got / (time.monotonic() - start)
    assert got == n, got
    port = free_port()
    gw = driver.gateway("tcp", port)
    try:
        driver.arrivals.clear()
        start = time.monotonic()
        with socket.create_connection(("127.0.0.1", port)) as s:
            s.sendall(data)
        if not driver.wait(lambda: len(driver.arrivals) >= n, 300):
            raise SystemExit(f"tcp: {len(driver.arrivals)} of {n} published ({driver.counters})")
        rate = n / (driver.arrivals[n - 1] - start)
    finally:
        stop(gw)
    return rate, peer_rate


def paced(port: int, rate: float, seconds: float) -> tuple[int, float]:
    """Send ``rate`` lines/s for ``seconds`` to a UDP port, each stamped with its send
    time; the lines sent and the rate achieved (a loaded driver may fall behind)."""
    n = int(rate * seconds)
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        start = time.monotonic()
        t0 = time.time()
        for k in range(n):
            due = start + k / rate
            if k % 64 == 0:
                lag = due - time.monotonic()
                if lag > 0:
                    time.sleep(lag)
            s.sendto(line(t0 + k / rate + 1e-7 * k), ("127.0.0.1", port))
        return n, n / (time.monotonic() - start)


def udp_rates(driver: Driver, rates: list[float], seconds: float) -> list[dict]:
    rows = []
    for rate in rates:
        peer, port = sink("udp")
        paced(port, rate, seconds)
        time.sleep(0.3)
        peer.send_signal(signal.SIGTERM)
        peer_got = int(peer.communicate(timeout=20)[0].strip())
        port = free_port()
        gw = driver.gateway("udp", port)
        try:
            driver.arrivals.clear()
            sent, achieved = paced(port, rate, seconds)

            def accounted():
                c = driver.counters
                return c.get("published", 0) + c.get("rejected", 0) + c.get("udp_dropped", 0) >= sent
            driver.wait(accounted, 60)
            c = driver.counters
            rows.append({"rate": rate, "achieved": achieved, "sent": sent, "published": c.get("published", 0),
                         "udp_dropped": c.get("udp_dropped", 0), "rejected": c.get("rejected", 0),
                         "peer_received": peer_got})
        finally:
            stop(gw)
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--lines", type=int, default=20000, help="lines of the TCP run (default %(default)s)")
    ap.add_argument("--rates", default="2000,4000,8000,16000", help="lines/s of the UDP runs (default %(default)s)")
    ap.add_argument("--seconds", type=float, default=3.0, help="length of each UDP run (default %(default)s)")
    ap.add_argument("--json", help="also write the figures here")
    args = ap.parse_args()
    rates = [float(r) for r in args.rates.split(",")]
    print(f"# JSON lines gateway\n\n{C.machine_line()}\n")
    dec = decode_rate(min(args.lines, 20000))
    driver = Driver()
    try:
        tcp, tcp_peer = tcp_rates(driver, args.lines)
        udp = udp_rates(driver, rates, args.seconds)
    finally:
        driver.close()
    print("## TCP\n")
    print(C.table(["what", "lines/s", "ratio to the gateway"],
                  [["gateway process (read, check, publish, heard by the driver)", f"{tcp:,.0f}", "1"],
                   ["sans-I/O path in one process (decode)", f"{dec:,.0f}", f"{dec / tcp:.1f}x"],
                   ["Python sink process (read and drop)", f"{tcp_peer:,.0f}", f"{tcp_peer / tcp:.1f}x"]]))
    print("\n## UDP (paced)\n")
    print(C.table(["lines/s asked", "sent at", "sent", "published", "udp_dropped", "refused", "lost (%)",
                   "sink peer received"],
                  [[f"{r['rate']:,.0f}", f"{r['achieved']:,.0f}", r["sent"], r["published"], r["udp_dropped"],
                    r["rejected"],
                    f"{100 * (1 - r['published'] / r['sent']):.1f}", r["peer_received"]] for r in udp]))
    clean = [r["rate"] for r in udp if r["published"] == r["sent"]]
    print(f"\nSustained: TCP {tcp:,.0f} lines/s (the sender slowed, nothing shed); UDP "
          f"{max(clean) if clean else math.nan:,.0f} lines/s without a loss (of the rates tried). Load now "
          f"{C.load_now():.1f}.")
    if args.json:
        Path(args.json).write_text(json.dumps({"decode": dec, "tcp": tcp, "tcp_peer": tcp_peer, "udp": udp}, indent=1))


if __name__ == "__main__":
    with tempfile.TemporaryDirectory(prefix="bench-gateway-") as tmp:
        SITE_PATH = Path(tmp) / "site.toml"
        SITE_PATH.write_text(SITE)
        main()
