"""``zfusion ingest adsb`` for real: an ``aircraft.json`` polled from a local web server
and a BaseStation feed read from a local TCP server, each reading published as a
``position`` measurement in the site's frame with the accuracy its message states."""

from __future__ import annotations

import json
import time
from datetime import datetime, timezone

import numpy as np
import pytest

from _ingest_helpers import Capture, DocServer, TcpServer, adsb_site_toml, gateway, stop
from fusion.geodetic import LocalFrame
from fusion.types import Identity
from schemas import to_measurement
from services.ingest.adsb import FT, horizontal_std, nacp_std_m, vertical_std

pytestmark = pytest.mark.slow

ORIGIN = (48.85, 2.35, 35.0)
FRAME = LocalFrame(*ORIGIN, deg=True)
RX = {"kind": "adsb", "period_s": 1.0, "std_pos_m": 30.0, "std_alt_m": 45.0}
SITE = adsb_site_toml(ORIGIN, RX)


@pytest.fixture
def site(tmp_path):
    path = tmp_path / "site.toml"
    path.write_text(SITE)
    return str(path)


def _check(m, lat, lon, alt, std):
    assert m.kind == "position" and m.sensor == "rx"
    assert np.allclose(m.z, FRAME.to_enu(lat, lon, alt), atol=1e-6)
    # The stated noise, turned from the ENU axes at the aircraft into the site's: the
    # covariance's trace (rotation-invariant) is the stated one's.
    C = np.outer(m.std, m.std) * (np.eye(3) if m.corr is None else m.corr)
    assert np.trace(C) == pytest.approx(float(np.sum(np.square(std))), rel=1e-9)


def test_polled_aircraft_json_publishes_each_position_once(deployment, site):
    now = time.time()
    doc = {"now": now, "aircraft": [
        {"hex": "39b002", "type": "adsb_icao", "flight": "AFR1234 ", "lat": 48.9, "lon": 2.4, "alt_geom": 10000,
         "seen_pos": 0.4, "nac_p": 9, "gva": 2},
        {"hex": "4ca7b1", "type": "mlat", "lat": 48.7, "lon": 2.1, "alt_baro": 24000, "seen_pos": 1.0,
         "mlat": ["lat", "lon"]},
        {"hex": "3c6444", "type": "adsb_icao", "lat": 48.8, "lon": 2.3, "alt_baro": "ground", "seen_pos": 0.2,
         "nac_p": 9},  # on the ground: no 3D position
        {"hex": "zzzzzz", "lat": 48.8}]}  # malformed
    with DocServer() as srv, Capture(deployment) as cap:
        srv.docs["/data/aircraft.json"] = json.dumps(doc).encode()
        p = gateway("adsb", "--id", "rx", "--site", site, "--url", f"{srv.url}/data/aircraft.json", "--poll-s", "0.2",
                    capture=cap)
        try:
            assert cap.wait(lambda: len(cap.of("position")) >= 2 or p.poll() is not None) and p.poll() is None
            assert cap.wait(lambda: cap.status("rx").get("counters", {}).get("repeats", 0) + cap.status("rx").get(
                "counters", {}).get("skipped.repeat", 0) >= 2)  # polled again: nothing new
            counters = cap.status("rx")["counters"]
        finally:
            stop(p)
    got = sorted((to_measurement(m) for m in cap.of("position")), key=lambda m: m.t)
    assert len(got) == 2, counters  # each position once
    adsb, mlat = sorted(got, key=lambda m: -m.t)
    assert adsb.t == pytest.approx(now - 0.4, abs=1e-3) and mlat.t == pytest.approx(now - 1.0, abs=1e-3)
    _check(adsb, 48.9, 2.4, 10000 * FT, [nacp_std_m(9)] * 2 + [vertical_std("geometric", gva=2)])
    _check(mlat, 48.7, 2.1, 24000 * FT, [horizontal_std("mlat", None)] * 2 + [vertical_std("barometric")])
    assert (adsb.identity, mlat.identity) == (Identity("39b002", "AFR1234"), Identity("4ca7b1", None))
    assert counters["skipped.no-altitude"] >= 1 and counters["rejected"] >= 1, counters


class _Feed(TcpServer):
    """A BaseStation feed on loopback (port 30003 of a receiver): sends ``lines`` to each
    client that connects, then holds the connection open."""

    lines: list[str] = []

    def handle(self, conn, n):
        conn.sendall("".join(self.lines).encode())
        self.closing.wait()


def test_sbs_feed_publishes_positions_with_their_time(deployment, site):
    t = time.time() - 0.5
    stamp = datetime.fromtimestamp(t, timezone.utc)
    d, c = stamp.strftime("%Y/%m/%d"), stamp.strftime("%H:%M:%S.%f")[:12]
    with _Feed() as feed, Capture(deployment) as cap:
        feed.lines = [f"MSG,1,1,1,4CA2D6,1,{d},{c},{d},{c},RYR12AB,,,,,,,,,,,0\r\n",
                      f"MSG,3,1,1,4CA2D6,1,{d},{c},{d},{c},,35000,,,52.1,4.2,,,0,0,0,0\r\n",
                      "MSG,3,1,1,4CA2D6,1,garbage\r\n"]
        p = gateway("adsb", "--id", "rx", "--site", site, "--sbs", f"127.0.0.1:{feed.port}", "--sbs-timezone", "UTC",
                    capture=cap)
        try:
            assert cap.wait(lambda: cap.of("position") or p.poll() is not None) and p.poll() is None
            assert cap.wait(lambda: cap.status("rx").get("counters", {}).get("lines", 0) >= 3)
            counters = cap.status("rx")["counters"]
        finally:
            stop(p)
    (m,) = [to_measurement(x) for x in cap.of("position")]
    assert m.t == pytest.approx(round(t * 1000) / 1000, abs=2e-3)
    _check(m, 52.1, 4.2, 35000 * FT, [horizontal_std("adsb", None)] * 2 + [vertical_std("barometric")])
    assert m.identity == Identity("4ca2d6", "RYR12AB")  # the callsign of an earlier MSG,1
    assert counters["connections"] == 1 and counters["rejected"] >= 1, counters


def test_a_site_sensor_that_is_no_adsb_receiver_is_one_line(tmp_path):
    import subprocess
    import sys

    path = tmp_path / "site.toml"
    path.write_text(adsb_site_toml(ORIGIN, {"kind": "df", "period_s": 1.0, "std_az_deg": 1.0, "pos_m": [0, 0, 0]}))
    r = subprocess.run([sys.executable, "-m", "services.cli", "ingest", "adsb", "--id", "rx", "--site", str(path),
                        "--url", "http://127.0.0.1:1/aircraft.json"], capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and "Traceback" not in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr
    assert 'kind = "adsb"' in r.stderr
