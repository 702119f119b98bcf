"""Real air traffic end to end: a local web server replays the Paris recording
(the ``traffic`` package's quickstart collection, an hour in: 22 aircraft) as readsb's
``aircraft.json`` in real time; ``zfusion ingest adsb --url`` polls it and a live
``zfusion fuser --site`` tracks what it publishes. Within 60 s ``zfusion picture`` must
hold a confirmed track within 200 m of every aircraft the server has listed for at least
30 s, against the recording's smoothed trajectory (sensors_sim/recorded.py) at the
track's time. The same through ``--sbs``: a BaseStation feed on loopback sending each
new position as a ``MSG,3`` line (after a ``MSG,1`` with the callsign) as it is heard.

The server lists each airborne aircraft with its latest new position at or before the
replayed time (``seen_pos`` its age), its barometric altitude and callsign, as readsb
would; NACp 7 (σ ≈ 76 m per axis): a recorded position is tagged to the second after it
was heard, up to a second late. The site's tracker is the frame-by-frame many-target
tracker over 0.9 s frames (one report per aircraft each), so one receiver's reports
confirm a track.
"""

from __future__ import annotations

import json
import signal
import socket
import subprocess
import sys
import threading
import time
from datetime import datetime, timezone

import numpy as np
import pytest

from _ingest_helpers import Capture, DocServer, TcpServer, adsb_site_toml
from fusion.geodetic import LocalFrame
from sensors_sim.recorded import FT, RecordedTraffic, Recording, read_traffic_json, traffic_sample

pytestmark = pytest.mark.slow

ORIGIN = (48.85, 2.45, 0.0)
OFFSET = 3600.0  # s into the recording
REPLAY = 75.0  # s replayed
DEADLINE, LISTED, NEAR = 60.0, 30.0, 200.0

SITE = adsb_site_toml(ORIGIN, {"kind": "adsb", "period_s": 1.0, "std_pos_m": 76.0, "std_alt_m": 40.0},
                      {"motion": "ca", "q": 0.5, "association": "gnn", "gate_prob": 0.999, "confirm_m": 3, "confirm_n": 4,
                       "delete_misses": 3, "max_pos_std": 2000.0, "pair_tol": 0.9, "init_vel_std": 300.0,
                       "init_vel_std_up": 30.0, "init_acc_std": 10.0, "init_acc_std_up": 1.0},
                      "an ADS-B receiver near Paris")


class Replay:
    """The recording's airborne aircraft from ``t_first`` on, each as its new positions
    (a state vector repeats the last one heard): ``doc(tau)`` is the aircraft.json of
    replay time ``tau``."""

    def __init__(self, records, t_first: float):
        keep = (records.t >= t_first) & (records.t <= t_first + REPLAY) & ~records.ground & np.isfinite(records.alt)
        self.rows: dict[str, list] = {}
        for i in np.flatnonzero(keep):
            rows = self.rows.setdefault(str(records.id[i]), [])
            if rows and (rows[-1][1], rows[-1][2]) == (records.lat[i], records.lon[i]):
                continue
            rows.append((float(records.t[i] - t_first), float(records.lat[i]), float(records.lon[i]),
                         float(records.alt[i]), str(records.callsign[i])))
        self.times = {a: np.array([r[0] for r in rows]) for a, rows in self.rows.items()}

    def heard(self, aircraft: str, tau: float) -> int:
        """The index of the aircraft's latest position at or before ``tau`` (−1: none)."""
        return int(np.searchsorted(self.times[aircraft], tau, side="right")) - 1

    def doc(self, now: float, tau: float) -> bytes:
        out = []
        for a, rows in self.rows.items():
            k = self.heard(a, tau)
            if k < 0 or tau - rows[k][0] > 30.0:  # not heard yet, or gone
                continue
            t, lat, lon, alt, callsign = rows[k]
            out.append({"hex": a, "flight": callsign, "type": "adsb_icao", "lat": lat, "lon": lon,
                        "alt_baro": round(alt / FT), "seen_pos": round(tau - t, 3), "nac_p": 7})
        return json.dumps({"now": now, "messages": 0, "aircraft": out}).encode()

    def sbs(self, wall0: float, after: float, tau: float) -> str:
        """The BaseStation lines of the positions heard in ``(after, tau]``, stamped with
        their wall time (UTC), each aircraft's callsign first."""
        out = []
        for a, rows in self.rows.items():
            for t, lat, lon, alt, callsign in rows:
                if after < t <= tau:
                    stamp = datetime.fromtimestamp(wall0 + t, timezone.utc)
                    d, c = stamp.strftime("%Y/%m/%d"), stamp.strftime("%H:%M:%S.%f")[:12]
                    if callsign:
                        out.append(f"MSG,1,1,1,{a.upper()},1,{d},{c},{d},{c},{callsign},,,,,,,,,,,0\r\n")
                    out.append(f"MSG,3,1,1,{a.upper()},1,{d},{c},{d},{c},,{round(alt / FT)},,,{lat},{lon},,,0,0,0,0\r\n")
        return "".join(out)

    def listed(self, tau: float, since: float) -> list[str]:
        """The aircraft listed from ``since`` or earlier and still heard within 5 s of ``tau``."""
        return [a for a, t in self.times.items() if t[0] <= since and 0 <= self.heard(a, tau)
                and tau - t[self.heard(a, tau)] <= 5.0]


