"""The CoT 2.0 event structure, as the MITRE base-event schema (Event-PUBLIC.xsd,
version 2.0) and TAK's detail schemas document it, written as checks: every event the
exporter builds must pass them.

Base event: ``<event>`` holds exactly one ``<point>`` and at most one ``<detail>``; its
required attributes are ``version`` (decimal ≥ 2), ``uid``, ``type`` (``\\w+(-\\w+)*`` with
an optional ``;extra``), ``time``/``start``/``stale`` (ISO 8601 UTC, fractional seconds
optional) and ``how`` (``\\w(-\\w+)*``). ``<point>`` requires ``lat`` (−90..90), ``lon``
(−180..180), ``hae``, ``ce`` and ``le`` (decimals; an error is never negative). TAK's
details: ``<contact callsign>``, ``<track course speed>``, ``<link>`` either a vertex
(``point="lat,lon[,hae]"``) or a relation (``uid``, ``type``, ``relation``),
``<shape><ellipse major minor angle/>``, ``<strokeColor value>`` (a signed 32-bit ARGB).
"""

from __future__ import annotations

import datetime as dt
import re
import xml.etree.ElementTree as ET

TYPE = re.compile(r"\w+(-\w+)*(;[^;]*)?")
HOW = re.compile(r"\w(-\w+)*")
TIME = re.compile(r"\d{4}-\d\d-\d\dT\d\d:\d\d:\d\d(\.\d+)?Z")
DECIMAL = re.compile(r"-?\d+(\.\d+)?")


def _decimal(el: ET.Element, name: str, lo: float = -float("inf"), hi: float = float("inf")) -> float:
    v = el.get(name)
    assert v is not None and DECIMAL.fullmatch(v), f"<{el.tag} {name}={v!r}>: not a decimal"
    assert lo <= float(v) <= hi, f"<{el.tag} {name}={v}>: outside [{lo}, {hi}]"
    return float(v)


def _utc(s: str) -> float:
    assert TIME.fullmatch(s), f"{s!r}: not ISO 8601 UTC"
    return dt.datetime.fromisoformat(s.replace("Z", "+00:00")).timestamp()


def check_event(data: bytes) -> ET.Element:
    """The event, once it has passed every check (module docstring)."""
    assert not data.startswith(b"<?xml"), "a stream of events carries no XML declaration"
    ev = ET.fromstring(data)
    assert ev.tag == "event"
    assert float(ev.get("version")) >= 2.0 and ev.get("uid")
    assert TYPE.fullmatch(ev.get("type")), ev.get("type")
    assert HOW.fullmatch(ev.get("how")), ev.get("how")
    _utc(ev.get("time"))
    assert _utc(ev.get("start")) <= _utc(ev.get("stale"))
    tags = [c.tag for c in ev]
    assert tags.count("point") == 1 and tags.count("detail") <= 1 and set(tags) <= {"point", "detail"}, tags
    pt = ev.find("point")
    _decimal(pt, "lat", -90, 90), _decimal(pt, "lon", -180, 180), _decimal(pt, "hae")
    _decimal(pt, "ce", 0), _decimal(pt, "le", 0)
    for el in ev.iterfind("detail/contact"):
        assert el.get("callsign")
    for el in ev.iterfind("detail/track"):
        _decimal(el, "course", 0, 360), _decimal(el, "speed", 0)
    for el in ev.iterfind("detail//link"):
        if el.get("point") is not None:
            parts = el.get("point").split(",")
            assert len(parts) in (2, 3) and all(DECIMAL.fullmatch(p) for p in parts), el.get("point")
            assert -90 <= float(parts[0]) <= 90 and -180 <= float(parts[1]) <= 180
        else:
            assert el.get("uid") and TYPE.fullmatch(el.get("type")) and el.get("relation"), el.attrib
    for el in ev.iterfind("detail/shape/ellipse"):
        major, minor = _decimal(el, "major", 0), _decimal(el, "minor", 0)
        assert major >= minor
        _decimal(el, "angle", 0, 360)
    for el in ev.iterfind("detail/strokeColor"):
        assert -2**31 <= int(el.get("value")) < 2**31
    return ev
