"""Real sensors, end to end: KrakenSDR stations (served or POSTing like the device) and
JSON-line sensors through ``zfusion ingest`` gateways into a live ``zfusion fuser
--site``, over real Zenoh sessions.

DF: the emitter's fix must be within 3× the Cramér–Rao bound of the bearings the fuser
had (fusion/df/crb.py) — through ``/DOA_value.html``, ``/doa.xml`` and Kraken Pro POSTs,
and with a mobile station whose position and heading change in its messages. 3D: a 2D
radar and an angle sensor's emulated measurements, sent as JSON lines, give the track
the in-process estimator gives on the same measurements, to 1e-9.
"""

from __future__ import annotations

import json
import math
import subprocess
import sys
import threading
import time
import urllib.request

import numpy as np
import pytest

from _ingest_helpers import Capture, DocServer, Processes, kraken_csv, kraken_json, kraken_xml
from fusion.df.crb import crb_rmse
from fusion.geodetic import LocalFrame
from schemas import to_estimate, to_measurement
from services.launcher import free_port

pytestmark = pytest.mark.slow

ORIGIN = (21.0285, 105.8542, 0.0)
FRAME = LocalFrame(*ORIGIN, deg=True)
EMITTER = np.array([5000.0, 8000.0])
SIGMA_DEG = 1.0
STATIONS = {"df1": ((0.0, 0.0), 0.0), "df2": ((12000.0, 0.0), 90.0), "df3": ((0.0, 14000.0), 200.0)}
FRAMES, FRAME_S = 24, 0.5


def site_file(tmp_path, stations: dict[str, tuple | None]) -> str:
    """A site file: DF stations pinned at ENU positions, or (None) with their site in
    the messages."""
    lines = ['description = "ingest e2e"', "[origin]", f"lat_deg = {ORIGIN[0]}", f"lon_deg = {ORIGIN[1]}",
             f"alt_m = {ORIGIN[2]}", "[defaults]", 'topology = "centralised"', 'method = "EKF"', "[tracker]",
             f"sigma = {math.radians(SIGMA_DEG)!r}"]
    for sid, pos in stations.items():
        lines += [f"[sensors.{sid}]", 'kind = "df"', "period_s = 0.5", f"std_az_deg = {SIGMA_DEG}",
                  f"pos_m = [{pos[0]}, {pos[1]}, 0.0]" if pos is not None else 'site = "messages"']
    path = tmp_path / "site.toml"
    path.write_text("\n".join(lines) + "\n")
    return str(path)


def true_bearing_deg(site_en) -> float:
    d = EMITTER - np.asarray(site_en)[:2]
    return math.degrees(math.atan2(d[0], d[1])) % 360.0


class Session(Processes):
    """The capture hub, the gateways and a live fuser (:class:`Processes`)."""

    def __init__(self, deployment: str, site: str):
        super().__init__(deployment)
        self.site = site

    def fuser(self, *extra: str) -> None:
        self.start("fuser", "fuser", "--site", self.site, *extra)

    def report(self) -> dict:
        """What each process says (for a failing assertion's message)."""
        return {src: (len(self.cap.of("bearing", src)), self.cap.status(src).get("counters"),
                      self.cap.status(src).get("sources")) for src in [*self.procs, "fuser"]}


def released_all(cap: Capture, timeout: float = 30.0) -> bool:
    """Wait until the fuser's last fix is as late as the last bearing published: every
    epoch has been released (after the gateways' heartbeats and the fuser's bounded wait)."""

    def done() -> bool:
        fixes, bearings = cap.of("track", "fuser"), cap.of("bearing")
        return bool(fixes and bearings) and fixes[-1].t >= max(m.t for m in bearings)

    return cap.wait(done, timeout=timeout)


def check_fix(cap: Capture) -> dict:
    """The fuser's last fix against 3× the CRB of the bearings up to its time."""
    fixes = [to_estimate(m) for m in cap.of("track", "fuser")]
    assert fixes, "no fix published"
    fix = fixes[-1]
    meas = [to_measurement(m) for m in cap.of("bearing")]
    used = [m for m in meas if m.t <= fix.t]
    bound = crb_rmse(EMITTER, np.array([m.site for m in used]), np.array([m.std[0] for m in used]))
    err = float(np.linalg.norm(fix.x[:2] - EMITTER))
    assert err <= 3.0 * bound, f"fix {fix.x[:2]} is {err:.1f} m off, 3 x CRB = {3 * bound:.1f} m ({len(used)} bearings)"
    return {"err_m": err, "crb_m": bound, "bearings": len(used), "fixes": len(fixes)}


def feed(frames: int, publish) -> list[float]:
    """``publish(t, k)`` for each frame ``k`` at its time; returns the frame times."""
    times = []
    for k in range(frames):
        t = time.time()
        publish(t, k)
        times.append(t)
        time.sleep(FRAME_S)
    return times


