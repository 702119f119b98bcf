"""What TAK reads of our events: the exporter's TCP stream framed by pytak's receiver
(``RXWorker.readcot``, events cut at ``</event>``) and each event parsed by takproto into
TAK's protobuf message, as a TAK Server or ATAK in protobuf mode does; the parsed fields
equal what we meant (positions from pymap3d, errors, times, callsign, course and speed,
the ellipse and the line vertices in the XML detail). pytak and takproto are test-only
references."""

from __future__ import annotations

import asyncio
import math
import warnings
import xml.etree.ElementTree as ET

import numpy as np
import pymap3d
import pytest

from _cot_schema import check_event
from fusion.types import Estimate, Identity
from services import geo
from services.export import cot

with warnings.catch_warnings():  # pytak warns at import about its optional extras (TLS, HTTP)
    warnings.simplefilter("ignore")
    import pytak
import takproto

WGS84 = pymap3d.Ellipsoid.from_name("wgs84")
ORIGIN = (48.85, 2.35, 35.0)
FRAME = geo.frame_of(ORIGIN)
NOW = 1_796_000_000.25


def _events() -> list[tuple[str, bytes]]:
    p = cot.CoTPicture(FRAME, {"df1": ("df", np.array([-2000.0, 500.0, 3.0])),
                               "radar2d": ("radar2d", np.array([0.0, 0.0, 12.0]))},
                       "paris", cot.Types(), 30.0, live=False)
    P = np.diag([900.0, 100.0, 400.0, 4.0, 4.0, 1.0])
    P[0, 1] = P[1, 0] = 200.0
    track = Estimate(10.0, np.array([4000.0, 3000.0, 2500.0, 60.0, -80.0, 0.0]), P, "SS", "centre", "T4",
                     identity=Identity("3c6444", "DLH4AB"))
    moved = Estimate(11.0, track.x + np.array([60.0, -80.0, 0, 0, 0, 0]), P, "SS", "centre", "T4",
                     identity=track.identity)
    fix = Estimate(10.0, np.array([1500.0, 2500.0]), np.array([[2500.0, -300.0], [-300.0, 900.0]]), "EKF",
                   "centre", "E1")
    return [*p.tick({}, NOW, 0.0), *p.update(track, NOW, 0.0), *p.update(fix, NOW, 0.0),
            *p.update(moved, NOW, 1.0), *p.bearing("df1", "df", np.array([-2000.0, 500.0, 3.0]), math.radians(70.0),
                                                   10.0, [fix], NOW, 1.0)]


def _received(events: list[tuple[str, bytes]]) -> list[bytes]:
    """The events sent by our TCP sender, as pytak's receiver cuts them off the stream."""

    async def main() -> list[bytes]:
        got: asyncio.Queue = asyncio.Queue()

        async def serve(reader, writer):
            rx = pytak.RXWorker(asyncio.Queue(), {"TAK_PROTO": "0"}, reader)
            while (data := await rx.readcot()) is not None:
                await got.put(data)
            writer.close()

        server = await asyncio.start_server(serve, "127.0.0.1", 0)
        port = server.sockets[0].getsockname()[1]

        def send() -> None:
            s = cot.TcpSender("127.0.0.1", port)
            for uid, data in events:
                assert s.send(uid, data)
            s.close()

        await asyncio.get_running_loop().run_in_executor(None, send)
        out = [await asyncio.wait_for(got.get(), 10.0) for _ in events]
        server.close()
        return out

    return asyncio.run(main())


def _geodetic(enu) -> tuple[float, float, float]:
    return pymap3d.enu2geodetic(*enu, *ORIGIN, ell=WGS84, deg=True)


