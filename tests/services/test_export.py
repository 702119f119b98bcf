"""The exporters: the picture's validation, GeoJSON checked against RFC 7946 (the
``geojson`` package's validator, plus winding and ranges) and pymap3d, CoT events parsed
as XML, TCP reconnection, the process over Zenoh through a fuser restart, and the
acceptance runs of thesis-fixed-c1 (GeoJSON) and patent-3d (CoT over UDP)."""

from __future__ import annotations

import datetime as dt
import json
import math
import signal
import socket
import subprocess
import threading
import time
import xml.etree.ElementTree as ET

import geojson as geojson_pkg
import msgpack
import numpy as np
import pymap3d
import pytest
import zenoh

from fusion.links import Init
from fusion.types import Estimate
from schemas import KeySpace, encode_estimate
from schemas.links import encode_downlink
from sensors_sim import load_scenario
from services import geo
from services.export import cot, geojson
from services.export.tracks import TrackTable, sensor_sites
from services.node import RejectLog, ZenohOptions
from services.scoring import truth_function

from services.launcher import free_port
from conftest import wait_for, zfusion

KEYS = KeySpace("xtest")
WGS84 = pymap3d.Ellipsoid.from_name("wgs84")


def _est(t, x, P=None, track="E1", method="EKF", seq=1, src="fuser") -> bytes:
    x = np.asarray(x, float)
    P = np.eye(x.size) * 100.0 if P is None else np.asarray(P, float)
    return encode_estimate(Estimate(float(t), x, P, method, "centre", track), src, seq)


def _horizontal_m(lon_lat_a, lat_lon_b) -> float:
    """Ground distance (m) between (lon, lat) and (lat, lon), by pymap3d's ENU at b."""
    e, n, _ = pymap3d.geodetic2enu(lon_lat_a[1], lon_lat_a[0], 0.0, lat_lon_b[0], lat_lon_b[1], 0.0, ell=WGS84,
                                   deg=True)
    return math.hypot(e, n)


def _valid_rfc7946(doc: dict) -> None:
    obj = geojson_pkg.loads(json.dumps(doc))
    assert obj.is_valid, obj.errors()
    assert doc["type"] == "FeatureCollection"
    for f in doc["features"]:
        g = f["geometry"]
        positions = [g["coordinates"]] if g["type"] == "Point" else g["coordinates"][0]
        for p in positions:
            assert -180 <= p[0] <= 180 and -90 <= p[1] <= 90  # [lon, lat(, alt)]
        if g["type"] == "Polygon":
            ring = np.array(g["coordinates"][0])
            area2 = np.dot(ring[:-1, 0], ring[1:, 1]) - np.dot(ring[1:, 0], ring[:-1, 1])
            assert area2 > 0, "an exterior ring must be counter-clockwise (RFC 7946 §3.1.6)"


def _same_position(coords, lon, lat, alt) -> None:
    """GeoJSON keeps 7 decimals of a degree (1 cm) and 2 of a metre."""
    np.testing.assert_allclose(coords[:2], [lon, lat], rtol=0, atol=6e-8)
    assert coords[2] == pytest.approx(alt, abs=0.006)


# -- the picture -----------------------------------------------------------------------------------


def test_picture_drops_bad_input_counts_it_and_is_unchanged():
    reject = RejectLog("x")
    pic = TrackTable(KEYS, reject, duration=100.0)
    good = _est(1.0, [10.0, 20.0], seq=1)
    assert pic.offer(KEYS.fused("fuser"), good) is not None
    before = {k: (e.t, e.x.tolist()) for k, e in pic.tracks.items()}
    nan = msgpack.packb({**msgpack.unpackb(_est(2.0, [1.0, 2.0], seq=2)), "x": [float("nan"), 2.0]})
    bad = {
        "key": (KEYS.truth("E1"), _est(2.0, [1.0, 2.0], seq=3)),
        "malformed": (KEYS.fused("fuser"), b"\x93garbage"),
        "non-finite": (KEYS.fused("fuser"), nan),
        "duplicate": (KEYS.fused("fuser"), good),
        "out-of-order": (KEYS.fused("fuser"), _est(0.5, [1.0, 2.0], seq=4)),
        "future": (KEYS.fused("fuser"), _est(1e6, [1.0, 2.0], seq=5)),
        "past": (KEYS.fused("fuser"), _est(-5.0, [1.0, 2.0], seq=6)),
        "kind": (KEYS.fused("fuser"), encode_downlink(Init("df1", Estimate(2.0, np.ones(2), np.eye(2), "EKF", "centre", "E1")),
                                               "fuser", 7)),
    }
    for cause, (key, data) in bad.items():
        assert pic.offer(key, data) is None, cause
        assert reject.by_cause[cause] == 1, (cause, dict(reject.by_cause))
    assert {k: (e.t, e.x.tolist()) for k, e in pic.tracks.items()} == before


