"""KrakenSDR direction-finding output, sans I/O: the device's text in, compass bearings out.

Everything that decides what a KrakenSDR reading means lives here; sockets, clocks and
Zenoh live in :mod:`services.ingest.process`. Four encodings of one DSP frame (one line
or message per active VFO), all normalised to :class:`DoaReport` (UTC seconds, Hz, dB):

* ``csv`` — the "Kraken App" lines served at ``/DOA_value.html``: epoch ms, ``360 − θ``,
  confidence, power dB, Hz, array, latency ms, station, lat, lon, GPS heading, compass
  heading, heading source, four reserved fields, then the 360-point DoA spectrum;
* ``xml`` — the df-aggregator document at ``/doa.xml`` (VFO 0 only): ``TIME`` ms,
  ``FREQUENCY`` MHz, raw ``θ`` in ``DOA``, ``PWR`` = dB + 100, ``CONF`` = ×100 integer
  (older firmware: the plain float);
* ``json`` — the "Kraken Pro" POST body (``tStamp`` ms, ``radioBearing`` = raw ``θ``,
  ``gpsBearing``; numbers often as strings); ``form`` — the "Full POST" form fields.

``θ`` is the DoA counted counter-clockwise from the array's reference direction (the
unit-circle convention of the DoA spectrum), so ``360 − θ`` is clockwise from it. The
station's ``heading`` is the compass direction of that reference (the GPS track of a
moving station, or the heading its operator fixed). The bearing from true north is::

    az = (heading + (360 − θ)) mod 360 = (heading + doa_cw) mod 360      [degrees]

(the rule df-aggregator applies to ``doa.xml`` with its default "inverted" box and the
one the KrakenSDR software uses to draw a bearing on a map). :class:`KrakenStation`
applies the options (:class:`KrakenOptions`) and picks the VFO channels.
"""

from __future__ import annotations

import json
import math
import re
import urllib.parse
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field

import numpy as np

from fusion.angles import wrap_2pi

from .gateway import DECODE_ERRORS, Reading, Rejected, undecodable

FORMATS = ("csv", "xml", "json", "form")
CSV_FIELDS = 17  # fixed fields before the spectrum
SPECTRUM_POINTS = 360
#: a DoA is an angle on the array's circle, [0, 360] (360 is 0): anything else is a device
#: fault, refused as ``range`` rather than wrapped into a plausible bearing
DOA_MAX = 360.0
MAX_BODY = 1 << 20  # bytes; a reading is ~3 kB per VFO
_MS_THRESHOLD = 1e11  # a time below this is seconds (year 5138), above it milliseconds
_MHZ_THRESHOLD = 1e5  # a frequency below this is MHz (100 GHz), above it Hz
_MISSING = {"", "none", "null", "r", "n/a"}


@dataclass(frozen=True)
class DoaReport:
    """One VFO of one KrakenSDR reading, as sent, in normalised units.

    Attributes:
        fmt: the encoding it came in (:data:`FORMATS`).
        t: time stamp, UTC POSIX seconds (the device sends ms).
        doa_deg: the DoA as sent (degrees), counted as ``convention`` says.
        convention: ``"cw"`` (``360 − θ``, the CSV) or ``"ccw"`` (raw ``θ``, XML/JSON).
        vfo: index of the line in its reading (0 for XML and JSON).
        station, heading_deg, lat_deg, lon_deg, conf, power_db, freq_hz: as sent, or
            None when the field is missing or empty.
    """

    fmt: str
    t: float
    doa_deg: float
    convention: str
    vfo: int = 0
    station: str | None = None
    heading_deg: float | None = None
    lat_deg: float | None = None
    lon_deg: float | None = None
    conf: float | None = None
    power_db: float | None = None
    freq_hz: float | None = None


@dataclass(frozen=True)
class Skipped:
    """A well-formed report deliberately not published (another VFO, low confidence, ...)."""

    cause: str


@dataclass(frozen=True)
class Bearing:
    """A compass bearing ready for the gateway: ``az`` (rad, clockwise from true north,
    [0, 2π)), UTC ``t``, the channel's sensor id and the station's reported position."""

    sensor: str
    t: float
    az: float
    lat_deg: float | None
    lon_deg: float | None
    conf: float | None
    power_db: float | None
    freq_hz: float | None

    def reading(self):
        """The gateway's :class:`~services.ingest.gateway.Reading` of this bearing."""
        geo = None if self.lat_deg is None else (self.lat_deg, self.lon_deg, None)
        return Reading(sensor=self.sensor, t=self.t, kind="bearing", z=np.array([self.az]), geodetic=geo)


class ParseError(ValueError):
    def __init__(self, cause: str, detail: str):
        super().__init__(detail)
        self.cause = cause


