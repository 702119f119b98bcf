"""``zfusion export asterix``'s core: a fused estimate as a CAT062 system track, read back
by libasterix (a decoder that is not ours) and checked against pymap3d and the
covariance; the sink's per-update and periodic sending with CAT065."""

from __future__ import annotations

import dataclasses
import math
import signal
import socket
import subprocess
import time
from types import SimpleNamespace

import asterix.generated as lib
import numpy as np
import pymap3d
import pytest
import zenoh
from asterix.base import Bits, RawDatablock
from conftest import zfusion

from fusion.geodetic import LocalFrame
from fusion.types import Estimate, Identity
from schemas import KeySpace, encode_estimate
from schemas import asterix as ax
from services.export.asterix import AsterixSink, TrackNumbers, system_track
from services.launcher import free_port
from services.node import ZenohOptions

FRAME = LocalFrame(52.0, 4.0, 10.0, deg=True)
FT = 0.3048


def lib_records(data: bytes) -> list:
    out = []
    for db in RawDatablock.parse(Bits.from_bytes(data)):
        cls = {62: lib.Cat_062_1_21, 65: lib.Cat_065_1_6}[db.get_category()]
        out.extend((db.get_category(), r) for r in cls.cv_uap.parse(db.get_raw_records()))
    return out


def q(rec, item, sub, unit):
    return rec.get_item(item).variation.get_item(sub).variation.content.as_quantity(unit)


def test_a_3d_track_as_libasterix_reads_it():
    x = np.array([12_345.6, -23_456.7, 9_876.5, 180.3, -20.7, 3.1, 0.5, -0.2, 0.0])
    A = np.random.default_rng(3).normal(size=(9, 9))
    P = A @ A.T + np.diag([900.0, 1600.0, 2500.0, 25.0, 36.0, 4.0, 1.0, 1.0, 1.0])
    e = Estimate(t=1_764_633_600.0 + 3_723.25, x=x, P=P, method="SS", track="T42")
    rec = system_track(e, FRAME, sac=25, sic=100, number=42, first=True)
    (cat, r), = lib_records(ax.encode([rec])[0])
    assert cat == 62 and r.get_item("040").variation.content.as_uint() == 42
    assert r.get_item("070").variation.content.as_quantity("s") == 3_723.25  # UTC time of day
    lat, lon, alt = pymap3d.enu2geodetic(*x[:3], 52.0, 4.0, 10.0)
    assert q(r, "105", "LAT", "°") == pytest.approx(lat, abs=180 / 2**25)
    assert q(r, "105", "LON", "°") == pytest.approx(lon, abs=180 / 2**25)
    assert r.get_item("130").variation.content.as_quantity("ft") * FT == pytest.approx(alt, abs=6.25 * FT / 2)
    assert (q(r, "100", "X", "m"), q(r, "100", "Y", "m")) == (pytest.approx(x[0], abs=0.25),
                                                             pytest.approx(x[1], abs=0.25))
    assert (q(r, "185", "VX", "m/s"), q(r, "185", "VY", "m/s")) == (pytest.approx(x[3], abs=0.125),
                                                                   pytest.approx(x[4], abs=0.125))
    assert r.get_item("080").variation.get_item("TSB").as_uint() == 1
    acc = r.get_item("500").variation
    apc = acc.get_item("APC").variation
    assert apc.get_item("X").variation.content.as_quantity("m") == pytest.approx(math.sqrt(P[0, 0]), abs=0.25)
    assert apc.get_item("Y").variation.content.as_quantity("m") == pytest.approx(math.sqrt(P[1, 1]), abs=0.25)
    cov = acc.get_item("COV").variation.content.as_quantity("m")
    assert cov == pytest.approx(math.copysign(math.sqrt(abs(P[0, 1])), P[0, 1]), abs=0.25)
    assert acc.get_item("AGA").variation.content.as_quantity("ft") * FT == pytest.approx(math.sqrt(P[2, 2]),
                                                                                         abs=6.25 * FT / 2)
    atv = acc.get_item("ATV").variation
    assert atv.get_item("X").variation.content.as_quantity("m/s") == pytest.approx(math.sqrt(P[3, 3]), abs=0.125)
    # σ of latitude: σ_north over the meridian radius of curvature, in degrees
    m = 6378137.0 * (1 - 6.69437999014e-3) / (1 - 6.69437999014e-3 * math.sin(math.radians(lat)) ** 2) ** 1.5
    apw = acc.get_item("APW").variation
    assert apw.get_item("LAT").variation.content.as_quantity("°") == pytest.approx(
        math.degrees(math.sqrt(P[1, 1]) / m), abs=180 / 2**26)


