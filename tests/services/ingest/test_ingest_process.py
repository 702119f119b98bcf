"""The gateway processes, for real: ``zfusion ingest krakensdr|jsonl`` against a local
web server, POSTs, stdin, UDP and TCP, publishing over a real Zenoh session."""

from __future__ import annotations

import json
import math
import socket
import subprocess
import sys
import time
import urllib.request

import psutil
import pytest

from _ingest_helpers import Capture, DocServer, TcpServer, gateway, kraken_csv, kraken_json, site_toml, stop
from schemas import to_measurement
from services.launcher import free_port
from conftest import ROOT, wait_for

pytestmark = pytest.mark.slow


@pytest.fixture
def site(tmp_path):
    path = tmp_path / "site.toml"
    path.write_text(site_toml({"df1": {"pos_m": [0.0, 0.0, 0.0]}, "df2": {}}))
    return str(path)


def test_polls_publish_each_frame_once_and_survive_http_errors(deployment, site):
    with DocServer() as srv, Capture(deployment) as cap:
        p = gateway("krakensdr", "--id", "df1", "--site", site, "--url", srv.url, "--poll-s", "0.2",
                    capture=cap)
        try:
            assert cap.wait(lambda: cap.of("status", "df1") or p.poll() is not None) and p.poll() is None
            t1 = time.time()  # the page is 404 until then: counted as an HTTP error
            srv.docs["/DOA_value.html"] = kraken_csv(t1, [45.0])
            assert cap.wait(lambda: cap.of("bearing")), "no bearing published"
            srv.fail = 3  # the station's web server fails for a while: backoff 0.4, 0.8, 1.6 s (6 failures waited 25 s)
            assert cap.wait(lambda: cap.status("df1").get("counters", {}).get("http_errors", 0) >= 2)
            t2 = time.time()
            srv.docs["/DOA_value.html"] = kraken_csv(t2, [50.0])
            assert cap.wait(lambda: len(cap.of("bearing")) >= 2, timeout=40)
            assert cap.wait(lambda: cap.status("df1")["counters"]["repeats"] >= 2)  # the page, polled again
            counters = cap.status("df1")["counters"]
        finally:
            err = stop(p)
    meas = [to_measurement(m) for m in cap.of("bearing")]
    assert [m.t for m in meas] == [round(t1 * 1000) / 1000, round(t2 * 1000) / 1000]  # repeats not republished
    assert [round(math.degrees(m.z[0]), 9) for m in meas] == [45.0, 50.0]
    assert all(m.site.tolist() == [0.0, 0.0, 0.0] for m in meas)  # df1 is pinned in the site file
    assert counters["http_errors"] >= 2 and counters["published"] == 2
    assert counters["rejected"] == 0
    assert err.count("HTTP 500") == 1 and err.count("HTTP 404") <= 1  # said once, not per failed poll
    assert cap.of("status", "df1")[-1].body["state"] == "stopped"
    # Watermarks: after each bearing, and heartbeats while the page repeats itself.
    assert len(cap.of("watermark", "df1")) > 2


