"""The fused picture as Cursor-on-Target events, for TAK (ATAK, WinTAK, TAK Server).

Pure builders return each event's XML bytes; :class:`CoTPicture` says which events to
send when (sans I/O); :class:`UdpSender` or :class:`TcpSender` sends them::

    <event version="2.0" uid=… type=… time=… start=… stale=… how=…>
      <point lat=… lon=… hae=… ce=… le=…/>
      <detail><contact callsign=…/><track course=… speed=…/>
              <shape><ellipse major=… minor=… angle=…/>…</shape><remarks>…</remarks>
              <zfusion kind=… track=… method=… node=… t=… position_std=… [existence=…] [address=…]/></detail>
    </event>

A fused track or fix (:func:`track_event`) carries its 95 % horizontal error ellipse
(:func:`error_ellipse`: semi-axes ``√(χ²₂(0.95) λᵢ)`` of the 2×2 ENU covariance, the
major axis's compass angle), also sent as a drawn ellipse (``u-d-c-e``,
:func:`ellipse_event`), and, where its target claims one, the identity's callsign.
``ce``/``le`` are 1σ metres, as the CoT 2.0 schema defines an error
(:func:`services.geo.ce_le`). Drawings (``u-d-f``, a line of ``<link point=…>``
vertices, :func:`line_event`): each track's breadcrumb trail (its latest
``TRAIL_POINTS`` positions, one per ``TRAIL_STEP_S`` of its time, re-sent at most every
``TRAIL_PERIOD_S``) and each DF station's latest bearing (:func:`bearing_event`, at most
every ``BEARING_PERIOD_S``, stale after ``BEARING_STALE_S``). Every sensor is a point of
its kind's type (:func:`sensor_event`, :mod:`.cot_types`); a DF station moves with its
bearings' positions (a mobile or airborne one). ``start`` is the estimate's
UTC time in a live session, else now (scenario seconds have no date; the scenario time is
in ``<zfusion t=…>``). Over TCP a failed send closes the connection and the sender
reconnects with exponential backoff (``BACKOFF_MIN_S`` to ``BACKOFF_MAX_S``), then
re-sends the latest event of every uid (at most ``MAX_PENDING``), so a TAK server that
comes back gets the picture. Field by field: docs/viewing.md.
"""

from __future__ import annotations

import logging
import math
import socket
import time
import xml.etree.ElementTree as ET
from collections import OrderedDict, deque
from dataclasses import dataclass
from typing import NamedTuple
from urllib.parse import urlsplit

import numpy as np

from fusion.geodetic import LocalFrame
from fusion.types import Estimate
from schemas.keys import DEFAULT_FUSER
from sensors_sim.spec import SENSOR_KINDS

from .. import geo
from .cot_types import TYPE_EMITTER, TYPE_SENSOR, TYPE_TRACK
from .tracks import is_fix, utc_iso

log = logging.getLogger("zfusion")

UNKNOWN = 9999999.0  # CoT's "not known" for hae, ce, le
SENSOR_TYPES = {**{k.name: "a-f-G-E-S-R" for k in SENSOR_KINDS.values() if k.active},  # radars
                **{k.name: "a-f-A" for k in SENSOR_KINDS.values() if k.airborne}}
TYPE_LINE = "u-d-f"  # a drawn line: the trails and the bearings
TYPE_ELLIPSE = "u-d-c-e"  # a drawn ellipse: a track's 95 % region
BACKOFF_MIN_S = 0.5
BACKOFF_MAX_S = 30.0
MAX_PENDING = 4096
TRAIL_POINTS = 120  # positions kept per track: memory at most MAX_TRACKS × TRAIL_POINTS
TRAIL_STEP_S = 1.0  # a trail point at most every second of the track's time
TRAIL_PERIOD_S = 5.0  # a track's trail is sent at most this often (wall clock)
BEARING_PERIOD_S = 1.0  # a station's bearing line is sent at most this often (wall clock)
BEARING_STALE_S = 5.0  # and stays on the map this long
BEARING_RANGE_M = 30_000.0  # a bearing line's length when no fix says better
BEARING_FIX_FACTOR = 1.5  # else it reaches this many times the farthest fix's distance
MOVED_M = 1.0  # a DF station whose bearing comes from this far from its known position is re-sent there
COLOR_TRAIL = -32768  # ARGB as TAK's signed int: opaque orange (0xffff8000)
COLOR_BEARING = -16711681  # opaque cyan (0xff00ffff)
KML_ELLIPSE = "ff0080ff"  # the ellipse's line, KML aabbggrr: opaque orange


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


