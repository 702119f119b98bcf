"""The jsonl line format (services/ingest/jsonl.py), its JSON Schema and line splitting.

docs/ingest-line.schema.json is checked with jsonschema as an independent reading of
the format: every valid fixture line satisfies it, every malformed one it can express
violates it, and the parser agrees.
"""

from __future__ import annotations

import json
import math

import jsonschema
import numpy as np
import pytest

from fusion.geodetic import LocalFrame
from schemas import KeySpace, decode, to_measurement
from services.ingest.gateway import Gateway, Reading, Rejected, SensorSite
from services.ingest.jsonl import MAX_LINE, LineSplitter, reading
from services.node import RejectLog
from conftest import DATA as TESTS_DATA, ROOT

ROOT = ROOT
DATA = TESTS_DATA / "jsonl"
SCHEMA = json.loads((ROOT / "docs" / "ingest-line.schema.json").read_text())
NOW = 1764612010.0
RADAR_STD = np.array([math.radians(1.0), 20.0])

BAD_CAUSES = ["missing", "range", "range", "type", "unknown-field", "unknown-field", "kind", "shape", "range",
              "missing", "position", "position", "non-finite", "non-finite", "stale", "time", "type", "json",
              "json"]


def lines(name: str) -> list[bytes]:
    return (DATA / name).read_bytes().splitlines()


def radar_gateway(pinned: bool = True) -> Gateway:
    site = SensorSite("radar2d", "range_az", RADAR_STD, np.zeros(3) if pinned else None)
    return Gateway({"radar2d": site}, LocalFrame(21.0285, 105.8542, 10.0, deg=True), KeySpace(), RejectLog("gw"))


@pytest.mark.parametrize("kind, fields, z", [
    ("bearing", {"az_deg": 90.0}, [math.pi / 2]),
    ("bearing", {"az_deg": -90.0}, [3 * math.pi / 2]),  # wrapped to [0, 360)
    ("bearing", {"az_deg": 360.0}, [0.0]),
    ("azel", {"az_deg": 45.0, "el_deg": -10.0}, [math.pi / 4, -math.pi / 18]),
    ("range_az", {"az_deg": 180.0, "range_m": 1500.5}, [math.pi, 1500.5]),
    ("az_el_range", {"az_deg": 270.0, "el_deg": 90.0, "range_m": 3.0}, [1.5 * math.pi, math.pi / 2, 3.0]),
])
def test_components_in_si_units(kind, fields, z):
    line = json.dumps({"t": NOW, "kind": kind, **fields}).encode()
    r = reading(line, "s1")
    assert isinstance(r, Reading) and r.kind == kind and r.sensor == "s1" and r.t == NOW
    assert np.allclose(r.z, z, rtol=0, atol=1e-15)
    assert r.std is None and r.site is None and r.geodetic is None
    jsonschema.validate(json.loads(line), SCHEMA)


def test_std_and_positions():
    r = reading(b'{"t": 5.0, "kind": "az_el_range", "az_deg": 1, "el_deg": 2, "range_m": 3, "std": [0.5, 0.25, 7]}',
                "s")
    assert np.allclose(r.std, [math.radians(0.5), math.radians(0.25), 7.0])
    r = reading(b'{"t": 5.0, "kind": "bearing", "az_deg": 1, "lat_deg": 21.5, "lon_deg": 105.5}', "s")
    assert r.geodetic == (21.5, 105.5, None)
    r = reading(b'{"t": 5.0, "kind": "bearing", "az_deg": 1, "site_m": [1, 2, 3]}', "s")
    assert r.site.tolist() == [1.0, 2.0, 3.0]


def test_the_documented_example_is_valid_and_published_in_full():
    gw = radar_gateway()
    published = []
    for line in lines("radar2d.jsonl"):
        jsonschema.validate(json.loads(line), SCHEMA)
        r = reading(line, "radar2d")
        assert isinstance(r, Reading), r
        published += [decode(d) for _, d in gw.offer(r, NOW)]
    meas = [to_measurement(m) for m in published if m.kind == "range_az"]
    assert len(meas) == 10 and gw.reject.total == 0
    # Two detections of one scan (t = ...006) both travel; azimuth -27.05° is 332.95°.
    assert [m.t for m in meas].count(1764612006.0) == 2
    assert math.degrees(meas[-1].z[0]) == pytest.approx(332.95)
    assert all(np.array_equal(m.std, RADAR_STD) for m in meas)
    assert all(np.array_equal(m.site, np.zeros(3)) for m in meas)  # the site file pins it


def test_an_unpinned_sensor_takes_the_position_of_each_line():
    gw = radar_gateway(pinned=False)
    sites = []
    for line in lines("radar2d.jsonl"):
        sites += [to_measurement(decode(d)).site for _, d in gw.offer(reading(line, "radar2d"), NOW)[:1]]
    # ENU [0,0,0] and the origin's lat/lon/alt are one point; the 8 other lines have none.
    assert len(sites) == 2 and np.allclose(sites, 0.0, atol=1e-6)
    assert gw.reject.by_cause == {"no-position": 8}


def test_malformed_lines_are_refused_by_parser_gateway_and_schema_alike():
    bad = lines("bad.jsonl")
    assert len(bad) == len(BAD_CAUSES)
    gw = radar_gateway()
    causes = []
    for line in bad:
        r = reading(line, "radar2d")
        if isinstance(r, Rejected):
            causes.append(r.cause)
        else:
            assert gw.offer(r, NOW) == []
            (cause,) = [c for c, n in gw.reject.by_cause.items() if n] if len(gw.reject.by_cause) == 1 else [None]
            causes.append(cause)
            gw.reject.by_cause.clear()
        try:
            obj = json.loads(line)
        except ValueError:
            continue
        finite = all(not isinstance(v, float) or math.isfinite(v) for v in (obj.values() if isinstance(obj, dict)
                                                                              else obj))
        if finite and not (isinstance(obj, dict) and obj.get("t") == 25.0):  # a gateway check, not a format one
            with pytest.raises(jsonschema.ValidationError):
                jsonschema.validate(obj, SCHEMA)
    assert causes == BAD_CAUSES


def test_line_splitter_joins_chunks_and_bounds_long_lines():
    s = LineSplitter(max_line=16)
    assert s.feed(b'{"a"') == []
    assert s.feed(b': 1}\n{"b": 2}\n\n{"c"') == [b'{"a": 1}', b'{"b": 2}']
    assert s.feed(b": 3}\n") == [b'{"c": 3}']
    out = s.feed(b"x" * 40 + b"\nok\n")
    assert isinstance(out[0], Rejected) and out[0].cause == "line-too-long" and out[1:] == [b"ok"]
    out = s.feed(b"y" * 10) + s.feed(b"y" * 10) + s.feed(b"y" * 10 + b"\nz\n")
    assert [type(o) for o in out] == [Rejected, bytes] and out[1] == b"z"
    assert MAX_LINE >= 4096


def test_the_docs_show_the_tested_example():
    doc = (ROOT / "docs" / "ingest.md").read_text()
    block = doc.split("```jsonl\n", 1)[1].split("```", 1)[0]
    assert block.encode() == (DATA / "radar2d.jsonl").read_bytes()
    assert len(block.splitlines()) == 10
