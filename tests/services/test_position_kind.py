"""The position kind end to end outside fusion/: the scenario sensor kind ``adsb`` and its
emulator, the wire with a report's own covariance, ``zfusion ingest jsonl`` (position
lines in ENU and WGS-84, malformed ones refused by cause, the JSON Schema agreeing), the
fuser's intake, the recorder, and runs over Zenoh equal to the in-process evaluation."""

from __future__ import annotations

import dataclasses
import json
import math

import jsonschema
import numpy as np
import pymap3d
import pytest
from scipy import stats

from fusion.geodetic import LocalFrame
from fusion.types import Measurement
from schemas import KeySpace, SchemaError, decode, encode, encode_measurement, to_measurement
from schemas.messages import _validate_fast, _validate_strict
from sensors_sim import ScenarioError, load_scenario, sensor_events, truth_trajectory
from services.fuser import MeasurementIntake
from services.ingest.gateway import Gateway, Reading, Rejected, SensorSite
from services.ingest.jsonl import reading
from services.node import RejectLog

from _recording import KEYS, Session, meas_msg
from _runs import in_process, run_cmd, same_series
from conftest import DATA, ROOT

SCENARIO = DATA / "patent-3d-adsb.toml"
SCHEMA = json.loads((ROOT / "docs" / "ingest-line.schema.json").read_text())
ORIGIN = (21.0285, 105.8542, 10.0)
NOW = 1764612010.0
STD = np.array([30.0, 30.0, 45.0])
CORR = np.array([[1.0, 0.3, -0.2], [0.3, 1.0, 0.1], [-0.2, 0.1, 1.0]])


def position(z=(5875.3, 8023.9, 2089.8), std=STD, corr=None, t=2.5, seq=3) -> Measurement:
    return Measurement(t, "adsb", "position", np.array(z, float), np.array(std, float), np.zeros(3), seq,
                       None if corr is None else np.array(corr, float))


# The scenario sensor kind and its emulator ------------------------------------------------
def test_an_adsb_sensor_reports_each_target_s_position_with_its_std():
    sc = load_scenario(SCENARIO)
    s = sc.sensors["adsb"]
    assert s.measurement_kind == "position" and s.components == ("east", "north", "up")
    np.testing.assert_array_equal(s.std, STD)
    np.testing.assert_array_equal(s.site.points, np.zeros((1, 3)))  # no position needed
    white = []
    for run in range(20):
        traj = truth_trajectory(sc, "T1", run)
        evs = [e for e in sensor_events(sc, "adsb", run) if e.measurement is not None]
        assert [e.t for e in evs] == [0.5 + k for k in range(30)]  # one report per target per period
        for e in evs:
            m = e.measurement
            np.testing.assert_array_equal(m.std, STD)
            assert m.corr is None and m.kind == "position"
            white.append((m.z - traj.position(m.t)) / STD)
    white = np.array(white)
    assert np.all(np.abs(white.mean(axis=0)) < 4 / np.sqrt(len(white)))
    for k in range(3):
        assert stats.kstest(white[:, k], "norm").pvalue > 1e-3


def _adsb(tmp_path, body: str):
    text = SCENARIO.read_text().split("[sensors.adsb]")[0] + "[sensors.adsb]\n" + body
    p = tmp_path / "s.toml"
    p.write_text(text)
    return p


def test_adsb_keys_std_alt_defaults_to_std_pos_and_the_rest_is_refused(tmp_path):
    sc = load_scenario(_adsb(tmp_path, 'kind = "adsb"\nperiod_s = 2.0\nstd_pos_km = 0.05\n'))
    np.testing.assert_array_equal(sc.sensors["adsb"].std, [50.0, 50.0, 50.0])
    with pytest.raises(ScenarioError, match="std_pos"):
        load_scenario(_adsb(tmp_path, 'kind = "adsb"\nperiod_s = 2.0\nstd_alt_m = 5.0\n'))
    with pytest.raises(ScenarioError, match="std_az_deg"):
        load_scenario(_adsb(tmp_path, 'kind = "adsb"\nperiod_s = 2.0\nstd_pos_m = 5.0\nstd_az_deg = 1.0\n'))
    with pytest.raises(ScenarioError, match="clutter needs a finite coverage"):
        load_scenario(_adsb(tmp_path, 'kind = "adsb"\nperiod_s = 2.0\nstd_pos_m = 5.0\nclutter_rate = 1.0\n'))


# The wire ---------------------------------------------------------------------------------
def test_a_position_report_with_its_own_covariance_round_trips_bit_for_bit():
    for m in (position(), position(corr=CORR)):
        data = encode_measurement(m, "adsb")
        back = to_measurement(decode(data))
        assert back == m
        np.testing.assert_array_equal(back.R, m.R)
    d = {"v": 1, "kind": "position", "src": "adsb", "seq": 3, "t": 2.5, **_payload(position())}
    fast = _validate_fast(d)  # the fast path takes it, as the strict one does
    assert fast is not None and to_measurement(fast) == to_measurement(_validate_strict(d))
    assert _validate_fast({**d, "corr": [0.1, 0.0, 0.0]}) is None  # a stated correlation: the strict path