def test_live_table_refuses_updates_ahead_of_the_clock_and_has_no_end():
    reject = RejectLog("x")
    now = 1_796_000_000.0
    table = TrackTable(KEYS, reject, duration=None, clock=lambda: now, max_skew=5.0)
    assert table.offer(KEYS.fused("fuser"), _est(now - 3600.0, [1.0, 2.0], seq=1)) is not None  # an hour old: fine
    assert table.offer(KEYS.fused("fuser"), _est(now + 4.0, [1.0, 2.0], seq=2)) is not None
    assert table.offer(KEYS.fused("fuser"), _est(now + 6.0, [1.0, 2.0], seq=3)) is None
    assert reject.by_cause == {"future": 1}


def test_picture_forgets_a_track_the_fused_stream_stopped_reporting():
    pic = TrackTable(KEYS, RejectLog("x"), delete_misses=3)
    for k in range(1, 9):
        pic.offer(KEYS.fused("fuser"), _est(k, [k, 0.0], track="E1", seq=2 * k))
        if k <= 2:
            pic.offer(KEYS.fused("fuser"), _est(k, [0.0, k], track="E2", seq=2 * k + 1))
    assert list(pic.tracks) == ["E1"]  # E2 missed frames 3, 4, 5: gone from frame 6 on


# -- GeoJSON -------------------------------------------------------------------------------------


def test_feature_collection_is_rfc7946_with_positions_from_pymap3d():
    sc = load_scenario("thesis-fixed-c1")
    frame = geo.frame_of(sc.origin)
    P = np.array([[9e4, 3e4], [3e4, 4e4]])
    fix = Estimate(12.0, np.array([15_000.0, 14_000.0]), P, "EKF", "centre", "E1")
    trk = Estimate(12.0, np.array([1_000.0, 2_000.0, 3_000.0, 50.0, 0.0, 0.0]), np.eye(6) * 25.0, "SS", "centre", "T1")
    doc = geojson.feature_collection([fix, trk], sensor_sites(sc), frame, live=False)
    _valid_rfc7946(doc)
    by = {(f["properties"]["id"], f["geometry"]["type"]): f for f in doc["features"]}
    for sid, s in sc.sensors.items():
        lat, lon, alt = pymap3d.enu2geodetic(*s.site.position(0.0), *sc.origin, ell=WGS84, deg=True)
        _same_position(by[(sid, "Point")]["geometry"]["coordinates"], lon, lat, alt)
        assert by[(sid, "Point")]["properties"]["kind"] == "sensor"
    lat, lon, alt = pymap3d.enu2geodetic(1_000.0, 2_000.0, 3_000.0, *sc.origin, ell=WGS84, deg=True)
    _same_position(by[("T1", "Point")]["geometry"]["coordinates"], lon, lat, alt)
    props = by[("E1", "Point")]["properties"]
    assert props == {"id": "E1", "method": "EKF", "time": 12.0, "kind": "fix",
                     "position_std_m": pytest.approx(math.sqrt(13e4), abs=1e-3)}
    ring = np.array(by[("E1", "Polygon")]["geometry"]["coordinates"][0])
    e, n, _ = pymap3d.geodetic2enu(ring[:, 1], ring[:, 0], 0.0, *sc.origin, ell=WGS84, deg=True)
    d = np.stack([e, n], axis=1) - fix.x
    from scipy.stats import chi2

    np.testing.assert_allclose(np.einsum("ij,jk,ik->i", d, np.linalg.inv(P), d), chi2.ppf(0.95, 2), rtol=1e-3)
    assert ("T1", "Polygon") not in by  # ellipses are the fixes'