def noisy(rng, sid) -> float:
    return true_bearing_deg(STATIONS[sid][0]) + rng.normal(0.0, SIGMA_DEG)


@pytest.mark.parametrize("encoding", ["csv", "xml"])
def test_three_polled_stations_fix_the_emitter_within_3_crb(deployment, tmp_path, encoding):
    site = site_file(tmp_path, {s: pos for s, (pos, _) in STATIONS.items()})
    page = {"csv": "/DOA_value.html", "xml": "/doa.xml"}[encoding]
    make = {"csv": lambda t, b, h: kraken_csv(t, [b], heading=h), "xml": lambda t, b, h: kraken_xml(t, b, heading=h)}
    rng = np.random.default_rng(11)
    with DocServer() as srv, Session(deployment, site) as s:
        s.fuser("--method", "EKF")
        for sid in STATIONS:
            s.start(sid, "ingest", "krakensdr", "--id", sid, "--site", site, "--url", f"{srv.url}/{sid}{page}",
                    "--format", encoding, "--poll-s", "0.1")
        s.ready([*STATIONS, "fuser"])

        def publish(t, k):
            for sid, (_, heading) in STATIONS.items():
                srv.docs[f"/{sid}{page}"] = make[encoding](t, noisy(rng, sid), heading)

        feed(FRAMES, publish)
        # The first frames may go by while a gateway backs off from the 404 page before them.
        assert s.cap.wait(lambda: len(s.cap.of("bearing")) >= 3 * (FRAMES - 4), timeout=20), s.report()
        assert released_all(s.cap), s.report()
        result = check_fix(s.cap)
    assert result["bearings"] >= 3 * (FRAMES - 4)


def test_three_posting_stations_fix_the_emitter_within_3_crb(deployment, tmp_path):
    site = site_file(tmp_path, {s: pos for s, (pos, _) in STATIONS.items()})
    ports = {sid: free_port() for sid in STATIONS}
    rng = np.random.default_rng(12)
    with Session(deployment, site) as s:
        s.fuser("--method", "EKF")
        for sid in STATIONS:
            s.start(sid, "ingest", "krakensdr", "--id", sid, "--site", site, "--listen", f"127.0.0.1:{ports[sid]}")
        s.ready([*STATIONS, "fuser"])

        def post(sid, body):
            req = urllib.request.Request(f"http://127.0.0.1:{ports[sid]}/doapost", data=body,
                                         headers={"Content-Type": "application/json"})
            with urllib.request.urlopen(req, timeout=5) as r:
                assert r.status == 200

        def publish(t, k):
            for sid, (_, heading) in STATIONS.items():
                post(sid, kraken_json(t, noisy(rng, sid), heading=heading))

        feed(FRAMES, publish)
        assert s.cap.wait(lambda: len(s.cap.of("bearing")) == 3 * FRAMES, timeout=20), s.report()
        assert released_all(s.cap), s.report()
        check_fix(s.cap)


