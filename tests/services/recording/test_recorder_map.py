"""The recording's map and the geodetic shapes behind it (services.geo, services.recording.map):
rings and tracks checked against pymap3d and χ² directly, a recorder fed encoded messages
read back from its file, and the recordings of real runs of patent-3d and df-multi."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pymap3d
import pytest
from scipy.stats import chi2

from sensors_sim import load_scenario
from services import geo
from services.recording import draw
from services.recording.recorder import Recorder
from services.recording.stream import open_recording
from services.recording.map import map_path

from _recording import KEYS, est_msg, meas_msg, read_rrd, truth_msg, verify

ORIGIN = (48.8566, 2.3522, 35.0)  # Paris: far from the equator, so lat and lon scale differently
WGS84 = pymap3d.Ellipsoid.from_name("wgs84")


def _enu_of(lat, lon, alt, origin=ORIGIN):
    return np.stack(pymap3d.geodetic2enu(lat, lon, alt, *origin, ell=WGS84, deg=True), axis=-1)


@pytest.mark.parametrize("P2", [
    np.diag([4e6, 2.5e5]),  # axis-aligned, east-west elongated
    np.array([[1e6, 8e5], [8e5, 9e5]]),  # correlated
    np.array([[2.5e5, -2e5], [-2e5, 4e6]]),  # eigenvectors with det -1 from eigh: the ring must be reversed
])
def test_ring_vertices_lie_on_the_95_percent_ellipse_closed_and_counter_clockwise(P2):
    frame = geo.frame_of(ORIGIN)
    center = np.array([12_000.0, -30_000.0, 0.0])
    ring = geo.ring(frame, center, P2)
    assert np.array_equal(ring[0], ring[-1])  # closed
    d = _enu_of(ring[:-1, 0], ring[:-1, 1], ring[:-1, 2]) - center  # back through pymap3d, independently
    m2 = np.einsum("ij,jk,ik->i", d[:, :2], np.linalg.inv(P2), d[:, :2])
    np.testing.assert_allclose(m2, chi2.ppf(0.95, 2), rtol=1e-7)
    np.testing.assert_allclose(d[:, 2], 0.0, atol=1e-6)
    # Counter-clockwise in (lon, lat): the angle about the centre only ever grows, by one turn.
    c_lat, c_lon, _ = pymap3d.enu2geodetic(*center, *ORIGIN, ell=WGS84, deg=True)
    ang = np.unwrap(np.arctan2(ring[:, 0] - c_lat, ring[:, 1] - c_lon))
    assert np.all(np.diff(ang) > 0)
    assert ang[-1] - ang[0] == pytest.approx(2 * math.pi)


def test_track_positions_and_lines_are_pymap3d_of_the_enu_states():
    frame = geo.frame_of(ORIGIN)
    x = np.array([5_000.0, 80_000.0, 9_000.0, 200.0, 0.0, 0.0])
    lat, lon, alt = pymap3d.enu2geodetic(5_000.0, 80_000.0, 9_000.0, *ORIGIN, ell=WGS84, deg=True)
    np.testing.assert_allclose(geo.lat_lon_alt(frame, geo.enu3(x)), [lat, lon, alt], rtol=0, atol=1e-9)
    fix = geo.lat_lon_alt(frame, geo.enu3(np.array([-3_000.0, 4_000.0])))  # an emitter fix sits on u = 0
    np.testing.assert_allclose(_enu_of(*fix), [-3_000.0, 4_000.0, 0.0], atol=1e-6)
    a, b = np.array([0.0, 0.0, 0.0]), np.array([300_000.0, 400_000.0, 0.0])
    pts = geo.line(frame, a, b)
    enu = _enu_of(pts[:, 0], pts[:, 1], pts[:, 2])
    # every vertex on the ENU segment (a bearing ray is straight in ENU, curved on the map)
    np.testing.assert_allclose((enu[:, 0] * b[1] - enu[:, 1] * b[0]) / np.linalg.norm(b), 0.0, atol=1e-4)
    np.testing.assert_allclose(enu[[0, -1]], [a, b], atol=1e-4)


def test_ce_le_are_one_sigma_figures_of_the_covariance():
    P = np.diag([900.0, 400.0, 2500.0, 1.0, 1.0, 1.0])
    P[0, 1] = P[1, 0] = 300.0
    ce, le = geo.ce_le(np.zeros(6), P)
    assert ce == pytest.approx(math.sqrt(max(np.linalg.eigvalsh(P[:2, :2]))))
    assert le == pytest.approx(50.0)
    assert geo.ce_le(np.zeros(2), P[:2, :2])[1] is None


def _rows_at(rows, column):
    return [r for r in rows if r.get(column) is not None]


def test_recorder_draws_sites_bearings_fixes_tracks_and_truth_on_the_map(tmp_path):
    sc = load_scenario("thesis-fixed-c1")
    path = tmp_path / "m.rrd"
    rec, _ = open_recording(str(path), geo=True)
    r = Recorder(rec, KEYS, None, sc)
    x_fix, P_fix = np.array([15_100.0, 14_900.0]), np.array([[40_000.0, 10_000.0], [10_000.0, 90_000.0]])
    for k in range(1, 4):
        t = float(k)
        r.offer(KEYS.truth("E1"), truth_msg(k, t, "E1", x=[15_000.0, 15_000.0, 0, 0, 0, 0, 0, 0, 0]))
        r.offer(KEYS.meas("df1"), meas_msg("df1", "bearing", [math.pi / 4], [0.0175], t, k))
        r.offer(KEYS.fused("fuser"), est_msg(t, x_fix, P_fix, method="EKF", track="E1", seq=k))
    x3 = np.array([6_000.0, 8_000.0, 2_000.0, 100.0, 0.0, 0.0])
    r.offer(KEYS.fused("fuser"), est_msg(3.0, x3, np.diag([100.0, 400.0, 900.0, 1, 1, 1]), method="SS", track="T1", seq=9))
    r.finish()
    rec.flush()
    rec.disconnect()
    verify(path)
    rows = read_rrd(path)
    frame_ref = sc.origin

    def ll(enu):
        lat, lon, _ = pymap3d.enu2geodetic(*enu, *frame_ref, ell=WGS84, deg=True)
        return [lat, lon]

    site = _rows_at(rows["/map/sites/df1"], "GeoPoints:positions")[0]["GeoPoints:positions"]
    np.testing.assert_allclose(site, [ll(sc.sensors["df1"].site.position(0.0))], atol=1e-9)
    fix = rows["/map/tracks/centre/E1"][-1]
    np.testing.assert_allclose(fix["GeoPoints:positions"], [ll([*x_fix, 0.0])], atol=1e-9)
    ring = np.array(fix["GeoLineStrings:line_strings"][0])
    d = _enu_of(ring[:, 0], ring[:, 1], 0.0, frame_ref)[:, :2] - x_fix  # (alt ignored: lat/lon only)
    np.testing.assert_allclose(np.einsum("ij,jk,ik->i", d, np.linalg.inv(P_fix), d), chi2.ppf(0.95, 2), rtol=1e-3)
    np.testing.assert_allclose(rows["/map/tracks/centre/T1"][-1]["GeoPoints:positions"], [ll(x3[:3])], atol=1e-9)
    bearing = np.array(rows["/map/meas/df1"][-1]["GeoLineStrings:line_strings"][0])
    enu = _enu_of(bearing[:, 0], bearing[:, 1], 0.0, frame_ref)
    az = np.arctan2(enu[1:, 0], enu[1:, 1])  # compass azimuth from df1 at the origin
    np.testing.assert_allclose(az, math.pi / 4, atol=1e-4)
    truth = rows["/map/truth/E1"][-1]["GeoPoints:positions"]
    np.testing.assert_allclose(truth, [ll([15_000.0, 15_000.0, 0.0])], atol=1e-9)
    assert len(rows["/map/tracks/centre/E1/path"][-1]["GeoLineStrings:line_strings"][0]) >= 2


def test_map_path_mirrors_world():
    assert map_path("/world/tracks/centre/T1") == "/map/tracks/centre/T1"
    with pytest.raises(AssertionError):
        map_path("/metrics/nees")


@pytest.mark.slow
@pytest.mark.parametrize("scenario", ["patent-3d", "df-multi"])
def test_recordings_of_real_runs_hold_geographic_points_and_line_strings(scenario, request):
    rrd = request.getfixturevalue({"patent-3d": "patent_3d_run", "df-multi": "df_multi_run"}[scenario])[1]
    verify(rrd)
    rows = read_rrd(rrd)
    sc = load_scenario(scenario)
    for sid in sc.sensors:
        assert _rows_at(rows[f"/map/sites/{sid}"], "GeoPoints:positions")
    tracks = [p for p in rows if p.startswith("/map/tracks/centre/") and not p.endswith("/path")]
    assert tracks and all(_rows_at(rows[p], "GeoLineStrings:line_strings") for p in tracks)  # rings
    assert any(p.endswith("/path") and p.startswith("/map/tracks/centre/") for p in rows)  # ground tracks
    for tid in sc.targets:
        assert _rows_at(rows[f"/map/truth/{tid}"], "GeoPoints:positions")
    if scenario == "df-multi":
        assert all(_rows_at(rows[f"/map/meas/{sid}"], "GeoLineStrings:line_strings") for sid in sc.sensors)
    # The fused positions on the map are the 3D scene's, converted: compare the last row of one track.
    path = sorted(tracks)[0]
    drawn = _rows_at(rows[path], "GeoPoints:positions")[-1]
    world = [r for r in _rows_at(rows[path.replace("/map/", "/world/", 1)], "Points3D:positions")
             if r["t"] == drawn["t"]][-1]
    lat, lon, _ = pymap3d.enu2geodetic(*world["Points3D:positions"][0], *sc.origin, ell=WGS84, deg=True)
    np.testing.assert_allclose(drawn["GeoPoints:positions"], [[lat, lon]], atol=1e-9)


def test_map_paths_are_the_world_paths_converted_row_by_row_past_a_full_path(tmp_path, monkeypatch):
    """The map converts each path point once (``Trail.mapped``), together with the row's
    position and ring: every map path row must still be pymap3d of the 3D path drawn at
    that time, also after the path has been full (``PATH_MAX``, made short here) and its
    buffer replaced, twice."""
    monkeypatch.setattr(draw, "PATH_MAX", 20)
    sc = dataclasses.replace(load_scenario("patent-3d"), duration=2000.0)
    path = tmp_path / "paths.rrd"
    rec, _ = open_recording(str(path), geo=True)
    r = Recorder(rec, KEYS, None, sc)
    n = 4 * draw.PATH_MAX + 7
    P = np.diag([400.0, 900.0, 100.0, 1.0, 1.0, 1.0])
    for k in range(n):
        t = k * draw.TRAIL_STEP_S
        x = [6_000.0 + 150.0 * t, 8_000.0 + 20_000.0 * math.sin(t / 200.0), 2_000.0, 150.0, 0.0, 0.0]
        r.offer(KEYS.truth("T1"), truth_msg(k + 1, t, "T1", x=[*x, 0.0, 0.0, 0.0]))
        r.offer(KEYS.fused("fuser"), est_msg(t, np.add(x, [30.0, -40.0, 5.0, 0, 0, 0]), P, track="T1", seq=k + 1))
    r.finish()
    rec.flush()
    rec.disconnect()
    verify(path)
    rows = read_rrd(path)

    def ll(enu):
        lat, lon, _ = pymap3d.enu2geodetic(enu[:, 0], enu[:, 1], enu[:, 2], *sc.origin, ell=WGS84, deg=True)
        return np.column_stack([lat, lon])

    for world, strips in (("/world/truth/T1", "LineStrips3D:strips"), ("/world/tracks/centre/T1", "LineStrips3D:strips")):
        drawn = {r["t"]: np.array(r[strips][0], float) for r in _rows_at(rows[world], strips)}
        mapped = {r["t"]: np.array(r["GeoLineStrings:line_strings"][0])
                  for r in rows[map_path(world) + "/path"]}
        assert len(mapped) == n - 1 and set(mapped) <= set(drawn)  # from the second point on, every step
        assert max(len(v) for v in mapped.values()) == draw.PATH_MAX
        for t, g in mapped.items():  # (3D strips are float32: 1e-7 deg is about a centimetre)
            np.testing.assert_allclose(g, ll(drawn[t]), rtol=0, atol=1e-6)
        points = {r["t"]: r["GeoPoints:positions"] for r in _rows_at(rows[map_path(world)], "GeoPoints:positions")}
        assert len(points) == n
    # the ring, converted with the position and path, is the ring converted on its own
    last = rows["/map/tracks/centre/T1"][-1]
    np.testing.assert_allclose(last["GeoLineStrings:line_strings"][0],
                               geo.ring(geo.frame_of(sc.origin), np.add(x, [30.0, -40.0, 5.0, 0, 0, 0])[:3],
                                        P[:2, :2])[:, :2], rtol=0, atol=1e-9)
    np.testing.assert_allclose(last["GeoPoints:positions"], ll(np.add(x, [30.0, -40.0, 5.0, 0, 0, 0])[None, :3]),
                               rtol=0, atol=1e-9)