# ------------------------------------------------------------------ field conversions


def _number(value, field: str, *, required: bool = False) -> float | None:
    """A finite float from a number or numeric text; None when missing."""
    if value is None or (isinstance(value, str) and value.strip().lower() in _MISSING):
        if required:
            raise ParseError("missing", f"{field}: required")
        return None
    if isinstance(value, bool):
        raise ParseError("value", f"{field}: {value!r} is not a number")
    try:
        x = float(value.strip() if isinstance(value, str) else value)
    except (TypeError, ValueError):
        raise ParseError("value", f"{field}: {str(value)[:40]!r} is not a number") from None
    except OverflowError:  # an integer beyond any float
        raise ParseError("range", f"{field}: {str(value)[:40]}... is beyond any float") from None
    if not math.isfinite(x):
        if required:
            raise ParseError("non-finite", f"{field}: {value!r}")
        return None
    return x


def utc_seconds(value, field: str) -> float:
    """Epoch time in s or ms (the device sends ms) -> UTC seconds."""
    x = _number(value, field, required=True)
    if x <= 0:
        raise ParseError("time", f"{field}: {value!r} is not an epoch time")
    return x / 1000.0 if x >= _MS_THRESHOLD else x


def hertz(value, field: str) -> float | None:
    """Frequency in Hz or MHz (``doa.xml`` sends MHz) -> Hz."""
    x = _number(value, field)
    if x is None:
        return None
    if x <= 0:
        raise ParseError("value", f"{field}: {value!r} is not a frequency")
    return x * 1e6 if x < _MHZ_THRESHOLD else x


def _angle(value, field: str, lo: float, hi: float, *, required: bool = False) -> float | None:
    x = _number(value, field, required=required)
    if x is not None and not lo <= x <= hi:
        raise ParseError("range", f"{field}: {x:g} outside [{lo:g}, {hi:g}]")
    return x


def _position(lat, lon) -> tuple[float | None, float | None]:
    """(lat, lon) degrees, or (None, None) when missing or (0, 0): the device writes
    0, 0 when its GPS has no fix."""
    la = _angle(lat, "latitude", -90.0, 90.0)
    lo = _angle(lon, "longitude", -180.0, 180.0)
    if la is None or lo is None or (la == 0.0 and lo == 0.0):
        return None, None
    return la, lo


# ------------------------------------------------------------------ the four encodings


def parse_csv(text: str) -> list[DoaReport | Rejected]:
    """The "Kraken App" lines of ``/DOA_value.html``: one per active VFO."""
    out: list[DoaReport | Rejected] = []
    vfo = 0
    for line in text.splitlines():
        if not line.strip():
            continue
        f = [x.strip() for x in line.split(",")]
        try:
            if len(f) < CSV_FIELDS:
                raise ParseError("fields", f"{len(f)} fields, a Kraken App line has {CSV_FIELDS} + the spectrum")
            spectrum = len(f) - CSV_FIELDS
            if spectrum not in (0, SPECTRUM_POINTS):  # a read torn by the device's rewrite
                raise ParseError("spectrum", f"{spectrum} spectrum values, expected {SPECTRUM_POINTS}")
            lat, lon = _position(f[8], f[9])
            gps, compass = _angle(f[10], "gps heading", -360, 720), _angle(f[11], "compass heading", -360, 720)
            heading = compass if f[12].lower() == "compass" and compass is not None else gps
            out.append(DoaReport(
                fmt="csv", t=utc_seconds(f[0], "time"), doa_deg=_angle(f[1], "doa", 0, DOA_MAX, required=True),
                convention="cw", vfo=vfo, station=f[7] or None, heading_deg=heading, lat_deg=lat, lon_deg=lon,
                conf=_number(f[2], "confidence"), power_db=_number(f[3], "power"), freq_hz=hertz(f[4], "frequency")))
        except ParseError as e:
            out.append(Rejected(e.cause, f"csv line {vfo + 1}: {e}"))
        vfo += 1
    if not out:
        out.append(Rejected("empty", "no Kraken App line in the document"))
    return out


def _xml_text(root: ET.Element, path: str) -> str | None:
    el = root.find(path)
    return None if el is None or el.text is None else el.text.strip()