def test_pytak_and_takproto_read_every_event_as_we_meant_it():
    events = _events()
    received = _received(events)
    assert [r.strip() for r in received] == [d for _, d in events]  # framed whole, in order
    msgs = {}
    for data in received:
        check_event(data)
        msg = takproto.parse_proto(takproto.xml2proto(data.strip().decode(), takproto.TAKProtoVer.MESH))
        msgs[msg.cotEvent.uid] = msg.cotEvent
    assert sorted(msgs) == sorted({uid for uid, _ in events})

    ev = msgs["zfusion.paris.fuser.T4"]  # the latest update of the track
    assert (ev.type, ev.how) == ("a-u-A", "m-f")
    lat, lon, hae = _geodetic((4060.0, 2920.0, 2500.0))
    assert (ev.lat, ev.lon) == pytest.approx((lat, lon), abs=1e-6) and ev.hae == pytest.approx(hae, abs=0.05)
    assert ev.ce == pytest.approx(math.sqrt(np.linalg.eigvalsh([[900.0, 200.0], [200.0, 100.0]])[-1]), abs=0.05)
    assert ev.le == pytest.approx(20.0)
    assert ev.sendTime == ev.startTime == round(NOW * 1000) and ev.staleTime - ev.startTime == 30_000
    assert ev.detail.contact.callsign == "DLH4AB"
    assert ev.detail.track.course == pytest.approx(math.degrees(math.atan2(60.0, -80.0)) % 360, abs=0.05)
    assert ev.detail.track.speed == pytest.approx(100.0)
    extra = ET.fromstring(f"<x>{ev.detail.xmlDetail}</x>")
    major, minor, angle = cot.error_ellipse(np.array([[900.0, 200.0], [200.0, 100.0]]))
    el = extra.find("shape/ellipse")
    assert [float(el.get(k)) for k in ("major", "minor", "angle")] == pytest.approx([major, minor, angle], abs=0.05)
    assert extra.find("zfusion").get("address") == "3c6444" and extra.find("zfusion").get("track") == "T4"

    drawn = msgs["zfusion.paris.fuser.T4.ellipse"]  # the same ellipse as a shape TAK draws
    assert (drawn.type, drawn.how) == ("u-d-c-e", "m-f") and (drawn.lat, drawn.lon) == (ev.lat, ev.lon)
    assert drawn.detail.contact.callsign == "DLH4AB 95 %" and drawn.staleTime == ev.staleTime
    el = ET.fromstring(f"<x>{drawn.detail.xmlDetail}</x>").find("shape/ellipse")
    assert [float(el.get(k)) for k in ("major", "minor", "angle")] == pytest.approx([major, minor, angle], abs=0.05)

    fix = msgs["zfusion.paris.fuser.E1"]
    assert fix.type == "a-u-G-E" and fix.le == cot.UNKNOWN and fix.detail.contact.callsign == "E1"
    assert (fix.lat, fix.lon) == pytest.approx(_geodetic((1500.0, 2500.0, 0.0))[:2], abs=1e-6)

    trail = msgs["zfusion.paris.fuser.T4.trail"]
    assert trail.type == "u-d-f" and trail.detail.contact.callsign == "DLH4AB trail"
    points = [tuple(float(v) for v in link.get("point").split(","))
              for link in ET.fromstring(f"<x>{trail.detail.xmlDetail}</x>").iterfind("link")]
    want = [_geodetic((4000.0, 3000.0, 2500.0)), _geodetic((4060.0, 2920.0, 2500.0))]
    assert np.allclose([p[:2] for p in points], [w[:2] for w in want], atol=1e-6)

    bearing = msgs["zfusion.paris.sensor.df1.bearing"]
    links = ET.fromstring(f"<x>{bearing.detail.xmlDetail}</x>").findall("link")
    assert len(links) == geo.LINE_POINTS and bearing.staleTime - bearing.startTime == cot.BEARING_STALE_S * 1000
    assert (bearing.lat, bearing.lon) == pytest.approx(_geodetic((-2000.0, 500.0, 3.0))[:2], abs=1e-6)

    for sid, kind_type in (("df1", "a-f-G-E-S"), ("radar2d", "a-f-G-E-S-R")):
        s = msgs[f"zfusion.paris.sensor.{sid}"]
        assert s.type == kind_type and s.detail.contact.callsign == sid and s.how == "h-e"