def error_ellipse(P2: np.ndarray, p: float = geo.CONFIDENCE) -> tuple[float, float, float]:
    """The ``p`` ellipse of a 2×2 ENU position covariance: (semi-major m, semi-minor m,
    compass angle ° of the major axis, clockwise from true north, in [0, 180)).

    With ``P2 = V diag(λ₁ ≤ λ₂) V'`` the region ``d' P2⁻¹ d ≤ χ²₂(p)`` has semi-axes
    ``√(χ²₂(p) λᵢ)``; the major axis is ``V[:, 1] = (e, n)``, at ``atan2(e, n)``."""
    w, V = np.linalg.eigh(0.5 * (P2 + P2.T))
    k = geo.k_sigma(p)
    e, n = V[:, 1]
    return (k * math.sqrt(max(float(w[1]), 0.0)), k * math.sqrt(max(float(w[0]), 0.0)),
            math.degrees(math.atan2(e, n)) % 180.0)


def callsign_of(e: Estimate) -> str:
    """What TAK labels a track with: the callsign its target claims, else its track id."""
    return e.identity.callsign if e.identity is not None and e.identity.callsign else e.track


class Geometry(NamedTuple):
    """Where an estimate is and its 95 % ellipse, worked out once for all its events."""

    lla: np.ndarray  # [lat °, lon °, alt m]
    ellipse: tuple[float, float, float]  # error_ellipse's

    @classmethod
    def of(cls, e: Estimate, frame: LocalFrame) -> "Geometry":
        return cls(geo.lat_lon_alt(frame, geo.enu3(e.x)), error_ellipse(geo.horizontal_cov(e.P)))


def track_event(e: Estimate, frame: LocalFrame, uid: str, types: Types, now: float, stale_s: float,
                live: bool, g: Geometry | None = None) -> bytes:
    """The event of one fused track or fix, ``now`` being the UTC POSIX time (``g``:
    its geometry, if worked out already)."""
    fix = is_fix(e)
    ce, le = geo.ce_le(e.x, e.P)
    lla, (major, minor, angle) = g or Geometry.of(e, frame)
    ev, detail = _event(uid, types.emitter if fix else types.track, "m-f", now, e.t if live else now, stale_s,
                        lla, ce, le)
    ET.SubElement(detail, "contact", callsign=callsign_of(e))
    v = geo.velocity(e.x)
    if v is not None:  # course: degrees clockwise from true north; speed: m/s over ground
        ET.SubElement(detail, "track", course=_num(round(math.degrees(math.atan2(v[0], v[1])), 1) % 360.0, 1),
                      speed=_num(math.hypot(v[0], v[1]), 1))
    _shape(detail, uid, major, minor, angle)
    what = "emitter fix" if fix else "track"
    ET.SubElement(detail, "remarks").text = (f"zfusion {e.method} {what} {e.track}, 1-sigma {ce:.0f} m, "
                                             f"95 % ellipse {major:.0f} x {minor:.0f} m at {angle:.0f} deg")
    z = ET.SubElement(detail, "zfusion", kind="fix" if fix else "track", track=e.track, method=e.method,
                      node=e.node, t=repr(float(e.t)), position_std=_num(geo.position_std(e.x, e.P), 1))
    if e.existence is not None:  # the probability that the target exists (a JIPDA track's)
        z.set("existence", _num(e.existence, 4))
    if e.identity is not None and e.identity.address:
        z.set("address", e.identity.address)
    return ET.tostring(ev, encoding="utf-8", xml_declaration=False)


def _shape(detail: ET.Element, uid: str, major: float, minor: float, angle: float) -> None:
    """``<shape><ellipse major minor angle/>`` and its line style, as TAK's drawn ellipses carry them."""
    shape = ET.SubElement(detail, "shape")
    ET.SubElement(shape, "ellipse", major=_num(major, 1), minor=_num(minor, 1), angle=_num(angle, 1))
    style = ET.SubElement(ET.SubElement(shape, "link", uid=f"{uid}.Style", type="b-x-KmlStyle", relation="p-c"),
                          "Style")
    line = ET.SubElement(style, "LineStyle")
    ET.SubElement(line, "color").text = KML_ELLIPSE
    ET.SubElement(line, "width").text = "2.0"