def picture(cap: Capture) -> dict:
    got = subprocess.run([sys.executable, "-m", "services.cli", "picture", "--deployment", cap.keys.deployment,
                          "--connect", cap.endpoint, "--timeout", "3"], capture_output=True, text=True, timeout=60)
    assert got.returncode == 0, got.stderr[-2000:]
    return json.loads(got.stdout)


class Feed(TcpServer):
    """A receiver's BaseStation port replaying the recording: each client gets the
    positions heard since it connected, as they are heard."""

    replay: Replay
    wall0: float

    def handle(self, conn: socket.socket, n: int) -> None:
        after = time.time() - self.wall0
        while not self.closing.wait(0.2):
            tau = time.time() - self.wall0
            conn.sendall(self.replay.sbs(self.wall0, after, tau).encode())
            after = tau


@pytest.mark.parametrize("source", ["url", "sbs"])
def test_a_replayed_recording_is_tracked_through_ingest_and_a_live_fuser(tmp_path, deployment, source):
    try:
        records = read_traffic_json(traffic_sample())
    except FileNotFoundError:
        pytest.skip("traffic is not installed (pip install --no-deps traffic==2.13)")
    t_first = float(records.t.min()) + OFFSET
    replay = Replay(records, t_first)
    frame = LocalFrame(*ORIGIN, deg=True)
    truth = RecordedTraffic(Recording(records, frame, window=(t_first, t_first + REPLAY)), t_first)
    site = tmp_path / "site.toml"
    site.write_text(SITE)
    stop = threading.Event()
    procs: list[subprocess.Popen] = []
    with DocServer() as srv, Feed() as feed, Capture(deployment) as cap:
        wall0 = feed.wall0 = time.time()
        feed.replay = replay

        def serve():
            while not stop.is_set():
                now = time.time()
                srv.docs["/data/aircraft.json"] = replay.doc(now, now - wall0)
                stop.wait(0.2)

        server = threading.Thread(target=serve, daemon=True)
        server.start()
        fabric = ["--deployment", deployment, "--connect", cap.endpoint]
        try:
            for args in (["fuser", "--site", str(site)],
                         ["ingest", "adsb", "--id", "rx", "--site", str(site),
                          *(["--url", f"{srv.url}/data/aircraft.json", "--poll-s", "0.5"] if source == "url" else
                            ["--sbs", f"127.0.0.1:{feed.port}", "--sbs-timezone", "UTC"])]):
                procs.append(subprocess.Popen([sys.executable, "-m", "services.cli", *args, *fabric],
                                              stderr=subprocess.PIPE, text=True))
            missing, tracks, tau = None, [], 0.0
            while time.time() - wall0 < DEADLINE and any(p.poll() is None for p in procs):
                if time.time() - wall0 < LISTED + 2.0:
                    time.sleep(0.5)
                    continue
                doc = picture(cap)
                tau = time.time() - wall0
                tracks = [(tr["t"] - wall0, np.array(tr["x"][:3])) for tr in doc["tracks"]]
                missing = {}
                for a in replay.listed(tau, tau - LISTED):
                    rows = np.flatnonzero(truth.ids == a)
                    seg = rows[np.searchsorted(truth.t0[rows], tau, side="right") - 1]
                    d = [np.linalg.norm(x - truth.kinematics([seg], [t])[0][0]) for t, x in tracks]
                    if min(d, default=np.inf) >= NEAR:
                        missing[a] = min(d, default=None)
                if not missing:
                    break
            assert all(p.poll() is None for p in procs), [p.stderr.read()[-2000:] for p in procs]
            assert missing == {} and replay.listed(tau, tau - LISTED), (missing, len(tracks), tau)
        finally:
            stop.set()
            for p in procs:
                if p.poll() is None:
                    p.send_signal(signal.SIGTERM)
            errs = [p.communicate(timeout=20)[1] for p in procs]
    assert all(p.returncode == 0 for p in procs) and not any("Traceback" in e for e in errs), [e[-2000:] for e in errs]