def test_live_times_are_iso_8601_utc():
    frame = geo.frame_of((0.0, 0.0, 0.0))
    t = 1_796_000_000.25
    f = geojson.estimate_features(Estimate(t, np.zeros(2), np.eye(2), "EKF", "centre", "E1"), frame, live=True)[0]
    text = f["properties"]["time"]
    assert text.endswith("Z")
    assert dt.datetime.fromisoformat(text.replace("Z", "+00:00")).timestamp() == pytest.approx(t, abs=1e-3)


def test_write_atomic_replaces_the_file_and_leaves_no_temporary(tmp_path):
    path = tmp_path / "p.json"
    path.write_text("old")
    geojson.write_atomic(path, {"type": "FeatureCollection", "features": []})
    assert json.loads(path.read_text()) == {"type": "FeatureCollection", "features": []}
    assert [p.name for p in tmp_path.iterdir()] == ["p.json"]


# -- CoT -----------------------------------------------------------------------------------------


def test_cot_events_parse_with_type_point_errors_and_times():
    frame = geo.frame_of((51.5, -0.12, 10.0))
    P = np.diag([400.0, 100.0, 900.0, 1.0, 1.0, 1.0])
    e = Estimate(33.5, np.array([1000.0, -2000.0, 5000.0, 0.0, 100.0, 0.0]), P, "SS", "centre", "T1")
    now = 1_796_000_000.0
    ev = ET.fromstring(cot.track_event(e, frame, "zfusion.x.T1", cot.Types(), now, 45.0, live=False))
    assert ev.tag == "event" and ev.get("version") == "2.0" and ev.get("type") == "a-u-A" and ev.get("how") == "m-f"
    parse = lambda s: dt.datetime.fromisoformat(s.replace("Z", "+00:00")).timestamp()  # noqa: E731
    assert parse(ev.get("time")) == parse(ev.get("start")) == pytest.approx(now, abs=1e-3)
    assert parse(ev.get("stale")) - parse(ev.get("start")) == pytest.approx(45.0, abs=1e-3)
    pt = ev.find("point")
    lat, lon, alt = pymap3d.enu2geodetic(1000.0, -2000.0, 5000.0, 51.5, -0.12, 10.0, ell=WGS84, deg=True)
    assert float(pt.get("lat")) == pytest.approx(lat, abs=1e-6) and float(pt.get("lon")) == pytest.approx(lon, abs=1e-6)
    assert float(pt.get("hae")) == pytest.approx(alt, abs=0.1)
    assert float(pt.get("ce")) == pytest.approx(20.0) and float(pt.get("le")) == pytest.approx(30.0)
    assert float(ev.find("detail/track").get("course")) == pytest.approx(0.0)  # due north
    assert float(ev.find("detail/track").get("speed")) == pytest.approx(100.0)
    assert float(ev.find("detail/zfusion").get("t")) == 33.5
    fix = Estimate(7.0, np.array([0.0, 0.0]), np.eye(2), "EKF", "centre", "E1")
    ev = ET.fromstring(cot.track_event(fix, frame, "u", cot.Types(emitter="a-h-G"), now, 60.0, live=True))
    assert ev.get("type") == "a-h-G" and float(ev.find("point").get("le")) == cot.UNKNOWN
    assert parse(ev.get("start")) == pytest.approx(7.0, abs=1e-3)  # live: the time of validity, in UTC
    s = ET.fromstring(cot.sensor_event("radar2d", "radar2d", np.zeros(3), frame, "s", cot.Types(), now, 60.0))
    assert s.get("type") == "a-f-G-E-S-R" and s.find("detail/contact").get("callsign") == "radar2d"


@pytest.mark.parametrize("url", ["udp://host", "http://h:1", "tcp://:5", "udp://h:99999", "tcp://h:1/x"])
def test_bad_urls_are_refused(url):
    with pytest.raises(ValueError):
        cot.parse_url(url)


def _listen(port: int = 0) -> socket.socket:
    srv = socket.socket()
    srv.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    srv.bind(("127.0.0.1", port))
    srv.listen()
    srv.settimeout(5)
    return srv