def ellipse_event(e: Estimate, frame: LocalFrame, uid: str, callsign: str, now: float, stale_s: float,
                  live: bool, g: Geometry | None = None) -> bytes:
    """A track's 95 % ellipse as a drawn ellipse (``u-d-c-e``) centred on its position:
    the shape TAK clients draw (on a marker's own event they may ignore it)."""
    lla, (major, minor, angle) = g or Geometry.of(e, frame)
    ev, detail = _event(uid, TYPE_ELLIPSE, "m-f", now, e.t if live else now, stale_s, lla, UNKNOWN, None)
    _shape(detail, uid, major, minor, angle)
    ET.SubElement(detail, "strokeColor", value=str(COLOR_TRAIL))
    ET.SubElement(detail, "strokeWeight", value="2.0")
    ET.SubElement(detail, "fillColor", value="0")
    ET.SubElement(detail, "labels_on", value="false")
    ET.SubElement(detail, "contact", callsign=f"{callsign} 95 %")
    ET.SubElement(detail, "remarks").text = (f"zfusion {e.track}: 95 % ellipse {major:.0f} x {minor:.0f} m "
                                             f"at {angle:.0f} deg")
    ET.SubElement(detail, "zfusion", kind="ellipse", track=e.track, t=repr(float(e.t)))
    return ET.tostring(ev, encoding="utf-8", xml_declaration=False)


def sensor_event(sensor: str, kind: str, enu: np.ndarray, frame: LocalFrame, uid: str, types: Types, now: float,
                 stale_s: float) -> bytes:
    ev, detail = _event(uid, types.of_sensor(kind), "h-e", now, now, stale_s, geo.lat_lon_alt(frame, enu), 0.0, 0.0)
    ET.SubElement(detail, "contact", callsign=sensor)
    ET.SubElement(detail, "remarks").text = f"zfusion sensor {sensor} ({kind})"
    ET.SubElement(detail, "zfusion", kind="sensor", sensor=sensor, sensor_kind=kind)
    return ET.tostring(ev, encoding="utf-8", xml_declaration=False)


def line_event(uid: str, callsign: str, lla: np.ndarray, anchor: int, color: int, now: float, stale_s: float,
               how: str, remarks: str, **info: str) -> bytes:
    """A drawn line (``u-d-f``) through the ``[lat, lon, hae]`` rows of ``lla``: one
    ``<link point="lat,lon,hae"/>`` per vertex, the event's point at vertex ``anchor``
    (where TAK puts the label), ``info`` in ``<zfusion>``."""
    ev, detail = _event(uid, TYPE_LINE, how, now, now, stale_s, lla[anchor], UNKNOWN, None)
    for lat, lon, hae in lla:
        ET.SubElement(detail, "link", point=f"{_num(lat, 7)},{_num(lon, 7)},{_num(hae, 1)}")
    ET.SubElement(detail, "strokeColor", value=str(color))
    ET.SubElement(detail, "strokeWeight", value="2.0")
    ET.SubElement(detail, "labels_on", value="false")
    ET.SubElement(detail, "contact", callsign=callsign)
    ET.SubElement(detail, "remarks").text = remarks
    ET.SubElement(detail, "zfusion", **info)
    return ET.tostring(ev, encoding="utf-8", xml_declaration=False)


def trail_event(track: str, callsign: str, lla: np.ndarray, uid: str, now: float, stale_s: float) -> bytes:
    """A track's breadcrumb trail: its past positions, oldest first, labelled at the latest."""
    return line_event(uid, f"{callsign} trail", lla, len(lla) - 1, COLOR_TRAIL, now, stale_s, "m-f",
                      f"zfusion track {track}: its latest {len(lla)} positions", kind="trail", track=track)


def bearing_event(sensor: str, site: np.ndarray, azimuth: float, length: float, frame: LocalFrame, uid: str,
                  now: float, t: float) -> bytes:
    """A DF station's bearing (compass azimuth, rad) as a line of ``length`` m from its
    ``site`` (ENU), curved on the map as the straight ENU ray is (``geo.LINE_POINTS``)."""
    site = np.asarray(site, dtype=float)
    end = site + length * np.array([math.sin(azimuth), math.cos(azimuth), 0.0])
    deg = math.degrees(azimuth) % 360.0
    return line_event(uid, f"{sensor} {deg:.1f}", geo.line(frame, site, end), 0, COLOR_BEARING, now,
                      BEARING_STALE_S, "m-r", f"zfusion DF bearing of {sensor}: {deg:.1f} deg, drawn {length:.0f} m",
                      kind="bearing", sensor=sensor, azimuth=_num(deg, 2), t=repr(float(t)))


