"""``zfusion ingest asterix``: datagrams on a loopback UDP port, and a pcap replayed at
``--speed max``, to measurements and watermarks on Zenoh; a user's mistake is one line
and exit 2. Every wait is a poll with a deadline."""

from __future__ import annotations

import math
import socket
import subprocess
import sys
import time

import pytest
import zenoh
from _ingest_helpers import Capture, gateway, stop

from schemas import asterix as ax
from schemas import decode
from sensors_sim import load_site
from services.ingest.asterix import pcap_file, radars
from services.ingest.gateway import local_frame
from services.launcher import free_port
from services.node import ZenohOptions

NM = 1852.0
SITE = """
[origin]
lat_deg = 52.0
lon_deg = 4.0
alt_m = 0.0

[defaults]
topology = "centralised"
method = "EKF"

[tracker]

[sensors.r2d]
kind = "radar2d"
pos_km = [60, 0, 0.05]
rotation_period_s = 4.0
std_az_deg = 0.1
std_range_m = 50
sac_sic = [25, 1]

[sensors.r3d]
kind = "radar3d"
pos_km = [-30, 60, 0.02]
rotation_period_s = 6.0
std_az_deg = 0.2
std_el_deg = 0.3
std_range_m = 80
sac_sic = [25, 2]
"""


@pytest.fixture
def site(tmp_path):
    p = tmp_path / "site.toml"
    p.write_text(SITE)
    return p


def ingest(*args: str, capture: Capture) -> subprocess.Popen:
    return gateway("asterix", "--id", "gw", *args, capture=capture)


def tod(t: float) -> float:
    return t % 86400.0


def plot(sic: int, t: float, k: int = 0, **kw) -> ax.TargetReport:
    # ρ and θ on I048/040's grid: they cross the wire unchanged
    return ax.TargetReport(sac=25, sic=sic, tod=round(tod(t) * 128) / 128, rho=(7680 + k) * NM / 256,
                           theta=(1000 + k) * 2 * math.pi / 65536, **kw)


@pytest.mark.slow
def test_udp_datagrams_to_measurements(deployment, site):
    rs = radars(load_site(site), local_frame(load_site(site)))
    port = free_port()
    with Capture(deployment) as cap:
        p = ingest("--site", str(site), "--udp", f"127.0.0.1:{port}", capture=cap)
        try:
            assert cap.wait(lambda: cap.status("gw").get("state") == "running", timeout=30), p.stderr
            deadline = time.monotonic() + 20
            k = 0
            while (len(cap.of("range_az")) < 3 or not cap.of("az_el_range")) and time.monotonic() < deadline:
                now = time.time()
                d = ax.encode([plot(1, now - 0.5, k), plot(2, now - 0.5, k, flight_level=200.0),
                               ax.TargetReport(sac=99, sic=1, tod=tod(now), rho=1e3, theta=0.0)])[0]
                with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
                    s.sendto(d, ("127.0.0.1", port))
                    s.sendto(b"\x30\x00\x09garbage", ("127.0.0.1", port))
                k += 1
                time.sleep(0.2)
            assert cap.wait(lambda: cap.status("gw").get("counters", {}).get("rejected.unknown-source", 0) >= 1)
        finally:
            stop(p)
    for m in cap.of("range_az"):
        k = round(m.body["range"] * 256 / NM) - 7680  # which datagram it came in
        assert m.src == "r2d" and abs(time.time() - m.t) < 60
        assert [m.body["az"], m.body["range"]] == pytest.approx(
            rs[(25, 1)].to_site((1000 + k) * 2 * math.pi / 65536, (7680 + k) * NM / 256), abs=1e-9)
    m3 = cap.of("az_el_range")[0]
    z3 = [m3.body["az"], m3.body["el"], m3.body["range"]]
    assert m3.src == "r3d" and rs[(25, 2)].from_site(z3)[2] == pytest.approx(200 * 100 * 0.3048, abs=1e-3)
    counters = cap.status("gw")["counters"]
    assert counters["rejected.unknown-source"] >= 1 and counters["rejected.truncated"] >= 1  # the garbage
    assert counters["records.cat048"] >= 9


def feed(tmp_path, t0: float = 1_764_633_600.0 - 2.0):
    """A pcap of 30 CAT048 plots of r2d, each with its sector crossing, 0.1 s apart from ``t0``."""
    packets = []
    for k in range(30):
        t = t0 + 0.1 * k
        recs = [plot(1, t, k), ax.ServiceMessage(sac=25, sic=1, message_type=ax.SECTOR_CROSSING,
                                                 tod=round(tod(t + 0.05) * 128) / 128)]
        packets.append((t + 0.2, ax.encode(recs)[0]))  # received 0.2 s after the plot
    cap_file = tmp_path / "feed.pcap"
    cap_file.write_bytes(pcap_file(packets))
    return cap_file