def _payload(m: Measurement) -> dict:
    out = {"sensor": m.sensor, "site": m.site.tolist()}
    for i, c in enumerate(("east", "north", "up")):
        out[c], out[f"std_{c}"] = float(m.z[i]), float(m.std[i])
    return out


@pytest.mark.parametrize("corr, cause", [
    ([0.3, -0.2], "shape"),
    ([1.0, 0.0, 0.0], "range"),
    ([0.99, 0.99, -0.99], "value"),  # each in (-1, 1), the matrix not positive definite
    ("x", "type"),
])
def test_the_wire_refuses_a_bad_correlation_by_cause(corr, cause):
    with pytest.raises(SchemaError) as e:
        decode(_raw("position", _payload(position()), corr=corr))
    assert e.value.cause == cause and e.value.field == "corr"


def test_a_kind_whose_noise_is_its_sensor_s_states_no_correlation():
    radar = {"sensor": "r", "site": [0.0, 0.0, 0.0], "az": 0.5, "std_az": 0.01, "range": 1e4, "std_range": 20.0}
    with pytest.raises(SchemaError) as e:
        decode(_raw("range_az", radar, corr=[0.1]))
    assert e.value.cause == "unknown-field"
    with pytest.raises(SchemaError):
        encode_measurement(Measurement(0.0, "r", "range_az", np.array([0.5, 1e4]), np.array([0.01, 20.0]),
                                       np.zeros(3), 0, np.eye(2)), "r")


def _raw(kind: str, payload: dict, **extra) -> bytes:
    import msgpack

    return msgpack.packb({"v": 1, "kind": kind, "src": payload["sensor"], "seq": 1, "t": 1.0, **payload, **extra})


def test_the_fuser_takes_a_position_report_s_own_std_but_not_a_radar_s():
    sc = load_scenario(SCENARIO)
    intake = MeasurementIntake(sc.sensors)
    own = position(std=(12.0, 15.0, 20.0), corr=CORR)
    assert intake.item("adsb", decode(encode_measurement(own, "adsb")))[0] == "item"
    radar = Measurement(1.0, "radar2d", "range_az", np.array([0.6, 1e4]), np.array([0.02, 20.0]), np.zeros(3), 1)
    kind, why = intake.item("radar2d", decode(encode_measurement(radar, "radar2d")))
    assert kind is None and why.startswith("std-mismatch")


# ingest jsonl -----------------------------------------------------------------------------
def adsb_gateway() -> Gateway:
    sensors = {"adsb": SensorSite("adsb", "position", STD, None),
               "radar": SensorSite("radar", "range_az", np.array([math.radians(1.0), 20.0]), np.zeros(3))}
    return Gateway(sensors, LocalFrame(*ORIGIN, deg=True), KeySpace("t"), RejectLog("gw"))


def published(gw: Gateway, r: Reading) -> Measurement:
    (key, data), _ = gw.offer(r, NOW)
    return to_measurement(decode(data))


def test_position_lines_in_enu_and_wgs84_are_accepted():
    lines = (DATA / "jsonl" / "adsb.jsonl").read_bytes().splitlines()
    assert lines and (ROOT / "docs" / "ingest.md").read_text().count('"kind": "position"') == len(lines)
    gw = adsb_gateway()
    for line in lines:
        jsonschema.validate(json.loads(line), SCHEMA)
        r = reading(line, "adsb")
        assert isinstance(r, Reading) and r.kind == "position", r
    enu, geo = (reading(line, "adsb") for line in lines)
    np.testing.assert_array_equal(enu.z, [5875.3, 8023.9, 2089.8])
    np.testing.assert_array_equal(enu.std, [38.0, 38.0, 45.0])
    assert enu.corr is None and enu.geodetic is None and enu.site is None
    assert geo.z is None and geo.geodetic == (21.1007, 105.9106, 1961.6)
    np.testing.assert_array_equal(geo.corr, [[1.0, 0.2, 0.0], [0.2, 1.0, 0.0], [0.0, 0.0, 1.0]])
    m = published(gw, dataclasses.replace(enu, t=NOW - 2.0))
    np.testing.assert_array_equal(m.z, enu.z)
    np.testing.assert_array_equal(m.std, enu.std)  # the report's own, not the site file's
    assert m.corr is None and gw.reject.total == 0


