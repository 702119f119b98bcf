"""A gateway survives a document nested deeper than any decoder can follow, for real: a
``zfusion ingest jsonl`` on UDP fed a 60 kB line of ``[``, a ``zfusion ingest
krakensdr --listen`` sent a 200 kB POST of it and a polling one served a page of it each
keep running, count it (``rejected.too-deep``) and publish the next good reading."""

from __future__ import annotations

import json
import socket
import time
import urllib.request

import pytest

from _ingest_helpers import Capture, DocServer, gateway, kraken_csv, kraken_json, site_toml, stop
from services.launcher import free_port

pytestmark = pytest.mark.slow


@pytest.fixture
def site(tmp_path):
    path = tmp_path / "site.toml"
    path.write_text(site_toml({"df1": {"pos_m": [0.0, 0.0, 0.0]}}))
    return str(path)


def counted(cap: Capture, cause: str) -> int:
    return cap.status("df1").get("counters", {}).get(f"rejected.{cause}", 0)


def test_jsonl_on_udp_survives_a_60_kB_line_of_brackets(deployment, site):
    port = free_port()
    with Capture(deployment) as cap:
        p = gateway("jsonl", "--id", "df1", "--site", site, "--input", f"udp://127.0.0.1:{port}", capture=cap)
        try:
            assert cap.wait(lambda: cap.of("status", "df1") or p.poll() is not None) and p.poll() is None
            with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
                s.sendto(b"[" * 60_000 + b"\n", ("127.0.0.1", port))
                assert cap.wait(lambda: counted(cap, "too-deep") == 1 or p.poll() is not None, timeout=20)
                t = time.time()
                s.sendto((json.dumps({"t": t, "kind": "bearing", "az_deg": 42.0}) + "\n").encode(),
                         ("127.0.0.1", port))
                assert cap.wait(lambda: cap.of("bearing") or p.poll() is not None, timeout=20)
            assert p.poll() is None, "the gateway died"
            assert [m.t for m in cap.of("bearing")] == [t]
            assert counted(cap, "too-deep") == 1
        finally:
            stop(p)


def test_krakensdr_survives_a_deep_post_and_a_deep_page(deployment, site):
    port = free_port()
    with Capture(deployment) as cap, DocServer() as srv:
        listening = gateway("krakensdr", "--id", "df1", "--site", site, "--listen", f"127.0.0.1:{port}",
                            capture=cap)
        try:
            assert cap.wait(lambda: cap.of("status", "df1") or listening.poll() is not None)

            def post(body: bytes) -> int:
                req = urllib.request.Request(f"http://127.0.0.1:{port}/doapost", data=body,
                                             headers={"Content-Type": "application/json"})
                with urllib.request.urlopen(req, timeout=5) as r:
                    return r.status

            for _ in range(50):  # the server may not be up yet
                try:
                    assert post(b"[" * 200_000) == 200  # taken, then refused and counted
                    break
                except OSError:
                    time.sleep(0.1)
            assert cap.wait(lambda: counted(cap, "too-deep") == 1 or listening.poll() is not None)
            assert post(kraken_json(time.time(), 300.0)) == 200
            assert cap.wait(lambda: cap.of("bearing") or listening.poll() is not None)
            assert listening.poll() is None, "the listening gateway died"
        finally:
            stop(listening)
        n = len(cap.of("bearing"))
        srv.docs["/DOA_value.html"] = b"[" * 500_000
        polling = gateway("krakensdr", "--id", "df1", "--site", site, "--url", srv.url, "--poll-s", "0.2",
                          capture=cap)
        try:
            assert cap.wait(lambda: counted(cap, "too-deep") >= 1 and cap.status("df1")["state"] == "running"
                            or polling.poll() is not None, timeout=30)
            srv.docs["/DOA_value.html"] = kraken_csv(time.time(), [45.0])
            assert cap.wait(lambda: len(cap.of("bearing")) > n or polling.poll() is not None, timeout=30)
            assert polling.poll() is None, "the polling gateway died"
        finally:
            stop(polling)
