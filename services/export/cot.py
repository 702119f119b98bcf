"""The fused picture as Cursor-on-Target events, for TAK (ATAK, WinTAK, TAK Server).

One CoT 2.0 event per fused update and per sensor (pure: :func:`track_event`,
:func:`sensor_event` return the XML bytes), sent by :class:`UdpSender` or
:class:`TcpSender`::

    <event version="2.0" uid=… type=… time=… start=… stale=… how=…>
      <point lat=… lon=… hae=… ce=… le=…/>
      <detail><contact callsign=…/><track course=… speed=…/><remarks>…</remarks>
              <zfusion kind=… method=… node=… t=… position_std=… [existence=…]/></detail>
    </event>

Types are MIL-STD-2525's tree: ``a-u-A`` a 3D track (air, unknown affiliation),
``a-u-G-E`` an emitter fix (ground equipment; the tree has no emitter leaf),
``a-f-G-E-S`` a sensor (``-R`` a radar, ``a-f-A`` an airborne DF): :mod:`.cot_types`. ``start`` is the
estimate's UTC time in a live session, else now (scenario seconds have no date; the
scenario time is in ``<zfusion t=…>``); ``ce``/``le`` are 1σ metres
(:func:`services.geo.ce_le`). Over TCP a failed send closes the connection and the
sender reconnects with exponential backoff (``BACKOFF_MIN_S`` to ``BACKOFF_MAX_S``),
then re-sends the latest event of every uid (at most ``MAX_PENDING``), so a TAK server
that comes back gets the picture. Field by field: docs/viewing.md.
"""

from __future__ import annotations

import logging
import math
import socket
import time
import xml.etree.ElementTree as ET
from collections import OrderedDict
from dataclasses import dataclass
from urllib.parse import urlsplit

import numpy as np

from fusion.geodetic import LocalFrame
from fusion.types import Estimate
from sensors_sim.spec import SENSOR_KINDS

from .. import geo
from .cot_types import TYPE_EMITTER, TYPE_SENSOR, TYPE_TRACK
from .tracks import utc_iso

log = logging.getLogger("zfusion")

UNKNOWN = 9999999.0  # CoT's "not known" for hae, ce, le
SENSOR_TYPES = {**{k.name: "a-f-G-E-S-R" for k in SENSOR_KINDS.values() if k.active},  # radars
                **{k.name: "a-f-A" for k in SENSOR_KINDS.values() if k.airborne}}
BACKOFF_MIN_S = 0.5
BACKOFF_MAX_S = 30.0
MAX_PENDING = 4096


@dataclass(frozen=True)
class Types:
    """The CoT type of each kind of object (module docstring)."""

    track: str = TYPE_TRACK
    emitter: str = TYPE_EMITTER
    sensor: str | None = None  # None: by sensor kind (SENSOR_TYPES, else TYPE_SENSOR)

    def of_sensor(self, kind: str) -> str:
        return self.sensor or SENSOR_TYPES.get(kind, TYPE_SENSOR)


def _num(x: float, decimals: int) -> str:
    """``x`` with ``decimals`` decimals, never ``-0.0`` (a value that rounds to zero is 0)."""
    return f"{round(float(x), decimals) + 0.0:.{decimals}f}"


def _event(uid: str, type_: str, how: str, now: float, start: float, stale_s: float, lla: np.ndarray,
           ce: float, le: float | None) -> tuple[ET.Element, ET.Element]:
    ev = ET.Element("event", version="2.0", uid=uid, type=type_, time=utc_iso(now), start=utc_iso(start),
                    stale=utc_iso(start + stale_s), how=how)
    lat, lon, hae = (float(v) for v in lla)
    ET.SubElement(ev, "point", lat=_num(lat, 7), lon=_num(lon, 7), hae=_num(hae, 1), ce=_num(ce, 1),
                  le=_num(UNKNOWN if le is None else le, 1))
    return ev, ET.SubElement(ev, "detail")


def track_event(e: Estimate, frame: LocalFrame, uid: str, types: Types, now: float, stale_s: float,
                live: bool) -> bytes:
    """The event of one fused track or fix, ``now`` being the UTC POSIX time."""
    fix = e.x.size == 2
    ce, le = geo.ce_le(e.x, e.P)
    lla = geo.lat_lon_alt(frame, geo.enu3(e.x))
    ev, detail = _event(uid, types.emitter if fix else types.track, "m-f", now, e.t if live else now, stale_s,
                        lla, ce, le)
    ET.SubElement(detail, "contact", callsign=e.track)
    v = geo.velocity(e.x)
    if v is not None:  # course: degrees clockwise from true north; speed: m/s over ground
        ET.SubElement(detail, "track", course=_num(round(math.degrees(math.atan2(v[0], v[1])), 1) % 360.0, 1),
                      speed=_num(math.hypot(v[0], v[1]), 1))
    what = "emitter fix" if fix else "track"
    ET.SubElement(detail, "remarks").text = f"zfusion {e.method} {what} {e.track}, 1-sigma {ce:.0f} m"
    z = ET.SubElement(detail, "zfusion", kind="fix" if fix else "track", method=e.method, node=e.node,
                      t=repr(float(e.t)), position_std=_num(geo.position_std(e.x, e.P), 1))
    if e.existence is not None:  # the probability that the target exists (a JIPDA track's)
        z.set("existence", _num(e.existence, 4))
    return ET.tostring(ev, encoding="utf-8", xml_declaration=False)