def _read_events(conn: socket.socket, n: int) -> list[ET.Element]:
    buf = b""
    conn.settimeout(5)
    while buf.count(b"</event>") < n:
        chunk = conn.recv(65536)
        if not chunk:
            break
        buf += chunk
    return [ET.fromstring(p + b"</event>") for p in buf.split(b"</event>") if p.strip()]


def test_tcp_sender_reconnects_with_backoff_and_resends_the_picture():
    srv = _listen()
    port = srv.getsockname()[1]
    clock = [0.0]
    s = cot.TcpSender("127.0.0.1", port, clock=lambda: clock[0])
    ev = lambda uid, k: f'<event version="2.0" uid="{uid}" n="{k}"></event>'.encode()  # noqa: E731
    assert s.send("a", ev("a", 1)) and s.send("b", ev("b", 1))
    conn, _ = srv.accept()
    assert [e.get("uid") for e in _read_events(conn, 2)] == ["a", "b"]
    conn.close()
    srv.close()  # the server goes away
    for k in range(2, 20):  # a send after the peer closed fails (the first may still seem to go out)
        s.send("a", ev("a", k))
        if not s.connected:
            break
        time.sleep(0.05)
    assert not s.connected and s.failed >= 1
    s.poll()  # no try before BACKOFF_MIN_S has passed
    assert not s.connected
    clock[0] += cot.BACKOFF_MIN_S + 0.01
    s.poll()  # refused (the server is down): the next try waits twice as long (2 × BACKOFF_MIN_S)
    assert not s.connected
    srv = _listen(port)  # the server is back
    clock[0] += 1.5 * cot.BACKOFF_MIN_S
    s.poll()
    assert not s.connected  # still backing off
    clock[0] += 0.5 * cot.BACKOFF_MIN_S + 0.01
    s.poll()
    assert s.connected and s.connects == 2
    conn, _ = srv.accept()
    got = {e.get("uid"): e.get("n") for e in _read_events(conn, 2)}
    assert got == {"a": str(k), "b": "1"}  # the latest event of each uid
    conn.close()
    srv.close()
    s.close()


# -- processes -----------------------------------------------------------------------------------