def test_listens_for_kraken_pro_and_full_post_bodies(deployment, site):
    port = free_port()
    with Capture(deployment) as cap:
        p = gateway("krakensdr", "--id", "df2", "--site", site, "--listen", f"127.0.0.1:{port}", capture=cap)
        try:
            assert cap.wait(lambda: cap.of("status", "df2"))

            def post(body: bytes, ctype: str) -> int:
                req = urllib.request.Request(f"http://127.0.0.1:{port}/doapost", data=body,
                                             headers={"Content-Type": ctype})
                with urllib.request.urlopen(req, timeout=5) as r:
                    return r.status

            t = time.time()

            def posted() -> bool:  # the server may not be up yet
                try:
                    return post(kraken_json(t, 300.0), "application/json") == 200
                except OSError:
                    return False

            wait_for(posted, "the gateway's HTTP server took a post", poll=0.1)
            form = (f"id=KRK&time={round((t + 1) * 1000)}&lat=21.1&lng=105.9&gpsheading=10&radiobearing=20"
                    f"&conf=2.5&power=-50&freq=433920000").encode()
            assert post(form, "application/x-www-form-urlencoded") == 200
            assert post(b"{not json", "application/json") == 200  # taken, then refused and counted
            assert cap.wait(lambda: len(cap.of("bearing")) >= 2)
            assert cap.wait(lambda: cap.status("df2").get("counters", {}).get("rejected.json") == 1)
        finally:
            stop(p)
    a, b = (to_measurement(m) for m in cap.of("bearing"))
    assert math.degrees(a.z[0]) == pytest.approx(300.0) and math.degrees(b.z[0]) == pytest.approx(350.0)
    assert a.site.tolist() != b.site.tolist()  # df2's site comes from each message


def test_jsonl_from_stdin_udp_and_tcp(deployment, tmp_path):
    site = tmp_path / "site.toml"
    site.write_text(site_toml({"df1": {"pos_m": [0.0, 0.0, 0.0]}}))
    t = time.time()
    line = lambda k: json.dumps({"t": t + k, "kind": "bearing", "az_deg": 10.0 * k}) + "\n"  # noqa: E731
    with Capture(deployment) as cap:
        # stdin: the process finishes at the end of its input, having promised all it sent.
        # No heartbeats (a replay): t was taken before the process started.
        p = gateway("jsonl", "--id", "df1", "--site", str(site), "--watermark-lag", "0", capture=cap,
                    stdin=subprocess.PIPE)
        _, err = p.communicate(line(0) + "garbage\n" + line(1), timeout=30)
        assert p.returncode == 0, err[-2000:]
        assert cap.wait(lambda: cap.of("status", "df1") and cap.of("status", "df1")[-1].body["state"] == "done")
        assert [m.t for m in cap.of("bearing")] == [t, t + 1]
        assert cap.of("watermark", "df1")[-1].t == t + 1
        assert cap.status("df1")["counters"]["rejected.json"] == 1
        for scheme in ("udp", "tcp"):
            port = free_port()
            n = len(cap.of("bearing"))
            p = gateway("jsonl", "--id", "df1", "--site", str(site), "--input", f"{scheme}://127.0.0.1:{port}",
                        capture=cap)
            try:
                deadline = time.monotonic() + 60  # the gateway may take seconds to start listening
                while len(cap.of("bearing")) < n + 2 and time.monotonic() < deadline:
                    k = time.time() - t  # fresh times: older than the heartbeat lag would be late
                    try:
                        if scheme == "udp":
                            with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
                                s.sendto((line(k) + line(k + 0.01)).encode(), ("127.0.0.1", port))
                        else:
                            with socket.create_connection(("127.0.0.1", port), timeout=2) as s:
                                s.sendall(line(k).encode())
                                s.sendall(line(k + 0.01)[:10].encode())
                                time.sleep(0.05)
                                s.sendall(line(k + 0.01)[10:].encode())  # a line split across segments
                    except OSError:
                        pass
                    time.sleep(0.3)
            finally:
                stop(p)
            got = cap.of("bearing")[n:]
            assert len(got) >= 2 and got[-1].t - got[-2].t == pytest.approx(0.01), scheme