def test_a_wgs84_report_is_converted_with_its_covariance_turned_into_the_site_s_axes():
    """The published position is pymap3d's; the covariance stated along the east, north
    and up at the aircraft is, in the site's axes, ``T C Tᵀ`` with ``T``'s columns the
    aircraft's axes as pymap3d carries a displacement along each (an independent route
    to the rotation: three converted points)."""
    lat, lon, alt = 21.9, 106.8, 9000.0  # ≈ 100 km out: its axes are turned by ≈ 1°
    std, corr = np.array([38.0, 20.0, 45.0]), CORR
    m = published(adsb_gateway(), Reading("adsb", NOW - 1.0, "position", None, std, geodetic=(lat, lon, alt),
                                          corr=corr))
    p = np.array(pymap3d.geodetic2enu(lat, lon, alt, *ORIGIN))
    np.testing.assert_allclose(m.z, p, rtol=0, atol=1e-6)
    T = np.column_stack([(np.array(pymap3d.geodetic2enu(*pymap3d.enu2geodetic(*(1000.0 * e), lat, lon, alt),
                                                        *ORIGIN)) - p) / 1000.0 for e in np.eye(3)])
    C = np.outer(std, std) * corr
    np.testing.assert_allclose(m.R, T @ C @ T.T, rtol=1e-6, atol=1e-6)
    assert abs(m.R[0, 1] - C[0, 1]) > 1.0  # the turn shows: not the stated matrix


@pytest.mark.parametrize("fields, cause", [
    ({"east_m": 1.0, "north_m": 2.0}, "missing"),
    ({"east_m": 1.0, "north_m": 2.0, "up_m": 3.0, "lat_deg": 21.0}, "position"),
    ({"lat_deg": 21.0, "lon_deg": 105.0}, "missing"),  # a reported position needs its altitude
    ({"east_m": 1.0, "north_m": 2.0, "up_m": 3.0, "site_m": [0, 0, 0]}, "unknown-field"),
    ({"east_m": 1.0, "north_m": 2.0, "up_m": 3.0, "az_deg": 10.0}, "unknown-field"),
    ({"east_m": 1.0, "north_m": 2.0, "up_m": 3.0, "corr": [0.1, 0.2]}, "shape"),
    ({"east_m": 1.0, "north_m": 2.0, "up_m": 3.0, "corr": [1.0, 0.0, 0.0]}, "range"),
    ({"east_m": 1.0, "north_m": 2.0, "up_m": 3.0, "std": [1.0, 0.0, 2.0]}, "range"),
    ({"east_m": 1.0, "north_m": 2.0, "up_m": "3"}, "type"),
    ({"east_m": 1.0, "north_m": 2.0, "up_m": 3.0, "std": [1.0, 2.0]}, "shape"),
])
def test_malformed_position_lines_are_refused_by_cause_and_by_the_schema(fields, cause):
    obj = {"t": NOW, "kind": "position", **fields}
    r = reading(json.dumps(obj).encode(), "adsb")
    assert isinstance(r, Rejected) and r.cause == cause, r
    with pytest.raises(jsonschema.ValidationError):
        jsonschema.validate(obj, SCHEMA)


def test_corr_is_for_position_reports_only():
    obj = {"t": NOW, "kind": "range_az", "az_deg": 10.0, "range_m": 5e3, "corr": [0.1]}
    r = reading(json.dumps(obj).encode(), "radar")
    assert isinstance(r, Rejected) and r.cause == "unknown-field"
    with pytest.raises(jsonschema.ValidationError):
        jsonschema.validate(obj, SCHEMA)


def test_a_non_positive_definite_correlation_is_refused_by_the_gateway():
    gw = adsb_gateway()
    line = json.dumps({"t": NOW - 1.0, "kind": "position", "east_m": 1.0, "north_m": 2.0, "up_m": 3.0,
                       "corr": [0.99, 0.99, -0.99]}).encode()
    r = reading(line, "adsb")
    assert isinstance(r, Reading) and gw.offer(r, NOW) == []
    assert gw.reject.by_cause == {"value": 1}


# The recorder -----------------------------------------------------------------------------
def test_the_recorder_draws_a_position_report_as_its_point(tmp_path):
    s = Session(tmp_path)
    z = [5875.3, 8023.9, 2089.8]
    s.put(KEYS.meas("adsb"), meas_msg("adsb", "position", z, STD, 0.5, 0))
    s.put(KEYS.meas("adsb"), encode("watermark", "adsb", 1, 0.5))
    assert s.reject.total == 0
    rows = s.close()
    (row,) = rows["/world/meas/adsb"]
    np.testing.assert_allclose(row["Points3D:positions"], [z], rtol=1e-6)
    assert "LineStrips3D:strips" not in row  # no ray, no arc


# Over Zenoh -------------------------------------------------------------------------------
@pytest.mark.slow
@pytest.mark.parametrize("method", ["SS", "HNV"])
def test_a_run_with_an_adsb_sensor_equals_the_in_process_evaluation(tmp_path, deployment, method):
    import subprocess

    p = subprocess.run(run_cmd(tmp_path, str(SCENARIO), deployment, "--method", method, "--speed", "max"),
                       capture_output=True, text=True, timeout=180)
    assert p.returncode == 0, p.stderr[-3000:]
    doc = json.loads((tmp_path / "out.json").read_text())
    same_series(doc["methods"][method], in_process(str(SCENARIO), method))
    if method == "HNV":
        assert "trk-adsb" in doc["exit_codes"]  # a local tracker on the position reports