def parse_xml(data: bytes | str) -> list[DoaReport | Rejected]:
    """The df-aggregator document of ``/doa.xml`` (VFO 0)."""
    text = data.decode("utf-8", "replace") if isinstance(data, bytes) else data
    if "<!DOCTYPE" in text or "<!ENTITY" in text:
        return [Rejected("xml", "a DOCTYPE or ENTITY declaration (refused: entity expansion)")]
    try:
        root = ET.fromstring(text)
    except (ET.ParseError, *DECODE_ERRORS) as e:  # (ET.ParseError is a SyntaxError)
        return [undecodable(e, "xml")]
    if root.tag != "DATA":
        return [Rejected("xml", f"root element <{root.tag[:20]}>, expected <DATA>")]
    g = lambda p: _xml_text(root, p)  # noqa: E731
    try:
        conf_text = g("CONF")
        conf = _number(conf_text, "CONF")
        # Current firmware writes int(conf × 100); older firmware the plain float.
        if conf is not None and conf_text is not None and re.fullmatch(r"[+-]?\d+", conf_text):
            conf /= 100.0
        pwr = _number(g("PWR"), "PWR")
        lat, lon = _position(g("LOCATION/LATITUDE"), g("LOCATION/LONGITUDE"))
        return [DoaReport(
            fmt="xml", t=utc_seconds(g("TIME"), "TIME"), doa_deg=_angle(g("DOA"), "DOA", 0, DOA_MAX, required=True),
            convention="ccw", station=g("STATION_ID") or None,
            heading_deg=_angle(g("LOCATION/HEADING"), "HEADING", -360, 720), lat_deg=lat, lon_deg=lon, conf=conf,
            power_db=None if pwr is None else pwr - 100.0, freq_hz=hertz(g("FREQUENCY"), "FREQUENCY"))]
    except ParseError as e:
        return [Rejected(e.cause, f"doa.xml: {e}")]


def _report_from_map(d: dict, fmt: str, keys: dict[str, str]) -> DoaReport:
    k = lambda name: d.get(keys[name])  # noqa: E731
    lat, lon = _position(k("lat"), k("lon"))
    station = k("station")
    return DoaReport(
        fmt=fmt, t=utc_seconds(k("time"), keys["time"]),
        doa_deg=_angle(k("doa"), keys["doa"], 0, DOA_MAX, required=True), convention="ccw",
        station=None if station is None else str(station)[:64],
        heading_deg=_angle(k("heading"), keys["heading"], -360, 720), lat_deg=lat, lon_deg=lon,
        conf=_number(k("conf"), keys["conf"]), power_db=_number(k("power"), keys["power"]),
        freq_hz=hertz(k("freq"), keys["freq"]))


_JSON_KEYS = {"time": "tStamp", "doa": "radioBearing", "station": "station_id", "heading": "gpsBearing",
              "lat": "latitude", "lon": "longitude", "conf": "conf", "power": "power", "freq": "freq"}
_FORM_KEYS = {"time": "time", "doa": "radiobearing", "station": "id", "heading": "gpsheading",
              "lat": "lat", "lon": "lng", "conf": "conf", "power": "power", "freq": "freq"}


def parse_json(data: bytes | str) -> list[DoaReport | Rejected]:
    """A "Kraken Pro" POST body: one object (one VFO), or a list of them."""
    try:
        obj = json.loads(data)
    except DECODE_ERRORS as e:
        return [undecodable(e, "json")]
    items = obj if isinstance(obj, list) else [obj]
    out: list[DoaReport | Rejected] = []
    for i, d in enumerate(items[:64]):
        if not isinstance(d, dict):
            out.append(Rejected("json", f"item {i}: expected an object, got {type(d).__name__}"))
            continue
        try:
            out.append(_report_from_map(d, "json", _JSON_KEYS))
        except ParseError as e:
            out.append(Rejected(e.cause, f"json: {e}"))
    return out or [Rejected("empty", "an empty JSON list")]


def parse_form(data: bytes | str) -> list[DoaReport | Rejected]:
    """A "Full POST" form body (``id, time, lat, lng, gpsheading, radiobearing, ...``)."""
    text = data.decode("utf-8", "replace") if isinstance(data, bytes) else data
    d = {k: v[-1] for k, v in urllib.parse.parse_qs(text, keep_blank_values=True).items()}
    try:
        return [_report_from_map(d, "form", _FORM_KEYS)]
    except ParseError as e:
        return [Rejected(e.cause, f"form: {e}")]


def detect(data: bytes, content_type: str | None = None) -> str:
    """The encoding of a body, from its content type or its first character."""
    ct = (content_type or "").lower()
    if "json" in ct:
        return "json"
    if "x-www-form-urlencoded" in ct:
        return "form"
    head = data.lstrip()[:1]
    if head == b"<":
        return "xml"
    if head in (b"{", b"["):
        return "json"
    if head.isdigit() and b"=" not in data[:64]:
        return "csv"
    return "form" if b"=" in data[:256] else "csv"