def test_a_track_with_an_identity_carries_its_address_and_callsign():
    """I062/380 ADR (the 24-bit address) and I062/245 (the callsign), as libasterix reads
    them; a non-ICAO address (``~``: TIS-B, anonymous) is no 24-bit address and is left out."""
    x, P = np.array([1000.0, 2000.0, 9000.0, 200.0, 0.0, 0.0]), np.eye(6) * 100.0
    e = Estimate(t=10.0, x=x, P=P, method="SS", track="T1", identity=Identity("4ca1f2", "EIN21"))
    (_, r), = lib_records(ax.encode([system_track(e, FRAME, 1, 2, 3)])[0])
    assert r.get_item("380").variation.get_item("ADR").variation.content.as_uint() == 0x4CA1F2
    assert r.get_item("245").variation.get_item("CHR").variation.content.as_string().strip() == "EIN21"
    tisb = dataclasses.replace(e, identity=Identity("~1a2b3c", None))
    back = ax.decode(ax.encode([system_track(tisb, FRAME, 1, 2, 3)])[0])[0]
    assert (back.address, back.callsign) == (None, None)
    plain = ax.decode(ax.encode([system_track(dataclasses.replace(e, identity=None), FRAME, 1, 2, 3)])[0])[0]
    assert (plain.address, plain.callsign) == (None, None)


def test_an_emitter_fix_has_no_height_and_no_velocity():
    e = Estimate(t=100.5, x=np.array([1000.0, 2000.0]), P=np.array([[400.0, -100.0], [-100.0, 900.0]]),
                 method="EKF", track="E1")
    back = ax.decode(ax.encode([system_track(e, FRAME, 1, 2, 7)])[0])[0]
    assert (back.x, back.y, back.vx, back.altitude, back.tod) == (1000.0, 2000.0, None, None, 100.5)
    a = back.accuracy
    assert (a.apc_x, a.apc_y, a.cov_xy, a.aga, a.atv_x) == (20.0, 30.0, -10.0, None, None)
    two_d = Estimate(t=1.0, x=np.array([1.0, 2.0, 30.0, -40.0]), P=np.diag([4.0, 4.0, 9.0, 16.0]), method="EKF")
    b = ax.decode(ax.encode([system_track(two_d, FRAME, 1, 2, 8)])[0])[0]
    assert (b.vx, b.vy, b.accuracy.atv_x, b.accuracy.atv_y, b.altitude) == (30.0, -40.0, 3.0, 4.0, None)


def test_track_numbers_are_stable_and_bounded():
    n = TrackNumbers()
    assert [n.of(t) for t in ("T1", "T2", "T1")] == [(1, True), (2, True), (1, False)]
    for k in range(200):
        n.of(f"X{k}")
    n.forget({"T1"})
    assert n.numbers == {"T1": 1} and n.of("T9")[0] == 203
    n.next = 65535
    assert n.of("last")[0] == 65535 and n.of("wrapped")[0] == 1


class Sender:
    def __init__(self):
        self.datagrams, self.failed = [], 0

    def send(self, uid, data):
        self.datagrams.append(data)
        return True

    def close(self):
        pass


