"""A track's existence probability (JIPDA's) from the outside: on the wire (``track``
messages, both the fast and the strict paths, and the links' uplinks), in ``zfusion
picture``'s answer, in the recording (a scalar per track, read back from the file), and
in the GeoJSON and CoT properties; absent everywhere for a track without one, with the
bytes of such a track unchanged."""

from __future__ import annotations

import dataclasses
import json
import math
import xml.etree.ElementTree as ET

import msgpack
import numpy as np
import pytest
import zenoh

from fusion.motion import make_motion
from fusion.links import Init, LocalReport
from fusion.patent import LocalTracker
from fusion.measurement.models import SphericalModel
from fusion.types import Estimate
from schemas import KeySpace, SchemaError, decode, encode, encode_estimate, to_estimate
from schemas.links import encode_downlink, encode_uplink, uplink
from schemas.messages import _estimate_payload, _validate_strict
from services import geo, picture
from services.export import cot, geojson
from services.launcher import free_port
from services.node import ZenohOptions

from _recording import KEYS, Session


def _track(existence, track="T1", x=None) -> Estimate:
    x = np.array([1000.0, -2000.0, 5000.0, 0.0, 100.0, 0.0]) if x is None else x
    return Estimate(12.0, x, np.diag([400.0, 100.0, 900.0, 1.0, 1.0, 1.0]), "SS", "centre", track, 2.5, 3,
                    existence=existence)


@pytest.mark.parametrize("existence", [0.0, 0.37, 1.0])
def test_existence_on_the_wire_fast_and_strict(existence):
    e = _track(existence)
    data = encode_estimate(e, "fuser", 7)
    assert msgpack.unpackb(data)["existence"] == existence
    strict = encode("track", "fuser", 7, e.t, **_estimate_payload(e))
    assert data == strict
    assert to_estimate(decode(data)).existence == existence
    assert to_estimate(_validate_strict(msgpack.unpackb(data))).existence == existence


def test_no_existence_leaves_the_message_as_it_was():
    data = encode_estimate(_track(None), "fuser", 7)
    assert "existence" not in msgpack.unpackb(data)
    assert to_estimate(decode(data)).existence is None


@pytest.mark.parametrize("bad", [-0.01, 1.5, math.nan, "high"])
def test_existence_outside_0_1_is_refused(bad):
    d = msgpack.unpackb(encode_estimate(_track(0.5), "fuser", 7))
    d["existence"] = bad
    with pytest.raises(SchemaError):
        decode(msgpack.packb(d))


def test_existence_of_a_local_track_crosses_the_link():
    """A JIPDA local track's report (the weighted update) as a ``local_report``, encoded
    and decoded bit for bit; no other link carries an existence."""
    model = SphericalModel(("az", "el", "range"), [0.0, 0.0, 0.0], (0.01, 0.01, 20.0), n_x=6)
    tr = LocalTracker("radar", make_motion("cv", 0.1), "HNV", "L1")
    tr.initialise(np.array([0.0, 20000.0, 5000.0, 0.0, 100.0, 0.0]), np.diag([1e4] * 3 + [100.0] * 3), 0.0)
    Z = np.array([model.h(np.array([0.0, 20100.0, 5000.0, 0, 0, 0])), model.h(np.array([50.0, 20000.0, 5030.0, 0, 0, 0]))])
    r = tr.update_weighted(model, Z, [0.5, 0.3], 0.2, 1.0, seq=1, existence=0.83)
    assert isinstance(r, LocalReport) and r.estimate.existence == 0.83
    got = uplink(decode(encode_uplink(r, "trk-radar", 1)))
    assert isinstance(got, LocalReport) and got.estimate.existence == 0.83 and got.estimate.nis == r.estimate.nis
    assert got.estimate.x.tobytes() == r.estimate.x.tobytes() and got.KH.tobytes() == r.KH.tobytes()
    with pytest.raises(ValueError, match="existence"):
        encode_downlink(Init("radar", dataclasses.replace(r.estimate, node="centre")), "fuser", 1)


def test_geojson_and_cot_carry_existence():
    frame = geo.frame_of((51.5, -0.12, 10.0))
    doc = geojson.feature_collection([_track(0.9731), _track(None, "T2")], {}, frame, live=False)
    props = {f["properties"]["id"]: f["properties"] for f in json.loads(json.dumps(doc))["features"]}
    assert props["T1"]["existence"] == 0.9731 and "existence" not in props["T2"]
    ev = ET.fromstring(cot.track_event(_track(0.9731), frame, "u", cot.Types(), 1.8e9, 60.0, live=False))
    assert float(ev.find("detail/zfusion").get("existence")) == pytest.approx(0.9731)
    ev = ET.fromstring(cot.track_event(_track(None), frame, "u", cot.Types(), 1.8e9, 60.0, live=False))
    assert ev.find("detail/zfusion").get("existence") is None


def test_recording_holds_the_existence_of_each_track(tmp_path):
    s = Session(tmp_path)
    for k, r in enumerate([0.5, 0.8, 0.95]):
        s.put(KEYS.fused("fuser"), encode_estimate(Estimate(float(k + 1), np.array([1000.0, 2000.0, 5000.0, 0, 0, 0.0]),
                                                     np.eye(6) * 100.0, "SS", "centre", "T1", existence=r),
                                            "fuser", k + 1))
    s.put(KEYS.fused("fuser"), encode_estimate(Estimate(3.5, np.array([5000.0, 2000.0, 5000.0, 0, 0, 0.0]), np.eye(6) * 100.0,
                                                 "SS", "centre", "T2"), "fuser", 4))
    rows = s.close()
    series = rows["/metrics/existence/centre/T1"]
    assert [r["t"] for r in series] == [1.0, 2.0, 3.0]
    assert [v for r in series for v in r["Scalars:scalars"]] == pytest.approx([0.5, 0.8, 0.95])
    assert not any(p.startswith("/metrics/existence/centre/T2") for p in rows)


def test_picture_answer_carries_existence(deployment):
    keys = KeySpace(deployment)
    ep = f"tcp/127.0.0.1:{free_port()}"
    hub = zenoh.open(ZenohOptions(listen=[ep]).to_config())
    try:
        def on_query(q) -> None:
            q.reply(keys.picture("fuser"), encode_estimate(_track(0.64, "T1"), "fuser", 3))
            q.reply(keys.picture("fuser"), encode_estimate(_track(None, "T2"), "fuser", 4))
            q.reply(keys.picture("fuser"), encode("watermark", "fuser", 0, 12.0, final=False))

        queryable = hub.declare_queryable(keys.picture("fuser"), on_query)
        with zenoh.open(ZenohOptions(connect=[ep]).to_config()) as session:
            doc = picture.query(session, keys, timeout=10.0)
        queryable.undeclare()
    finally:
        hub.close()
    assert doc is not None
    assert {t["id"]: t["existence"] for t in json.loads(json.dumps(doc))["tracks"]} == {"T1": 0.64, "T2": None}