def test_a_mobile_station_moves_and_turns_in_its_messages(deployment, tmp_path):
    """Station m1 drives east at 100 m/s, its heading (the array's reference) swinging
    ±30° about its track: its messages carry lat/lon/heading, the gateway publishes each
    bearing from where the message says, as a bearing from true north."""
    site = site_file(tmp_path, {"m1": None, "df3": STATIONS["df3"][0]})
    rng = np.random.default_rng(13)
    sent: list[tuple[float, np.ndarray, float]] = []  # (t, ENU site, published az in degrees)
    with DocServer() as srv, Session(deployment, site) as s:
        s.fuser("--method", "EKF")
        for sid in ("m1", "df3"):
            s.start(sid, "ingest", "krakensdr", "--id", sid, "--site", site, "--url",
                    f"{srv.url}/{sid}/DOA_value.html", "--poll-s", "0.1")
        s.ready(["m1", "df3", "fuser"])

        def publish(t, k):
            enu = np.array([-6000.0 + 100.0 * FRAME_S * k, -2000.0, 0.0])
            lat, lon, _ = FRAME.to_geodetic(enu)
            heading = 90.0 + 30.0 * math.sin(k / 3.0)
            b = true_bearing_deg(enu) + rng.normal(0.0, SIGMA_DEG)
            srv.docs["/m1/DOA_value.html"] = kraken_csv(t, [b], heading=heading, lat=float(lat), lon=float(lon))
            srv.docs["/df3/DOA_value.html"] = kraken_csv(t, [noisy(rng, "df3")], heading=STATIONS["df3"][1])
            sent.append((round(t * 1000) / 1000, FRAME.to_enu(float(lat), float(lon), ORIGIN[2]), b % 360))

        feed(FRAMES, publish)
        # Most frames: a poll every 0.1 s of a page that changes every 0.5 s, but a machine
        # under load (18 on two cores) was seen to miss 3 to 5 of the 24; what is checked
        # here is where each published bearing is from, not that every frame was caught.
        assert s.cap.wait(lambda: len(s.cap.of("bearing", "m1")) >= FRAMES // 2, timeout=20), s.report()
        assert released_all(s.cap), s.report()
        check_fix(s.cap)
    got = {m.t: m for m in map(to_measurement, s.cap.of("bearing", "m1"))}
    matched = [(got[t], site, az) for t, site, az in sent if t in got]
    assert len(matched) >= FRAMES // 2
    for m, site, az in matched:
        assert np.allclose(m.site, site, atol=1e-6)  # the message's position, in the site's frame
        assert abs((math.degrees(m.z[0]) - az + 180) % 360 - 180) < 1e-6  # heading + (360 − θ)
    # it did move: n distinct frames caught span at least n - 1 of its 50 m steps (less a
    # centimetre: its lat/lon is placed back at the origin's altitude, so its east steps
    # are 50 m to the Earth's curvature; all 24 frames span 1,149.9987 m)
    assert np.ptp([m.site[0] for m, _, _ in matched]) >= 100.0 * FRAME_S * (len(matched) - 1) - 0.01


def test_jsonl_radar_and_angle_sensor_give_the_in_process_track(deployment):
    """patent-3d's 2D radar (range_az) and angle sensor (azel): their emulated
    measurements, shifted to UTC and sent as JSON lines in real time through two
    gateways, make the live fuser's SS track equal the in-process SS run on the
    measurements the gateways published, to 1e-9."""
    from sensors_sim import load_scenario, sensor_events
    from services.evaluation import run_method

    scenario = load_scenario("patent-3d")
    n_scans = 16
    emitted = {sid: [ev.measurement for ev in sensor_events(scenario, sid)
                     if ev.measurement is not None and ev.t < n_scans] for sid in ("radar2d", "angle")}
    with Session(deployment, "patent-3d") as s:
        s.fuser("--method", "SS")
        gws = {}
        for sid in emitted:
            s.procs[sid] = gws[sid] = subprocess.Popen(
                [sys.executable, "-m", "services.cli", "ingest", "jsonl", "--id", sid, "--site", "patent-3d",
                 "--watermark-lag", "1", "--deployment", deployment, "--connect", s.cap.endpoint],
                stdin=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        s.ready([*emitted, "fuser"])
        t0 = math.floor(time.time()) + 2.0  # the first scan: an integer, so t0 + t is exact
        streams = {}
        for sid, ms in emitted.items():
            streams[sid] = []
            for m in ms:
                d = {"t": t0 + m.t, "kind": m.kind, "az_deg": math.degrees(m.z[0])}
                d.update({"range_m": float(m.z[1])} if m.kind == "range_az" else {"el_deg": math.degrees(m.z[1])})
                streams[sid].append((t0 + m.t, json.dumps(d) + "\n"))

        def pace(sid):
            for t, line in streams[sid]:
                time.sleep(max(0.0, t - time.time()))
                gws[sid].stdin.write(line)
                gws[sid].stdin.flush()

        threads = [threading.Thread(target=pace, args=(sid,)) for sid in streams]
        for th in threads:
            th.start()
        for th in threads:
            th.join()
        for g in gws.values():
            g.stdin.close()  # the end of the input: each gateway promises what it sent, and exits 0
            g.stdin = None
        for g in gws.values():
            assert g.wait(timeout=30) == 0
        last = t0 + n_scans - 1
        assert s.cap.wait(lambda: any(to_estimate(m).t >= last for m in s.cap.of("track", "fuser")), timeout=30)
    published = sorted((to_measurement(m) for m in s.cap.of("range_az") + s.cap.of("azel")),
                       key=lambda m: m.order_key)
    assert len(published) == sum(len(v) for v in streams.values())
    ref = {(e.track, e.t): e for e in run_method(scenario, "SS", measurements=published)}
    got = {}
    for e in map(to_estimate, s.cap.of("track", "fuser")):
        got[(e.track, e.t)] = e  # a re-published estimate (after an OOSM) replaces the first
    common = sorted(set(ref) & set(got), key=lambda k: k[1])
    assert len(common) >= n_scans - 2 and common[-1][1] >= last - 1
    for k in common:
        np.testing.assert_allclose(got[k].x, ref[k].x, rtol=0, atol=1e-9)
        np.testing.assert_allclose(got[k].P, ref[k].P, rtol=0, atol=1e-9)
    # The scenario's own run (times from 0) is the same track: only t0 + t and the degrees
    # of the lines stand between them.
    emulated = {(e.track, e.t + t0): e for e in run_method(scenario, "SS") if e.t < n_scans}
    for k in common:
        np.testing.assert_allclose(got[k].x[:3], emulated[k].x[:3], rtol=0, atol=1e-6)