def test_the_sink_sends_per_update_or_as_a_periodic_picture():
    site = SimpleNamespace(origin=(52.0, 4.0, 10.0), sensors={})
    clock = [0.0]
    est = {f"T{k}": Estimate(t=10.0 + k, x=np.array([k * 100.0, 0.0, 1000.0, 1.0, 2.0, 0.0]), P=np.eye(6),
                             method="SS", track=f"T{k}") for k in range(3)}
    table = SimpleNamespace(tracks=est)
    per_update = AsterixSink(Sender(), site, live=False, sac=25, sic=9, clock=lambda: clock[0])
    for e in est.values():
        per_update.update(table, e)
    per_update.tick(table)
    got = [r for d in per_update.sender.datagrams for r in ax.decode(d)]
    assert [(type(r).__name__, getattr(r, "track_number", None)) for r in got] == \
        [("SystemTrack", 1), ("SystemTrack", 2), ("SystemTrack", 3), ("SdpsStatus", None)]
    assert got[-1].message_type == ax.cat065.SDPS_STATUS and got[-1].tod == 12.0 and got[-1].nogo == 0
    periodic = AsterixSink(Sender(), site, live=False, sac=25, sic=9, period_s=4.0, clock=lambda: clock[0])
    for e in est.values():
        periodic.update(table, e)
    assert periodic.sender.datagrams == []
    periodic.tick(table)
    clock[0] = 2.0
    periodic.tick(table)  # not yet a period: only the status (a second has passed)
    clock[0] = 4.0
    periodic.tick(table)
    got = [r for d in periodic.sender.datagrams for r in ax.decode(d)]
    kinds = [(r.category, getattr(r, "message_type", None)) for r in got]
    assert kinds == [(62, None)] * 3 + [(65, 2), (65, 1), (65, 1)] + [(62, None)] * 3 + [(65, 2), (65, 1)]
    assert [r.status.tsb for r in got if r.category == 62] == [True] * 3 + [False] * 3
    assert [r.batch for r in got if r.category == 65 and r.message_type == 2] == [1, 2]


@pytest.mark.slow
def test_the_exporter_process_sends_what_it_is_fed(deployment):
    """Fused estimates on Zenoh in, CAT062 datagrams on a loopback UDP port out, read back
    by libasterix; SIGINT stops it with exit 0."""
    keys = KeySpace(deployment)
    ep = f"tcp/127.0.0.1:{free_port()}"
    hub = zenoh.open(ZenohOptions(listen=[ep]).to_config())
    rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    rx.bind(("127.0.0.1", 0))
    rx.settimeout(0.2)
    pub = hub.declare_publisher(keys.fused("fuser"))
    proc = zfusion("export", "asterix", "--udp", f"127.0.0.1:{rx.getsockname()[1]}", "--sac", "25", "--sic", "7",
                   "--scenario", "patent-3d", "--deployment", deployment, "--connect", ep,
                   stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    tracks, seq = {}, 0
    try:
        deadline = time.monotonic() + 30
        while len(tracks) < 2 and time.monotonic() < deadline:
            seq += 1
            x = np.array([1000.0 + seq, 2000.0, 3000.0, 50.0, 60.0, 1.0])
            pub.put(encode_estimate(Estimate(float(seq), x, np.eye(6) * 100.0, "SS", "centre", f"T{seq % 2}"),
                                    "fuser", seq))
            try:
                while True:
                    for cat, r in lib_records(rx.recv(65535)):
                        if cat == 62:
                            tracks[r.get_item("040").variation.content.as_uint()] = r
            except (TimeoutError, socket.timeout):
                pass
        assert len(tracks) == 2, proc.stderr
        r = next(iter(tracks.values()))
        assert r.get_item("010").variation.get_item("SIC").as_uint() == 7
        assert q(r, "100", "Y", "m") == 2000.0 and q(r, "185", "VY", "m/s") == 60.0
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=30)
        assert proc.returncode == 0 and "Traceback" not in err, err[-2000:]
    finally:
        if proc.poll() is None:
            proc.kill()
        pub.undeclare()
        hub.close()
        rx.close()