def sensor_event(sensor: str, kind: str, enu: np.ndarray, frame: LocalFrame, uid: str, types: Types, now: float,
                 stale_s: float) -> bytes:
    ev, detail = _event(uid, types.of_sensor(kind), "h-e", now, now, stale_s, geo.lat_lon_alt(frame, enu), 0.0, 0.0)
    ET.SubElement(detail, "contact", callsign=sensor)
    ET.SubElement(detail, "remarks").text = f"zfusion sensor {sensor} ({kind})"
    return ET.tostring(ev, encoding="utf-8", xml_declaration=False)


def parse_url(url: str) -> tuple[str, str, int]:
    """``udp://HOST:PORT`` or ``tcp://HOST:PORT`` -> (scheme, host, port); ValueError otherwise."""
    u = urlsplit(url)
    try:
        port = u.port
    except ValueError:
        port = None
    if u.scheme not in ("udp", "tcp") or not u.hostname or port is None or u.path not in ("", "/"):
        raise ValueError(f"{url!r}: expected udp://HOST:PORT or tcp://HOST:PORT")
    return u.scheme, u.hostname, port


class UdpSender:
    """One datagram per event."""

    def __init__(self, host: str, port: int):
        self.address = (host, port)
        self._sock = socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET, socket.SOCK_DGRAM)
        self.failed = 0

    def send(self, uid: str, data: bytes) -> bool:
        try:
            self._sock.sendto(data, self.address)
            return True
        except OSError as e:  # no route, buffer full: counted, the next update follows
            self.failed += 1
            log.debug("cot: udp send to %s: %s", self.address, e)
            return False

    def poll(self) -> None:
        pass

    def close(self) -> None:
        self._sock.close()


class TcpSender:
    """Events on one TCP connection, reconnected with backoff (module docstring).

    ``clock`` is monotonic seconds (a test may pass its own)."""

    def __init__(self, host: str, port: int, clock=time.monotonic, timeout: float = 2.0):
        self.address = (host, port)
        self._clock = clock
        self._timeout = timeout
        self._sock: socket.socket | None = None
        self._latest: OrderedDict[str, bytes] = OrderedDict()  # uid -> its latest event
        self._backoff = BACKOFF_MIN_S
        self._next_try = 0.0
        self.failed = 0
        self.connects = 0

    @property
    def connected(self) -> bool:
        return self._sock is not None

    def _connect(self) -> bool:
        if self._sock is not None:
            return True
        if self._clock() < self._next_try:
            return False
        try:
            self._sock = socket.create_connection(self.address, timeout=self._timeout)
        except OSError as e:
            log.debug("cot: tcp connect to %s: %s (next try in %.1f s)", self.address, e, self._backoff)
            self._back_off()
            return False
        self._backoff = BACKOFF_MIN_S
        self.connects += 1
        if self.connects > 1:
            log.info("cot: reconnected to %s:%d", *self.address)
        return self._flush()

    def _back_off(self) -> None:
        """A failure: the next try waits the current backoff, which then doubles."""
        self._next_try = self._clock() + self._backoff
        self._backoff = min(2 * self._backoff, BACKOFF_MAX_S)

    def _flush(self) -> bool:
        """Send the latest event of every uid (after a (re)connection)."""
        for data in list(self._latest.values()):
            if not self._write(data):
                return False
        return True

    def _write(self, data: bytes) -> bool:
        try:
            self._sock.sendall(data)
            return True
        except OSError as e:
            self.failed += 1
            log.warning("cot: tcp send to %s:%d failed (%s); reconnecting", *self.address, e)
            self._sock.close()
            self._sock = None
            self._back_off()
            return False

    def send(self, uid: str, data: bytes) -> bool:
        self._latest[uid] = data
        self._latest.move_to_end(uid)
        while len(self._latest) > MAX_PENDING:
            self._latest.popitem(last=False)
        if self._sock is None:
            return self._connect()  # which sends everything, this event too
        return self._write(data)

    def poll(self) -> None:
        """Retry a lost connection when its backoff has passed."""
        if self._sock is None:
            self._connect()

    def close(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None


def sender_for(url: str):
    scheme, host, port = parse_url(url)
    return UdpSender(host, port) if scheme == "udp" else TcpSender(host, port)