def parse(data: bytes, fmt: str = "auto", content_type: str | None = None) -> list[DoaReport | Rejected]:
    """Any encoding (``auto``: detected, so a CSV served where XML was expected, the
    quirk that breaks df-aggregator, still reads)."""
    if len(data) > MAX_BODY:
        return [Rejected("too-large", f"{len(data)} bytes > {MAX_BODY}")]
    fmt = detect(data, content_type) if fmt == "auto" else fmt
    if fmt == "csv":
        return parse_csv(data.decode("utf-8", "replace"))
    return {"xml": parse_xml, "json": parse_json, "form": parse_form}[fmt](data)


# ------------------------------------------------------------------ conversion


def compass_bearing(doa_deg: float, convention: str, heading_deg: float = 0.0) -> float:
    """Bearing from true north (rad, [0, 2π)) of a DoA counted ``cw`` or ``ccw`` from an
    array reference that points at compass ``heading_deg``: ``heading + doa_cw``."""
    cw = doa_deg if convention == "cw" else 360.0 - doa_deg
    return wrap_2pi(math.radians(math.fmod(heading_deg + cw, 360.0)))


@dataclass(frozen=True)
class KrakenOptions:
    """How readings become bearings.

    Attributes:
        convention: ``auto`` (the format's: CSV ``cw``, XML/JSON ``ccw``), or force
            ``cw`` / ``ccw`` (a firmware that writes the other one).
        heading: ``message`` (add the message's heading: a mobile station's GPS track,
            a fixed station's set heading; missing = 0), ``none`` (the DoA is already
            from true north), or a number: this fixed heading in degrees.
        vfos: ``()`` = the first VFO of each reading, published as the gateway's id; one
            frequency (Hz) = that channel, published as the id; several = channel ``k``
            of the list published as ``<id>-<k>``.
        vfo_tol_hz: how far a line's frequency may be from a listed channel.
        min_conf: readings with a lower confidence are skipped (``low-conf``).
        station: only readings whose station id is this (None: any).
    """

    convention: str = "auto"
    heading: str | float = "message"
    vfos: tuple[float, ...] = ()
    vfo_tol_hz: float = 12_500.0
    min_conf: float = 0.0
    station: str | None = None

    def __post_init__(self):
        if self.convention not in ("auto", "cw", "ccw"):
            raise ValueError(f"convention {self.convention!r}: auto, cw or ccw")
        if isinstance(self.heading, str) and self.heading not in ("message", "none"):
            raise ValueError(f"heading {self.heading!r}: message, none or degrees")

    def channel_ids(self, sensor: str) -> list[str]:
        return [f"{sensor}-{k}" for k in range(len(self.vfos))] if len(self.vfos) > 1 else [sensor]


@dataclass
class KrakenStation:
    """One KrakenSDR station's readings -> :class:`Bearing` events per channel.

    State: the last time stamp and frequency per channel (so that, with ``vfos = ()``, a
    second "Kraken Pro" POST of the same frame on another frequency — another VFO — is
    skipped), bounded by the number of channels.
    """

    sensor: str
    options: KrakenOptions = field(default_factory=KrakenOptions)
    _last: dict[str, tuple[float, float | None]] = field(default_factory=dict)

    def receive(self, data: bytes, fmt: str = "auto", content_type: str | None = None) \
            -> list[Bearing | Rejected | Skipped]:
        return [self.convert(r) if isinstance(r, DoaReport) else r for r in parse(data, fmt, content_type)]

    def channel(self, r: DoaReport) -> str | None:
        vfos = self.options.vfos
        if not vfos:
            last = self._last.get(self.sensor)
            if r.vfo != 0 or (r.fmt in ("json", "form") and last is not None and last[0] == r.t
                              and last[1] != r.freq_hz):
                return None
            return self.sensor
        if r.freq_hz is None:
            return None
        k = min(range(len(vfos)), key=lambda i: abs(vfos[i] - r.freq_hz))
        if abs(vfos[k] - r.freq_hz) > self.options.vfo_tol_hz:
            return None
        return self.options.channel_ids(self.sensor)[k]

    def convert(self, r: DoaReport) -> Bearing | Skipped:
        o = self.options
        if o.station is not None and r.station != o.station:
            return Skipped("other-station")
        ch = self.channel(r)
        if ch is None:
            return Skipped("other-vfo")
        if r.conf is not None and r.conf < o.min_conf:
            return Skipped("low-conf")
        self._last[ch] = (r.t, r.freq_hz)
        heading = (r.heading_deg or 0.0) if o.heading == "message" else 0.0 if o.heading == "none" \
            else float(o.heading)
        convention = r.convention if o.convention == "auto" else o.convention
        return Bearing(sensor=ch, t=r.t, az=compass_bearing(r.doa_deg, convention, heading), lat_deg=r.lat_deg,
                       lon_deg=r.lon_deg, conf=r.conf, power_db=r.power_db, freq_hz=r.freq_hz)