class CoTPicture:
    """Which events the exporter sends, and when (sans I/O: each call returns
    ``[(uid, event bytes)]``; ``now`` is UTC POSIX seconds, ``mono`` monotonic seconds).

    Per update, the track's event and its ellipse's, and its trail when ``TRAIL_PERIOD_S`` has passed since
    the last one; per DF bearing, the station's line when ``BEARING_PERIOD_S`` has passed;
    per tick, the sensors every ``stale_s / 2`` (so they never go stale). Memory: a trail of
    at most ``trail_points`` positions for each live track (``tracks`` of the last tick,
    and never more than ``MAX_PENDING`` trails)."""

    def __init__(self, frame: LocalFrame, sensors: dict[str, tuple[str, np.ndarray]], deployment: str,
                 types: Types, stale_s: float, live: bool, fuser: str = DEFAULT_FUSER,
                 trail_points: int = TRAIL_POINTS):
        self.frame = frame
        self.sensors = dict(sensors)  # id -> (kind, ENU): a DF station's moves with its bearings
        self.deployment = deployment
        self.fuser = fuser
        self.types = types
        self.stale_s = stale_s
        self.live = live
        self.trail_points = trail_points
        self.trails: OrderedDict[str, deque] = OrderedDict()  # track -> (t, [lat lon hae]), oldest first
        self._trail_sent: dict[str, float] = {}
        self._bearing_sent: dict[str, float] = {}
        self._sensors_at = -math.inf

    def uid(self, what: str) -> str:
        """``zfusion.<deployment>.<what>``: a sensor's ``sensor.<id>``, a track's ``<fuser>.<track>``
        (two fusers' tracks never share one)."""
        return f"zfusion.{self.deployment}.{what}"

    def update(self, e: Estimate, now: float, mono: float) -> list[tuple[str, bytes]]:
        uid = self.uid(f"{self.fuser}.{e.track}")
        callsign = callsign_of(e)
        g = Geometry.of(e, self.frame)
        out = [(uid, track_event(e, self.frame, uid, self.types, now, self.stale_s, self.live, g)),
               (f"{uid}.ellipse", ellipse_event(e, self.frame, f"{uid}.ellipse", callsign, now, self.stale_s,
                                                self.live, g))]
        trail = self.trails.get(e.track)
        if trail is None:
            trail = self.trails[e.track] = deque(maxlen=self.trail_points)
            while len(self.trails) > MAX_PENDING:
                gone, _ = self.trails.popitem(last=False)
                self._trail_sent.pop(gone, None)
        self.trails.move_to_end(e.track)
        if not trail or e.t - trail[-1][0] >= TRAIL_STEP_S:
            trail.append((e.t, g.lla))
        if len(trail) >= 2 and mono - self._trail_sent.get(e.track, -math.inf) >= TRAIL_PERIOD_S:
            self._trail_sent[e.track] = mono
            uid = self.uid(f"{self.fuser}.{e.track}.trail")
            out.append((uid, trail_event(e.track, callsign, np.array([p for _, p in trail]), uid, now,
                                         self.stale_s)))
        return out

    def bearing(self, sensor: str, kind: str, site: np.ndarray, azimuth: float, t: float, fixes,
                now: float, mono: float) -> list[tuple[str, bytes]]:
        """A DF station's bearing, from ``site`` (ENU, where the measurement says the
        station was); ``fixes``: the live estimates, whose farthest emitter fix from the
        station sets the line's length (else ``BEARING_RANGE_M``). A station first seen here
        (a mobile one, whose position comes with its measurements) or moved more than
        ``MOVED_M`` is also sent as a sensor at its new position."""
        if mono - self._bearing_sent.get(sensor, -math.inf) < BEARING_PERIOD_S:
            return []
        self._bearing_sent[sensor] = mono
        site = np.asarray(site, dtype=float)
        out = []
        known = self.sensors.get(sensor)
        if known is None or np.linalg.norm(known[1] - site) > MOVED_M:
            self.sensors[sensor] = (kind, site)
            uid = self.uid(f"sensor.{sensor}")
            out.append((uid, sensor_event(sensor, kind, site, self.frame, uid, self.types, now, self.stale_s)))
        far = [math.hypot(f.x[0] - site[0], f.x[1] - site[1]) for f in fixes if is_fix(f)]
        length = min(BEARING_FIX_FACTOR * max(far), BEARING_RANGE_M) if far else BEARING_RANGE_M
        uid = self.uid(f"sensor.{sensor}.bearing")
        return [*out, (uid, bearing_event(sensor, site, azimuth, length, self.frame, uid, now, t))]

    def tick(self, tracks, now: float, mono: float) -> list[tuple[str, bytes]]:
        """The sensors when due; forgets the trails of tracks no longer in ``tracks``."""
        for gone in [k for k in self.trails if k not in tracks]:
            del self.trails[gone]
            self._trail_sent.pop(gone, None)
        if mono - self._sensors_at < self.stale_s / 2:
            return []
        self._sensors_at = mono
        out = []
        for sid, (kind, enu) in self.sensors.items():
            uid = self.uid(f"sensor.{sid}")
            out.append((uid, sensor_event(sid, kind, enu, self.frame, uid, self.types, now, self.stale_s)))
        return out


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
