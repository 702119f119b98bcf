"""The CoT exporter in a run: DF bearings arrive as lines from each station along its
bearing, next to the fix, its trail and the stations, over a TCP connection to a
TAK-like server."""

from __future__ import annotations

import math
import socket
import subprocess
import threading

import numpy as np
import pymap3d

from _cot_schema import check_event
from _ingest_helpers import TcpServer
from conftest import zfusion
from sensors_sim import load_scenario
from services.export import cot
from services.scoring import truth_function

WGS84 = pymap3d.Ellipsoid.from_name("wgs84")


class Collector(TcpServer):
    """Keeps every byte the exporter sends."""

    def __init__(self):
        super().__init__()
        self.data = bytearray()
        self.lock = threading.Lock()

    def handle(self, conn: socket.socket, n: int) -> None:
        conn.settimeout(0.2)
        while not self.closing.is_set():
            try:
                chunk = conn.recv(65536)
            except socket.timeout:
                continue
            if not chunk:
                return
            with self.lock:
                self.data += chunk

    def events(self) -> list[bytes]:
        with self.lock:
            return [part + b"</event>" for part in bytes(self.data).split(b"</event>") if part.strip()]


def test_a_df_run_sends_each_stations_bearings_as_lines_toward_the_emitter(tmp_path, deployment):
    sc = load_scenario("thesis-fixed-c1")
    with Collector() as srv:
        p = zfusion("run", "--scenario", "thesis-fixed-c1", "--speed", "max", "--cot", f"tcp://127.0.0.1:{srv.port}",
                    "--rrd", str(tmp_path / "r.rrd"), "--deployment", deployment,
                    stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        out, err = p.communicate(timeout=600)
        assert p.returncode == 0, err[-3000:]
        events = [check_event(d) for d in srv.events()]
    kinds = {}
    for ev in events:
        z = ev.find("detail/zfusion")
        kinds.setdefault(z.get("kind"), []).append(ev)
    assert {"sensor", "fix", "trail", "bearing"} <= set(kinds), sorted(kinds)
    emitter = np.asarray(truth_function(sc)(0, "E1", 10.0))[:2]  # a static emitter
    seen = set()
    for ev in kinds["bearing"]:
        z = ev.find("detail/zfusion")
        sid = z.get("sensor")
        seen.add(sid)
        site = sc.sensors[sid].site.position(0.0)
        first, last = ([float(v) for v in ev.findall("detail/link")[i].get("point").split(",")] for i in (0, -1))
        assert np.allclose(pymap3d.geodetic2enu(*first, *sc.origin, ell=WGS84, deg=True)[:2], site[:2], atol=0.05)
        end = np.array(pymap3d.geodetic2enu(*last, *sc.origin, ell=WGS84, deg=True)[:2]) - site[:2]
        to_emitter = emitter - site[:2]
        off = (math.degrees(math.atan2(end[0], end[1]) - math.atan2(to_emitter[0], to_emitter[1])) + 180) % 360 - 180
        assert abs(off) < 5.0, (sid, off)  # the stations' σ is 1°
        assert np.hypot(*to_emitter) < np.hypot(*end) <= cot.BEARING_RANGE_M + 0.1  # it reaches past the emitter
        assert abs(float(z.get("azimuth")) - math.degrees(math.atan2(end[0], end[1])) % 360) < 0.006  # two decimals
    assert seen == set(sc.sensors)