@pytest.mark.parametrize("args, says", [
    (["krakensdr", "--id", "df1", "--site", "/nonexistent.toml", "--url", "http://127.0.0.1:1"], "site file"),
    (["krakensdr", "--id", "dfX", "--site", "SITE", "--url", "http://127.0.0.1:1"], "[sensors.dfX]"),
    (["krakensdr", "--id", "df1", "--site", "SITE", "--url", "ftp://x"], "--url"),
    (["krakensdr", "--id", "df1", "--site", "SITE", "--url", "http://h:1", "--format", "json"], "--listen"),
    (["krakensdr", "--id", "df1", "--site", "SITE", "--listen", "nowhere"], "--listen"),
    (["krakensdr", "--id", "df1", "--site", "SITE", "--url", "http://h:1", "--heading", "north"], "--heading"),
    (["krakensdr", "--id", "df1", "--site", "SITE", "--url", "http://h:1", "--poll-s", "0"], "--poll-s"),
    (["krakensdr", "--id", "df1", "--site", "SITE", "--url", "http://h:1", "--vfo", "433.9", "--vfo", "446"],
     "[sensors.df1-0]"),
    (["jsonl", "--id", "df1", "--site", "SITE", "--input", "file.txt"], "--input"),
])
def test_user_mistakes_are_one_line_and_exit_2(site, args, says):
    args = [site if a == "SITE" else a for a in args]
    p = subprocess.run([sys.executable, "-m", "services.cli", "ingest", *args], capture_output=True, text=True,
                       timeout=60)
    assert p.returncode == 2, p.stderr
    lines = p.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"zfusion ingest {args[0]}: ") and says in lines[0], p.stderr


def test_the_documented_publisher_example_speaks_the_wire_format(deployment):
    """docs/examples/publish_measurements.py, run as written: what it publishes passes the
    project's strict decoder (the fuser's)."""
    example = ROOT / "docs" / "examples" / "publish_measurements.py"
    with Capture(deployment) as cap:
        p = subprocess.run([sys.executable, str(example), "--connect", cap.endpoint, "--deployment", deployment,
                            "--id", "radar7", "--count", "3", "--period-s", "0.1"], capture_output=True, text=True,
                           timeout=60)
        assert p.returncode == 0, p.stderr[-2000:]
        assert cap.wait(lambda: len(cap.of("watermark", "radar7")) == 3, timeout=10)
    meas = [to_measurement(m) for m in cap.of("range_az", "radar7")]
    assert [m.seq for m in meas] == [1, 2, 3]
    assert [round(math.degrees(m.z[0]), 9) for m in meas] == [30.0, 31.0, 32.0]
    assert all(abs(m.t - time.time()) < 60 for m in meas)


class _Trickle(TcpServer):
    """A web server that answers every GET a byte at a time, one every 0.3 s (forever):
    the headers on odd connections, the body after whole headers on even ones."""

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    def handle(self, conn, n):
        head = b"HTTP/1.1 200 OK\r\nContent-Type: text/html\r\nContent-Length: 100000\r\n\r\n"
        conn.recv(4096)
        if n % 2 == 0:
            conn.sendall(head)
        for b in (head if n % 2 else b"1" * 100_000):
            if self.closing.wait(0.3):
                break
            conn.sendall(bytes([b]) if n % 2 else b"1")


def test_a_trickled_answer_is_a_timeout_and_sigterm_ends_the_poll_at_once(deployment, site):
    """A station's web server that trickles its page (or its headers) a byte every 0.3 s:
    each poll is abandoned at --timeout-s whole (counted as an HTTP error, cause timeout,
    said once), the gateway keeps its status heartbeat meanwhile, and SIGTERM in the
    middle of a request ends it at once. (Before: the timeout bounded each read, so a
    trickle froze polls, heartbeats and status for as long as it lasted, and SIGTERM
    waited for it.)"""
    with _Trickle() as srv, Capture(deployment) as cap:
        p = gateway("krakensdr", "--id", "df1", "--site", site, "--url", srv.url, "--poll-s", "0.2",
                    "--timeout-s", "1", capture=cap)
        try:
            assert cap.wait(lambda: cap.status("df1").get("counters", {}).get("http_errors", 0) >= 3
                            or p.poll() is not None) and p.poll() is None
            assert srv.connections >= 3  # both kinds of trickle, each abandoned
            n = len(cap.of("status", "df1"))
            assert cap.wait(lambda: len(cap.of("status", "df1")) >= n + 2, timeout=10)  # status goes on
            k = srv.connections
            assert cap.wait(lambda: srv.connections > k)  # a request under way
            t0 = time.monotonic()
            err = stop(p)
            took = time.monotonic() - t0
        finally:
            if p.poll() is None:
                p.kill()
    assert took < 3.0, took  # the trickle lasts 100,000 x 0.3 s; a whole stop is well under a second here
    assert err.count("timeout") == 1, err  # said once, counted per poll
    assert cap.status("df1")["counters"]["http_errors"] >= 3