def test_cli_mistakes_are_one_line_and_exit_2(tmp_path):
    for argv in (["export", "cot", "--to", "udp://nowhere", "--scenario", "patent-3d"],
                 ["export", "geojson", "--file", str(tmp_path / "no" / "g.json"), "--scenario", "patent-3d"],
                 ["export", "geojson", "--file", str(tmp_path / "g.json"), "--site", str(tmp_path / "none.toml")],
                 ["export", "cot", "--to", "udp://127.0.0.1:9", "--stale-s", "-1", "--scenario", "patent-3d"],
                 ["run", "--scenario", "patent-3d", "--cot", "tcp://h"]):
        p = zfusion(*argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        out, err = p.communicate(timeout=60)
        assert p.returncode == 2, (argv, err)
        assert len(err.strip().splitlines()) == 1 and err.startswith("zfusion "), err


def test_geojson_process_rides_through_a_fuser_restart_and_stops_cleanly(tmp_path, deployment):
    """The process over Zenoh: garbage is counted, a 'fuser' that goes and comes back with
    its seq from 1 again is followed, SIGTERM leaves the last picture and exit 0."""
    ep = f"tcp/127.0.0.1:{free_port()}"
    keys = KeySpace(deployment)
    path = tmp_path / "g.json"
    hub = zenoh.open(ZenohOptions(listen=[ep]).to_config())
    proc = zfusion("export", "geojson", "--file", str(path), "--scenario", "thesis-fixed-c1", "--deployment",
                   deployment, "--connect", ep, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        status: list[dict] = []
        sub = hub.declare_subscriber(keys.status("export-geojson"),
                                     lambda s: status.append(msgpack.unpackb(s.payload.to_bytes())))
        deadline = time.monotonic() + 30
        while not status and time.monotonic() < deadline:
            time.sleep(0.05)
        assert status, "the exporter never reported"
        for incarnation in range(2):  # the fuser, then the fuser restarted
            fuser = zenoh.open(ZenohOptions(connect=[ep]).to_config())
            pub = fuser.declare_publisher(keys.fused("fuser"), congestion_control=zenoh.CongestionControl.BLOCK,
                                          reliability=zenoh.Reliability.RELIABLE)
            deadline = time.monotonic() + 30  # the exporter's subscription reaches the new session
            while not pub.matching_status.matching and time.monotonic() < deadline:
                time.sleep(0.05)
            for k in range(1, 6):
                t = 10.0 * incarnation + k
                pub.put(_est(t, [15_000.0 + t, 15_000.0], seq=k))
            pub.put(b"garbage")
            # the exporter has taken it all before this 'fuser' goes (its status, once a second)
            wait_for(lambda: status[-1]["counters"].get("updates") == 5 * (incarnation + 1)
                     and status[-1]["counters"].get("rejected.malformed") == incarnation + 1,
                     f"the exporter took incarnation {incarnation}'s messages")
            pub.undeclare()
            fuser.close()
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline:
            doc = json.loads(path.read_text()) if path.exists() else {"features": []}
            fix = [f for f in doc["features"] if f["properties"]["id"] == "E1" and f["geometry"]["type"] == "Point"]
            if fix and fix[0]["properties"]["time"] == 15.0:
                break
            time.sleep(0.1)
        assert fix and fix[0]["properties"]["time"] == 15.0, doc
        _valid_rfc7946(doc)
        deadline = time.monotonic() + 15  # the next status reports both incarnations
        while time.monotonic() < deadline and status[-1]["counters"].get("updates") != 10:
            time.sleep(0.1)
        assert status[-1]["counters"]["rejected.malformed"] == 2
        assert status[-1]["counters"]["updates"] == 10
        proc.send_signal(signal.SIGTERM)
        out, err = proc.communicate(timeout=30)
        assert proc.returncode == 0, err[-2000:]
    finally:
        if proc.poll() is None:
            proc.kill()
        sub.undeclare()
        hub.close()


@pytest.mark.slow
def test_run_with_geojson_puts_the_fix_within_300_m_of_the_emitter(tmp_path, deployment):
    path = tmp_path / "g.json"
    p = zfusion("run", "--scenario", "thesis-fixed-c1", "--speed", "max", "--geojson", str(path),
                "--rrd", str(tmp_path / "r.rrd"), "--json", str(tmp_path / "s.json"), "--deployment", deployment,
                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    out, err = p.communicate(timeout=600)
    assert p.returncode == 0, err[-3000:]
    assert json.loads((tmp_path / "s.json").read_text())["exit_codes"]["export-geojson"] == 0  # stopped cleanly
    doc = json.loads(path.read_text())
    _valid_rfc7946(doc)
    sc = load_scenario("thesis-fixed-c1")
    points = {f["properties"]["id"]: f for f in doc["features"] if f["geometry"]["type"] == "Point"}
    for sid in sc.sensors:
        assert points[sid]["properties"]["kind"] == "sensor"
    fixes = [f for f in points.values() if f["properties"]["kind"] == "fix"]
    assert len(fixes) == 1 and fixes[0]["properties"]["time"] == sc.duration
    e0 = sc.targets["E1"].x0
    lat, lon, _ = pymap3d.enu2geodetic(e0[0], e0[1], 0.0, *sc.origin, ell=WGS84, deg=True)
    miss = _horizontal_m(fixes[0]["geometry"]["coordinates"], (lat, lon))
    assert miss < 300.0, miss
    assert any(f["geometry"]["type"] == "Polygon" and f["properties"]["id"] == fixes[0]["properties"]["id"]
               for f in doc["features"])


@pytest.mark.slow
def test_run_with_cot_over_udp_delivers_tracks_within_100_m_of_truth(tmp_path, deployment):
    rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    rx.bind(("127.0.0.1", 0))
    rx.settimeout(0.2)
    port = rx.getsockname()[1]
    datagrams: list[bytes] = []
    done = threading.Event()

    def receive() -> None:
        while not done.is_set():
            try:
                datagrams.append(rx.recv(65536))
            except socket.timeout:
                pass

    th = threading.Thread(target=receive, daemon=True)
    th.start()
    try:
        p = zfusion("run", "--scenario", "patent-3d", "--speed", "max", "--cot", f"udp://127.0.0.1:{port}",
                    "--rrd", str(tmp_path / "r.rrd"), "--deployment", deployment,
                    stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        out, err = p.communicate(timeout=600)
        assert p.returncode == 0, err[-3000:]
    finally:
        done.set()
        th.join()
        rx.setblocking(False)  # the run is over: what it sent is in the socket's buffer
        while True:
            try:
                datagrams.append(rx.recv(65536))
            except BlockingIOError:
                break
        rx.close()
    events = [ET.fromstring(d) for d in datagrams]  # each datagram is one whole XML event
    sc = load_scenario("patent-3d")
    sensors = [e for e in events if e.get("uid").endswith(tuple(f"sensor.{s}" for s in sc.sensors))]
    assert {e.find("detail/contact").get("callsign") for e in sensors} == set(sc.sensors)
    tracks = [e for e in events if e.find("detail/zfusion[@kind='track']") is not None]
    assert len(tracks) > 10
    # a track's uid names its fuser: two fusers' tracks never share one in a TAK server
    assert {ev.get("uid") for ev in tracks} == {f"zfusion.{deployment}.fuser.{ev.find('detail/zfusion').get('track')}"
                                                for ev in tracks}
    truth = truth_function(sc)
    misses = []
    for ev in tracks:
        assert ev.get("type") == "a-u-A" and ev.get("version") == "2.0"
        t = float(ev.find("detail/zfusion").get("t"))
        x = truth(0, ev.find("detail/zfusion").get("track"), t)
        lat, lon, _ = pymap3d.enu2geodetic(*x[:3], *sc.origin, ell=WGS84, deg=True)
        pt = ev.find("point")
        misses.append(_horizontal_m((float(pt.get("lon")), float(pt.get("lat"))), (lat, lon)))
    assert max(misses) < 100.0, sorted(misses)[-5:]


def test_an_exporter_started_mid_session_begins_with_the_fusers_picture(tmp_path, deployment):
    """No update on ``fused`` at all: the file gets the track a 'fuser' answers the picture query with."""
    from schemas import encode

    ep = f"tcp/127.0.0.1:{free_port()}"
    keys = KeySpace(deployment)
    path = tmp_path / "g.json"
    hub = zenoh.open(ZenohOptions(listen=[ep]).to_config())

    def on_query(q) -> None:
        q.reply(keys.picture("fuser"), _est(7.0, [15_000.0, 15_000.0], track="E3", seq=41))
        q.reply(keys.picture("fuser"), encode("watermark", "fuser", 0, 7.0, final=False))

    queryable = hub.declare_queryable(keys.picture("fuser"), on_query)
    proc = zfusion("export", "geojson", "--file", str(path), "--scenario", "thesis-fixed-c1", "--deployment",
                   deployment, "--connect", ep, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 30
        ids: set = set()
        while "E3" not in ids and time.monotonic() < deadline:
            time.sleep(0.1)
            if path.exists():
                ids = {f["properties"]["id"] for f in json.loads(path.read_text())["features"]}
        assert "E3" in ids
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=30)
        assert proc.returncode == 0, err[-2000:]
    finally:
        if proc.poll() is None:
            proc.kill()
        queryable.undeclare()
        hub.close()


def test_cot_process_reconnects_to_a_tcp_server_that_dropped_it(deployment):
    """The real process: a TAK-like server takes the sensors' events, drops the connection,
    and is dialled again (sensors are re-sent every --stale-s / 2)."""
    srv = _listen()
    port = srv.getsockname()[1]
    srv.settimeout(30)
    proc = zfusion("export", "cot", "--to", f"tcp://127.0.0.1:{port}", "--stale-s", "1", "--scenario", "patent-3d",
                   "--deployment", deployment, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        sensors = set(load_scenario("patent-3d").sensors)
        for _ in range(2):  # the first connection, then the one after the drop
            conn, _ = srv.accept()
            got = {e.find("detail/contact").get("callsign") for e in _read_events(conn, len(sensors))}
            assert got == sensors
            conn.close()
        proc.send_signal(signal.SIGTERM)
        out, err = proc.communicate(timeout=30)
        assert proc.returncode == 0, err[-2000:]
    finally:
        if proc.poll() is None:
            proc.kill()
        srv.close()