@pytest.mark.slow
def test_a_pcap_replayed_at_full_speed(deployment, site, tmp_path):
    cap_file = feed(tmp_path)  # two seconds before midnight: the replay crosses it
    with Capture(deployment) as cap:
        p = ingest("--site", str(site), "--pcap", str(cap_file), "--speed", "max", "--watermark-lag", "0",
                   capture=cap)
        _, err = p.communicate(timeout=60)
        assert p.returncode == 0, err[-3000:]
        assert cap.wait(lambda: cap.status("gw").get("state") == "done")
        assert cap.wait(lambda: len(cap.of("range_az")) == 30)
    times = [m.t for m in cap.of("range_az")]
    want = [1_764_633_600.0 - 2.0 + 0.1 * k for k in range(30)]
    assert times == pytest.approx(want, abs=1 / 256)  # across midnight, on the capture's clock
    assert cap.of("watermark", "r2d")[-1].t == times[-1]  # the end of the capture promises all


@pytest.mark.slow
def test_a_replay_waits_for_its_consumer(deployment, site, tmp_path):
    """``--wait-for taker``: the replay starts once a process ``taker`` has announced
    itself (after its subscriber, as every zfusion process does), so the taker, which
    came up only after the gateway said it was waiting, hears every plot. Without the
    wait the replay, over in milliseconds, would be gone before the taker was there."""
    with Capture(deployment) as cap:
        p = ingest("--site", str(site), "--pcap", str(feed(tmp_path)), "--speed", "max", "--watermark-lag", "0",
                   "--wait-for", "taker", capture=cap)
        try:
            assert cap.wait(lambda: cap.status("gw").get("state") == "starting", timeout=30), p.stderr
            heard = []
            taker = zenoh.open(ZenohOptions(connect=[cap.endpoint]).to_config())
            try:
                sub = taker.declare_subscriber(cap.keys.meas("r2d"), lambda s: heard.append(decode(s.payload.to_bytes())))
                token = taker.liveliness().declare_token(cap.keys.alive("taker", str(taker.zid())))
                assert cap.wait(lambda: sum(m.kind == "range_az" for m in heard) == 30, timeout=30), len(heard)
                token.undeclare()
                sub.undeclare()
            finally:
                taker.close()
            _, err = p.communicate(timeout=30)
            assert p.returncode == 0, err[-3000:]
        finally:
            if p.poll() is None:
                stop(p)
    assert [m.t for m in heard if m.kind == "range_az"] == [m.t for m in cap.of("range_az")]


@pytest.mark.slow
def test_sigterm_while_it_waits_is_a_clean_stop(deployment, site, tmp_path):
    """Stopped while it waits for a process that never comes: it says "stopped" at once,
    exits 0 and publishes nothing (not "gave up waiting", exit 2). The exit's bound is
    one a loaded host keeps (test_sensor_process.py's twin says why)."""
    with Capture(deployment) as cap:
        p = ingest("--site", str(site), "--pcap", str(feed(tmp_path)), "--speed", "max", "--wait-for", "nobody",
                   capture=cap)
        assert cap.wait(lambda: cap.status("gw").get("state") == "starting", timeout=30), p.stderr
        t = time.monotonic()
        err = stop(p)
        assert time.monotonic() - t < 5.0 and "gave up" not in err, err
    assert not cap.of("range_az")


def test_mistakes_are_one_line_and_exit_2(tmp_path, site):
    no_radar = tmp_path / "none.toml"
    no_radar.write_text(SITE.replace("sac_sic = [25, 1]\n", "").replace("sac_sic = [25, 2]\n", ""))
    not_pcap = tmp_path / "x.pcap"
    not_pcap.write_bytes(b"not a capture at all, not even close")
    for args, says in ((["--site", str(no_radar), "--udp", "127.0.0.1:1"], "sac_sic"),
                       (["--site", str(site), "--pcap", str(not_pcap)], "not a pcap"),
                       (["--site", str(site), "--pcap", str(not_pcap), "--speed", "0"], "--speed"),
                       (["--site", str(site), "--udp", "127.0.0.1"], "HOST:PORT"),
                       (["--site", str(site), "--pcap", str(not_pcap), "--scenario-run", "r2d"], "--scenario-run"),
                       (["--site", str(site), "--udp", "127.0.0.1:1", "--scenario-run", ","], "--scenario-run")):
        p = subprocess.run([sys.executable, "-m", "services.cli", "ingest", "asterix", "--id", "gw", *args],
                           capture_output=True, text=True, timeout=60)
        assert p.returncode == 2, (args, p.stderr)
        assert says in p.stderr and "Traceback" not in p.stderr and len(p.stderr.strip().splitlines()) == 1