@pytest.mark.parametrize("scheme", ["tcp", "udp"])
def test_a_burst_is_published_or_counted_never_late(deployment, tmp_path, scheme):
    """5,000 valid lines as fast as the sender can: over TCP the gateway slows the
    sender (its queue full, the reader waits) and publishes every line, none refused as
    ``late``: its heartbeats never promise past what it has not read (before: 83 % of a
    10,000 lines/s burst were ``late``, behind the gateway's own heartbeat). Over UDP
    the kernel drops what the socket's buffer cannot hold: every line is published,
    refused or counted in ``udp_dropped`` (before: 16.6 % vanished uncounted)."""
    site = tmp_path / "site.toml"
    site.write_text(site_toml({"df1": {"pos_m": [0.0, 0.0, 0.0]}}))
    n = 5000
    port = free_port()
    with Capture(deployment) as cap:
        # A heartbeat lag of 0.2 s: any burst that takes longer than that to read would
        # meet the heartbeats if they ran ahead of the reading (the default 2 s needs ~10,000 lines).
        p = gateway("jsonl", "--id", "df1", "--site", str(site), "--input", f"{scheme}://127.0.0.1:{port}",
                    "--watermark-lag", "0.2", capture=cap)
        try:
            assert cap.wait(lambda: cap.of("status", "df1") or p.poll() is not None, timeout=60) and p.poll() is None
            # Each line stamped as it is sent, as a device does: a sender starved of the CPU for more
            # than the lag would otherwise send stamps the gateway had rightly promised past (with
            # stamps made before the burst, 256 of 5,000 were `late` over UDP with a core kept busy).
            def line() -> bytes:
                return json.dumps({"t": time.time(), "kind": "bearing", "az_deg": 1.0}).encode() + b"\n"
            if scheme == "tcp":  # in bursts of 100 lines
                with socket.create_connection(("127.0.0.1", port), timeout=60) as s:
                    for _ in range(n // 100):
                        s.sendall(b"".join(line() for _ in range(100)))
            else:
                with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
                    for _ in range(n):
                        s.sendto(line(), ("127.0.0.1", port))

            def accounted():
                c = cap.status("df1").get("counters", {})
                return c.get("published", 0) + c.get("rejected", 0) + c.get("udp_dropped", 0) == n

            assert cap.wait(accounted, timeout=120), cap.status("df1")
            counters = cap.status("df1")["counters"]
        finally:
            stop(p)
    assert counters.get("rejected.late", 0) == 0, counters
    if scheme == "tcp":
        assert counters["published"] == n, counters
    assert len(cap.of("bearing", "df1")) == counters["published"]


def test_listen_on_a_bare_port_is_loopback(deployment, site):
    """``--listen :PORT`` binds 127.0.0.1, not every interface (a station's POSTs reach
    the gateway from elsewhere only when told: ``0.0.0.0:PORT``)."""
    port = free_port()
    with Capture(deployment) as cap:
        p = gateway("krakensdr", "--id", "df1", "--site", site, "--listen", f":{port}", capture=cap)
        try:
            assert cap.wait(lambda: cap.of("status", "df1") or p.poll() is not None) and p.poll() is None
            bound = [c.laddr for c in psutil.Process(p.pid).net_connections(kind="tcp")
                     if c.status == psutil.CONN_LISTEN and c.laddr.port == port]
        finally:
            stop(p)
    assert [a.ip for a in bound] == ["127.0.0.1"], bound
