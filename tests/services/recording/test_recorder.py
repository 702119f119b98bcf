"""The recorder: encoded messages in through :meth:`Recorder.offer`, a real ``.rrd`` out,
read back from the file (never from the recorder's own bookkeeping) and verified with
``rerun rrd verify``; bad input counted and dropped; the process over Zenoh; a run whose
recorder is killed half-way."""

from __future__ import annotations

import json
import math
import signal
import subprocess
import sys
import time

import msgpack
import numpy as np
import pytest
import zenoh
from scipy.stats import chi2

import services.recording.recorder as recorder_mod
import services.scoring as scoring
from fusion.links import Drop, DropTrack
from fusion.types import Measurement
from schemas import KeySpace, decode, encode, encode_estimate
from schemas.links import encode_downlink, encode_uplink
from sensors_sim import load_scenario
from services.recording import draw
from services.node import ZenohOptions
from services.recording.stream import open_recording

from services.launcher import free_port
from conftest import CROSSING, ROOT, wait_for, zfusion
from _recording import (KEYS, Session, downlink_msg, est_msg, meas_msg, read_rrd, static_paths, status_msg, truth_msg,
                        uplink_msg, verify)

N = 8  # scans in the scripted streams


def chi2_95(dof: int) -> tuple[float, float]:
    """The 95 % interval of one χ²(dof) sample, from scipy (what the panels must draw)."""
    return tuple(float(v) for v in chi2.ppf([0.025, 0.975], dof))


def test_patent_like_stream_rows_read_back_from_file(tmp_path):
    """One row per measurement and per track update, metrics per update with their χ²
    bounds, truth per sample; estimates that arrive before their truth are scored too."""
    s = Session(tmp_path)
    for k in range(N):
        t = float(k)
        x_true = [6000.0 + 100 * t, 8000.0, 2000.0, 100.0, 0, 0, 0, 0, 0]
        est = np.array(x_true) + np.r_[30.0, -40.0, 0.0, np.zeros(6)]
        if k % 2:  # truth late for odd scans: the estimate must wait for it
            s.put(KEYS.fused("fuser"), est_msg(t, est, np.eye(9) * 400.0, nis=1.0 + k, dof=3, seq=k + 1))
        s.put(KEYS.truth("T1"), truth_msg(k + 1, t))
        s.put(KEYS.meas("radar2d"), meas_msg("radar2d", "range_az", [0.64, 10200.0], [0.017, 20.0], t, k))
        s.put(KEYS.meas("radar2d"), encode("watermark", "radar2d", k + 1, t))
        s.put(KEYS.meas("angle"), meas_msg("angle", "azel", [0.64, 0.19], [1e-3, 1e-3], t, k))
        if not k % 2:
            s.put(KEYS.fused("fuser"), est_msg(t, est, np.eye(9) * 400.0, nis=1.0 + k, dof=3, seq=k + 1))
    assert s.reject.total == 0
    rows = s.close()
    for path in ("/world/meas/radar2d", "/world/meas/angle", "/world/tracks/centre/T1", "/world/truth/T1",
                 "/metrics/error_pos/SS", "/metrics/nees/SS", "/metrics/nees/SS/lo", "/metrics/nees/SS/hi",
                 "/metrics/nis/SS", "/metrics/nis/SS/lo", "/metrics/nis/SS/hi"):
        assert len(rows[path]) == N, path
    assert [r["t"] for r in rows["/world/tracks/centre/T1"]] == [float(k) for k in range(N)]
    err = [r["Scalars:scalars"][0] for r in rows["/metrics/error_pos/SS"]]
    np.testing.assert_allclose(err, 50.0, rtol=1e-6)
    nees = [r["Scalars:scalars"][0] for r in rows["/metrics/nees/SS"]]
    np.testing.assert_allclose(nees, 2500.0 / 400.0, rtol=1e-6)
    lo, hi = chi2_95(9)
    assert rows["/metrics/nees/SS/lo"][0]["Scalars:scalars"][0] == pytest.approx(lo, rel=1e-6)
    assert rows["/metrics/nees/SS/hi"][0]["Scalars:scalars"][0] == pytest.approx(hi, rel=1e-6)
    assert rows["/metrics/nis/SS/hi"][0]["Scalars:scalars"][0] == pytest.approx(chi2_95(3)[1], rel=1e-6)
    assert [r["Scalars:scalars"][0] for r in rows["/metrics/nis/SS"]] == [1.0 + k for k in range(N)]
    # 3σ ellipsoid with the track: half-sizes 3·20 m
    np.testing.assert_allclose(rows["/world/tracks/centre/T1"][0]["Ellipsoids3D:half_sizes"][0], [60.0] * 3,
                               rtol=1e-5)
    # the 2D radar's report: a point in the site's horizontal plane at the slant range, plus its arc
    r0 = rows["/world/meas/radar2d"][0]
    p = np.array(r0["Points3D:positions"][0])
    np.testing.assert_allclose(np.linalg.norm(p), 10200.0, rtol=1e-6)
    assert p[2] == 0.0 and len(r0["LineStrips3D:strips"]) == 1
    # the angle report: a ray from its site
    ray = np.array(rows["/world/meas/angle"][0]["LineStrips3D:strips"][0])
    np.testing.assert_allclose(ray[0], 0.0)
    np.testing.assert_allclose(ray[1] / np.linalg.norm(ray[1]), draw.unit(0.64, 0.19), atol=1e-6)
    # sites, the blueprint and the view coordinates travel with the recording
    assert len(rows["/world/sites/radar2d"]) == len(rows["/world/sites/angle"]) == 1
    assert "/world" in static_paths(s.path)
    from rerun.chunk import RrdReader

    assert RrdReader(s.path).blueprints()


def test_bad_input_is_counted_and_dropped(tmp_path, monkeypatch):
    sc = load_scenario("patent-3d")  # horizon: its duration (30 s) + 1 s
    s = Session(tmp_path, scenario=sc)
    good = meas_msg("radar2d", "range_az", [0.5, 1e4], [0.01, 20.0], 1.0, 0)
    assert s.put(KEYS.meas("radar2d"), good) is not None
    plain = msgpack.unpackb(good)
    bad = {
        "malformed": (KEYS.meas("radar2d"), b"\xc1\xc1"),
        "not-a-map": (KEYS.meas("radar2d"), msgpack.packb([1, 2])),
        "version": (KEYS.meas("radar2d"), msgpack.packb({**plain, "v": 9})),
        "range": (KEYS.meas("radar2d"), msgpack.packb({**plain, "az": 7.0})),
        "duplicate": (KEYS.meas("radar2d"), good),
        "spoofed-src": (KEYS.meas("radar2d"), msgpack.packb({**plain, "src": "angle", "seq": 5})),
        "future": (KEYS.meas("radar2d"), msgpack.packb({**plain, "t": 1e6, "seq": 10**9})),
        "past": (KEYS.meas("radar2d"), msgpack.packb({**plain, "t": -1e308, "seq": 10**9 + 1})),
        "kind": (KEYS.meas("radar2d"), est_msg(1.0, np.zeros(9), np.eye(9))),
        "key": ("zf/other/meas/radar2d", good),
    }
    for cause, (key, data) in bad.items():
        assert s.put(key, data) is None, cause
    # not bad: a local tracker holding a plot at t = 0 says "nothing before 0" (the watermark
    # just below 0 of every distributed run)
    assert s.put(KEYS.local("trk-radar2d"), encode("watermark", "trk-radar2d", 1, -5e-324)) is not None
    s.put(KEYS.truth("T1"), truth_msg(1, 1.0, target="T2"))  # truth of T2 on truth/T1
    s.put(KEYS.status("fuser"), status_msg("angle", 1, 0.0))  # status of angle on status/fuser
    s.put(KEYS.jam("jammer"), truth_msg(2, 1.0))  # a truth message on jam/
    # the far-future message did not poison the stream: the next real report is recorded
    assert s.put(KEYS.meas("radar2d"), meas_msg("radar2d", "range_az", [0.5, 1e4], [0.01, 20.0], 2.0, 1)) is not None
    # a message the schema accepts but drawing chokes on: counted, and the recorder goes on
    monkeypatch.setattr(draw, "ellipsoid", lambda *a, **k: (_ for _ in ()).throw(np.linalg.LinAlgError("boom")))
    assert s.put(KEYS.fused("fuser"), est_msg(1.0, np.zeros(9), np.eye(9))) is None
    monkeypatch.undo()
    assert s.put(KEYS.fused("fuser"), est_msg(2.0, np.zeros(9), np.eye(9), seq=2)) is not None
    assert s.put(KEYS.fused("fuser"), est_msg(2.0, np.zeros(9), np.eye(9), seq=2)) is None  # the same update again
    by = dict(s.reject.by_cause)
    for cause in ("malformed", "not-a-map", "version", "range", "future", "past", "key", "unrecordable"):
        assert by.get(cause) == 1, (cause, by)
    assert by["duplicate"] == 2
    assert by["spoofed-src"] == 3 and by["kind"] == 2
    rows = s.close()
    assert [r["t"] for r in rows["/world/meas/radar2d"]] == [1.0, 2.0]
    assert "/world/meas/angle" not in rows and "/world/truth/T1" not in rows and "/world/truth/T2" not in rows
    assert max(r["t"] for rs in rows.values() for r in rs) <= sc.duration + 1.0
    assert len(rows["/world/tracks/centre/T1"]) == 1


def test_a_restarted_process_is_recorded_again_from_its_first_message(tmp_path):
    s = Session(tmp_path)
    s.put(KEYS.status("fuser"), status_msg("fuser", 1, 0.0, state="ready", role="fuser"))
    assert s.put(KEYS.fused("fuser"), est_msg(1.0, np.zeros(9), np.eye(9), seq=1)) is not None
    s.put(KEYS.status("fuser"), status_msg("fuser", 2, 1.0, role="fuser"))
    assert s.put(KEYS.fused("fuser"), est_msg(1.0, np.zeros(9), np.eye(9), seq=1)) is None  # a repeat
    # kill -9, restart: the new fuser says it is ready and counts from 1 again
    s.put(KEYS.status("fuser"), status_msg("fuser", 1, 0.0, state="ready", role="fuser"))
    assert s.put(KEYS.fused("fuser"), est_msg(5.0, np.zeros(9), np.eye(9), seq=1)) is not None
    assert s.reject.by_cause["duplicate"] == 1
    # restarted again, and its "ready" (published as its session opens) reached no one:
    # its seq 1 and 2, other messages, are recorded; a replay of the same bytes is not
    assert s.put(KEYS.fused("fuser"), est_msg(9.0, np.zeros(9), np.eye(9), seq=1)) is not None
    assert s.put(KEYS.fused("fuser"), est_msg(10.0, np.zeros(9), np.eye(9), seq=2)) is not None
    assert s.put(KEYS.fused("fuser"), est_msg(10.0, np.zeros(9), np.eye(9), seq=2)) is None
    assert s.reject.by_cause["duplicate"] == 2
    assert [r["t"] for r in s.close()["/world/tracks/centre/T1"]] == [1.0, 5.0, 9.0, 10.0]


def test_local_tracks_feedback_predictions_and_uplinked_measurements(tmp_path):
    s = Session(tmp_path)
    P6 = np.eye(6) * 100.0
    for k in range(N):
        t = float(k)
        s.put(KEYS.truth("T1"), truth_msg(k + 1, t))
        x = np.array([6000.0 + 100 * t + 10, 8000.0, 2000.0, 100.0, 0, 0])
        m = meas_msg("radar2d", "range_az", [0.64, 10200.0], [0.017, 20.0], t, k)
        s.put(KEYS.meas("radar2d"), m)
        s.put(KEYS.local("trk-radar2d"), uplink_msg(t, x, P6, "HNV", "radar2d", nis=0.5, dof=2, seq=2 * k + 1))
        s.put(KEYS.local("trk-radar2d"), encode("watermark", "trk-radar2d", 2 * k + 2, t))
        up = Measurement(t, "angle", "azel", np.array([0.64, 0.2]), np.array([0.001, 0.001]), np.zeros(3),
                         k + 1)  # the tracker sends it up with its prediction (two-stage)
        s.put(KEYS.local("trk-angle"), uplink_msg(t, x, P6, "HNV", "angle", seq=k + 1, measurement=up))
        s.put(KEYS.feedback("trk-radar2d"), downlink_msg(t, x, P6, "HNV", "radar2d", seq=2 * k + 1))
        s.put(KEYS.feedback("trk-radar2d"), encode("watermark", "fuser", 2 * k + 2, t))  # feedback horizon
        s.put(KEYS.fused("fuser"), est_msg(t, x, P6, "HNV", "centre", seq=k + 1))
    assert s.reject.total == 0 and s.r.uplinked == N
    rows = s.close()
    assert len(rows["/world/meas/radar2d"]) == N  # the sensor's reports, once
    assert len(rows["/world/tracks/angle/uplink"]) == N  # what its tracker sent up, as the node's
    assert len(rows["/world/tracks/radar2d/T1"]) == N
    assert len(rows["/world/tracks/angle/T1/prediction"]) == N and "/world/tracks/angle/T1" not in rows
    assert len(rows["/world/feedback/trk-radar2d/T1"]) == N
    assert len(rows["/world/tracks/centre/T1"]) == N  # feedback is not drawn as the fused track again
    # fused and local metrics are kept apart
    for path in ("/metrics/error_pos/HNV", "/metrics/nees/HNV", "/metrics/error_pos/HNV/radar2d",
                 "/metrics/nees/HNV/radar2d", "/metrics/nees/HNV/radar2d/hi", "/metrics/nis/HNV/radar2d"):
        assert len(rows[path]) == N, path
    assert "/metrics/error_pos/HNV/angle" not in rows  # predictions are drawn, not scored
    np.testing.assert_allclose([r["Scalars:scalars"][0] for r in rows["/metrics/error_pos/HNV/radar2d"]], 10.0,
                               rtol=1e-6)
    assert rows["/metrics/nees/HNV/radar2d/hi"][0]["Scalars:scalars"][0] == pytest.approx(chi2_95(6)[1])


def test_state_layouts_a_local_node_may_publish(tmp_path):
    """A smoothed bearing (1 state) is a ray with its ±3σ wedge from the node's site; a
    planar CV state (4) a point and ellipse on the map plane; an unknown layout is
    accepted but not drawn."""
    s = Session(tmp_path)
    s.put(KEYS.meas("df1"), meas_msg("df1", "bearing", [0.5], [0.02], 1.0, 0, (1000.0, 2000.0, 0.0)))
    s.put(KEYS.local("trk-df1"), uplink_msg(1.0, [0.5], [[0.01 ** 2]], "KF+TR", "df1", track="B1"))
    s.put(KEYS.local("trk-df1"), uplink_msg(1.0, [5e3, 6e3, 1.0, 2.0], np.diag([100.0, 400.0, 1.0, 1.0]), "KF", "df1",
                                         track="P1", seq=2))
    s.put(KEYS.local("trk-df1"), uplink_msg(1.0, np.zeros(5), np.eye(5), "X", "df1", track="Q1", seq=3))
    assert s.reject.total == 0
    rows = s.close()
    strips = [np.array(x) for x in rows["/world/tracks/df1/B1"][0]["LineStrips3D:strips"]]
    assert len(strips) == 3 and all(np.allclose(x[0], [1000.0, 2000.0, 0.0]) for x in strips)
    az = [math.atan2(*(x[1] - x[0])[:2]) % (2 * math.pi) for x in strips]
    np.testing.assert_allclose(az, [0.5, 0.5 - 0.03, 0.5 + 0.03], atol=1e-6)
    p1 = rows["/world/tracks/df1/P1"][0]
    assert p1["Points3D:positions"][0] == [5e3, 6e3, 0.0]
    ring = np.array(p1["LineStrips3D:strips"][0])
    np.testing.assert_allclose([ring[:, 0].max() - 5e3, ring[:, 1].max() - 6e3], [30.0, 60.0], rtol=1e-3)
    assert "/world/tracks/df1/Q1" not in rows


def test_df_bearings_fixes_and_airborne_path(tmp_path):
    """Bearings are rays on the map plane from the (moving) station, long enough to cross
    where the other bearings point but found without truth; fixes carry 3σ ellipses."""
    sc = load_scenario("thesis-moving-2")  # airborne DF adf, emitter E1 at (141, 141) km
    s = Session(tmp_path, scenario=sc)
    emitter = np.array([141e3, 141e3])
    sites = [np.array([130e3, 11e3, 3000.0]), np.array([160e3, 41e3, 3000.0])]  # flying at 3 km
    for k, (t, site) in enumerate(zip((0.0, 300.0), sites)):
        d = emitter - site[:2]
        az = math.atan2(d[0], d[1]) % (2 * math.pi)
        s.put(KEYS.truth("E1"), truth_msg(k + 1, t, "E1", [*emitter, 0, 0, 0, 0, 0, 0, 0]))
        s.put(KEYS.meas("adf"), meas_msg("adf", "bearing", [az], [0.0175], t, k, site))
    P = np.array([[4e6, 1e6], [1e6, 9e6]])
    s.put(KEYS.fused("fuser"), est_msg(300.0, emitter + [300.0, -400.0], P, "EKF", track="T1"))
    s.put(KEYS.meas("adf"), meas_msg("adf", "bearing", [0.1], [0.0175], 300.5, 2, sites[1]))  # after the fix
    assert s.reject.total == 0
    rows = s.close()
    # the airborne site: drawn on the map plane where the scenario puts it, then where it moved, with its path
    site_rows = rows["/world/sites/adf"]
    assert [r["t"] for r in site_rows] == [0.0, 300.0]
    assert site_rows[-1]["Points3D:positions"][0] == [160e3, 41e3, 0.0]
    assert len(site_rows[-1]["LineStrips3D:strips"][0]) == 2
    rays = [np.array(r["LineStrips3D:strips"][0]) for r in rows["/world/meas/adf"]]
    assert all(np.all(r[:, 2] == 0.0) for r in rays)
    lengths = [float(np.linalg.norm(r[1] - r[0])) for r in rays]
    span = float(np.linalg.norm(sites[1][:2] - sites[0][:2]))  # the scenario's scale: its sites
    assert lengths[0] == pytest.approx(max(recorder_mod.DEFAULT_RAY_M, 1.5 * span), rel=1e-6)
    # second bearing: 1.3 × the distance to where it crosses the first one (= the emitter here)
    assert lengths[1] == pytest.approx(1.3 * np.linalg.norm(emitter - sites[1][:2]), rel=1e-4)
    # after a fix: 1.5 × the distance to the fix
    fix = emitter + [300.0, -400.0]
    assert lengths[2] == pytest.approx(1.5 * np.linalg.norm(fix - sites[1][:2]), rel=1e-4)
    # the fix: a point on the map plane and its 3σ ellipse as a closed line strip
    tr = rows["/world/tracks/centre/T1"][0]
    assert tr["Points3D:positions"][0] == [*fix, 0.0]
    ring = np.array(tr["LineStrips3D:strips"][0])
    assert np.all(ring[:, 2] == 0.0) and np.allclose(ring[0], ring[-1])
    rel = ring[:, :2] - fix
    m = np.einsum("ni,ij,nj->n", rel, np.linalg.inv(P), rel)
    np.testing.assert_allclose(m, 9.0, rtol=1e-4)  # every point on the 3σ contour
    # a 2-state fix is scored against the emitter's position
    assert rows["/metrics/error_pos/EKF"][0]["Scalars:scalars"][0] == pytest.approx(500.0, rel=1e-6)
    assert rows["/metrics/nees/EKF/hi"][0]["Scalars:scalars"][0] == pytest.approx(chi2_95(2)[1])


def test_jamming_contamination_and_status_events(tmp_path):
    s = Session(tmp_path)
    for k, sensor in enumerate(("df1", "df2")):
        s.put(KEYS.meas(sensor), meas_msg(sensor, "bearing", [0.7], [0.0175], 1.0, 0, (10e3 * k, 0.0, 0.0)))
    schedule = [False, True, True, False]
    for k, on in enumerate(schedule):
        s.put(KEYS.jam("jammer"), encode("jam_state", "jammer", k + 1, float(k + 1), pos=[15e3, 40e3, 0.0], on=on,
                                         mode="barrage", power=1.0, law="laplacian",
                                         affects=["df1"] if on else []))
    s.put(KEYS.status("df1"), status_msg("df1", 1, 0.0, counters={"jammed": 2, "outliers": 1, "scans": 4}))
    s.put(KEYS.status("fuser"), status_msg("fuser", 1, 3.0, role="fuser", counters={"late": 0},
                                        events=["source df2 declared dead (silent for more than 5 s)",
                                                "source df2 rejoined"]))
    s.put(KEYS.status("df1"), status_msg("df1", 2, 4.0, state="done", counters={"jammed": 2, "outliers": 1}))
    s.put(KEYS.status("df2"), status_msg("df2", 1, 4.0, role="tracker", events=["feedback timeout: running alone"]))
    assert s.reject.total == 0 and s.r.finished == {"df1"}
    rows = s.close()
    assert [r["Scalars:scalars"][0] for r in rows["/jamming/jammer/on"]] == [0.0, 1.0, 1.0, 0.0]
    assert [r["Scalars:scalars"][0] for r in rows["/jamming/jammer/affects/df1"]] == [0.0, 1.0, 1.0, 0.0]
    assert [r["Scalars:scalars"][0] for r in rows["/jamming/jammer/affects/df2"]] == [0.0, 0.0, 0.0, 0.0]
    jam_log = [(r["t"], r["TextLog:text"][0], r["TextLog:level"][0]) for r in rows["/status/jammer/events"]]
    assert [(t, lvl) for t, _, lvl in jam_log] == [(1.0, "INFO"), (2.0, "WARN"), (4.0, "INFO")]
    assert "barrage" in jam_log[1][1] and "df1" in jam_log[1][1] and jam_log[2][1] == "jammer jammer off"
    # lines from the jammer to the sensors it jams, cleared when it stops
    assert len(rows["/world/jam/jammer"][1]["LineStrips3D:strips"]) == 1
    assert rows["/world/jam/jammer"][3]["LineStrips3D:strips"] == []
    # contamination counters of the sensor; undated status goes at the latest time seen (4 s)
    assert [(r["t"], r["Scalars:scalars"][0]) for r in rows["/jamming/df1/jammed"]] == [(4.0, 2.0), (4.0, 2.0)]
    assert len(rows["/jamming/df1/outliers"]) == 2 and len(rows["/status/df1/counters/scans"]) == 1
    fuser = [(r["TextLog:text"][0], r["TextLog:level"][0]) for r in rows["/status/fuser/events"]]
    assert fuser == [("fuser fuser: running", "INFO"),
                     ("fuser: source df2 declared dead (silent for more than 5 s)", "WARN"),
                     ("fuser: source df2 rejoined", "INFO")]
    df1 = [r["TextLog:text"][0] for r in rows["/status/df1/events"]]
    assert df1 == ["sensor df1: running", "sensor df1: done"]
    assert ("df2: feedback timeout: running alone", "WARN") in [
        (r["TextLog:text"][0], r["TextLog:level"][0]) for r in rows["/status/df2/events"]]


def test_spawn_without_display_records_to_file_and_says_how_to_view(tmp_path, monkeypatch, caplog):
    monkeypatch.setattr(sys, "platform", "linux")
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    monkeypatch.setattr(recorder_mod.rr, "spawn", lambda **kw: pytest.fail("must not spawn without a display"))
    path = tmp_path / "s.rrd"
    with caplog.at_level("WARNING", logger="zfusion"):
        rec, live = open_recording(str(path), spawn=True)
    assert not live
    text = caplog.text
    assert "no display" in text and str(path) in text and "zfusion view" in text and "--serve-web" in text
    rec.log("x", recorder_mod.rr.Scalars([1.0]))
    rec.flush()
    rec.disconnect()
    verify(path)


def test_spawn_failure_falls_back_to_the_file(tmp_path, monkeypatch, caplog):
    monkeypatch.setenv("DISPLAY", ":99")
    calls = []

    def broken_spawn(**kw):
        calls.append(kw)
        raise RuntimeError("no viewer here")

    monkeypatch.setattr(recorder_mod.rr, "spawn", broken_spawn)
    path = tmp_path / "f.rrd"
    with caplog.at_level("WARNING", logger="zfusion"):
        rec, live = open_recording(str(path), spawn=True)
    assert calls and calls[0]["connect"] is False and not live
    assert "could not start the Rerun viewer" in caplog.text
    rec.flush()
    rec.disconnect()
    verify(path)


def test_record_process_over_zenoh_until_expected_processes_are_done(tmp_path, deployment):
    """The process: subscribes to every key of its deployment, stops once the expected
    processes report done, leaves a verified file."""
    ep = f"tcp/127.0.0.1:{free_port()}"
    keys = KeySpace(deployment)
    session = zenoh.open(ZenohOptions(listen=[ep]).to_config())
    path = tmp_path / "p.rrd"
    proc = zfusion("record", "--rrd", str(path), "--expect", "radar2d", "--deployment", deployment, "--connect", ep,
                   stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        statuses: list[dict] = []
        sub = session.declare_subscriber(keys.status("recorder"),
                                         lambda s: statuses.append(decode(s.payload.to_bytes()).body["counters"]))
        wait_for(lambda: statuses, "the recorder reported")
        meas = session.declare_publisher(keys.meas("radar2d"), congestion_control=zenoh.CongestionControl.BLOCK,
                                         reliability=zenoh.Reliability.RELIABLE)
        fused = session.declare_publisher(keys.fused("fuser"), congestion_control=zenoh.CongestionControl.BLOCK,
                                          reliability=zenoh.Reliability.RELIABLE)
        status = session.declare_publisher(keys.status("radar2d"))
        for k in range(N):
            meas.put(meas_msg("radar2d", "range_az", [0.5, 1e4], [0.01, 20.0], float(k), k))
            fused.put(est_msg(float(k), np.zeros(9), np.eye(9), seq=k + 1))
        meas.put(b"garbage")
        # "done" only once the recorder has taken everything: the status goes out on another
        # publisher, which may overtake the data
        wait_for(lambda: statuses[-1].get("recorded", 0) >= 2 * N and statuses[-1].get("rejected", 0) >= 1,
                 "the recorder took what was sent")
        sub.undeclare()
        status.put(status_msg("radar2d", 1, float(N), state="done"))
        out, err = proc.communicate(timeout=30)
        assert proc.returncode == 0, err[-2000:]
    finally:
        if proc.poll() is None:
            proc.kill()
        session.close()
    verify(path)
    rows = read_rrd(path)
    assert len(rows["/world/meas/radar2d"]) == N and len(rows["/world/tracks/centre/T1"]) == N
    assert "malformed" in err


@pytest.mark.slow
def test_run_with_recorder_killed_half_way_completes_unchanged(tmp_path, deployment):
    """Recording never holds the fusion path: kill -9 the recorder mid-run; the run still
    finishes and its fused output equals the in-process evaluation."""
    import psutil

    from services.evaluation import run_method
    from services.scoring import truth_function
    from services.summary import method_summary

    js = tmp_path / "k.json"
    ep = f"tcp/127.0.0.1:{free_port()}"
    keys = KeySpace(deployment)
    session = zenoh.open(ZenohOptions(listen=[ep]).to_config())
    seen = {"fused": 0, "truth": 0}
    subs = [session.declare_subscriber(keys.fused("fuser"), lambda s: seen.__setitem__("fused", seen["fused"] + 1)),
            session.declare_subscriber(keys.all("truth"), lambda s: seen.__setitem__("truth", seen["truth"] + 1))]
    launcher = zfusion("run", "--scenario", "patent-3d", "--speed", "4", "--rrd", str(tmp_path / "k.rrd"),
                       "--json", str(js), "--deployment", deployment, "--connect", ep,
                       stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 60
        # half-way: every process is up and data flows (30 scenario seconds, 31 scans)
        while (seen["fused"] < 8 or not seen["truth"]) and time.monotonic() < deadline:
            time.sleep(0.02)
        assert seen["fused"] >= 8 and seen["truth"], f"the run did not get going: {seen}"
        victims = [p for p in psutil.Process(launcher.pid).children(recursive=True)
                   if "record" in p.cmdline() and "services.cli" in p.cmdline()]
        assert len(victims) == 1, "no recorder process"
        assert seen["fused"] < 31 and launcher.poll() is None, f"the run ended before the kill: {seen}"
        victims[0].send_signal(signal.SIGKILL)
        out, err = launcher.communicate(timeout=60)
    finally:
        if launcher.poll() is None:
            launcher.kill()
        for sub in subs:
            sub.undeclare()
        session.close()
    assert js.exists(), err[-3000:]
    doc = json.loads(js.read_text())
    sc = load_scenario("patent-3d")
    ref = method_summary([run_method(sc, "SS")], truth_function(sc))
    got = doc["methods"]["SS"]
    assert got["n_updates"] == ref["n_updates"] == 31
    np.testing.assert_allclose(got["series"]["rmse_pos"], ref["series"]["rmse_pos"], rtol=0, atol=1e-9)
    assert doc["exit_codes"]["recorder"] == -signal.SIGKILL and doc["exit_codes"]["fuser"] == 0
    # losing the recorder loses the recording, not the run
    assert launcher.returncode == 0, err[-3000:]


# Many targets ------------------------------------------------------------------------------------
def _track_entity(node: str, track: str) -> str:
    return f"/world/tracks/{node}/{track}"


def test_many_target_tracks_have_entities_by_id_and_are_cleared_once_gone(tmp_path):
    """Three crossing aircraft in clutter, distributed (HNV: fused ``T<n>`` and per-node
    ``L<n>`` tracks, coming and going), fed to the recorder as the processes publish
    them: every (node, id) is an entity of its own with one drawn row per estimate,
    labelled with its id; a track its stream stops reporting is cleared once the
    stream has reported ``delete_misses`` frames without it, and not before."""
    from fusion.mtt import AssociationConfig
    from schemas.keys import tracker_id
    from schemas.links import encode_uplink
    from services.evaluation import run_method

    from _recording import report_of

    sc = load_scenario(CROSSING)
    K = AssociationConfig.split(sc.tracker)[0].delete_misses
    out = run_method(sc, "HNV")
    s = Session(tmp_path, scenario=sc)
    seqs: dict[str, int] = {}
    frames: dict[str, list[float]] = {}  # stream -> its frame times
    life: dict[tuple[str, str], list[float]] = {}  # (node, id) -> its report times
    for e in out:
        fused = e.node == "centre"
        src = "fuser" if fused else tracker_id(e.node)
        seq = seqs[src] = seqs.get(src, 0) + 1
        if fused:
            s.put(KEYS.fused("fuser"), encode_estimate(e, src, seq))
        else:
            data = encode_uplink(report_of(e, seq), src, seq)
            s.put(KEYS.local(src), data)
        if not frames.setdefault(src, []) or frames[src][-1] < e.t:
            frames[src].append(e.t)
        life.setdefault((e.node, e.track), []).append(e.t)
    assert s.reject.total == 0
    rows = s.close()

    expected_clear = {}
    for (node, track), times in life.items():
        stream = frames["fuser" if node == "centre" else tracker_id(node)]
        after = [t for t in stream if t > times[-1]]
        expected_clear[(node, track)] = after[K] if len(after) > K else None
    gone = [key for key, t in expected_clear.items() if t is not None]
    assert any(n == "centre" for n, _ in gone) and any(n != "centre" for n, _ in gone), gone  # both kinds go
    drawn_entities = {p for p, rs in rows.items() if p.startswith("/world/tracks/")
                      and any("Points3D:positions" in r for r in rs)}
    assert drawn_entities == {_track_entity(*key) for key in life}
    for (node, track), times in life.items():
        rs = rows[_track_entity(node, track)]
        drawn = [r for r in rs if "Points3D:positions" in r]
        assert [r["t"] for r in drawn] == times, (node, track)
        assert all(track in r["Points3D:labels"][0] for r in drawn)
        clears = [r["t"] for r in rs if r.get("Clear:is_recursive") is not None]
        want = expected_clear[(node, track)]
        assert clears == ([want] if want is not None else []), (node, track, clears, want)
        assert all(r["t"] <= clears[0] for r in drawn) if clears else True


@pytest.mark.parametrize("by", ["node", "centre"])
def test_a_dropped_local_track_is_cleared_at_the_drop(tmp_path, by):
    """A local track the node says it deleted (``drop`` on ``local/<node>``) or the centre
    tells it to delete (``drop_track`` on ``feedback/<node>``) is cleared at the drop's
    time, not drawn as a report or as feedback; the node's other track stays."""
    x, P = [6000.0, 8000.0, 2000.0, 100.0, 0.0, 0.0], np.eye(6)
    s = Session(tmp_path)
    for k, t in enumerate((1.0, 2.0)):
        for j, track in enumerate(("L1", "L2")):
            s.put(KEYS.local("trk-radar2d"), uplink_msg(t, x, P, "HNV", "radar2d", track, nis=0.5, dof=2,
                                                        seq=2 * k + j + 1))
    if by == "node":
        s.put(KEYS.local("trk-radar2d"), encode_uplink(Drop(3.0, "radar2d", 5, "L1"), "trk-radar2d", 5))
    else:
        s.put(KEYS.feedback("trk-radar2d"), encode_downlink(DropTrack("radar2d", 3.0, "L1"), "fuser", 1))
    assert s.reject.total == 0
    rows = s.close()
    for track, clears in (("L1", [3.0]), ("L2", [])):
        rs = rows[_track_entity("radar2d", track)]
        assert [r["t"] for r in rs if "Points3D:positions" in r] == [1.0, 2.0]
        assert [r["t"] for r in rs if r.get("Clear:is_recursive") is not None] == clears, track
    assert not any(p.startswith("/world/feedback/") for p in rows)


@pytest.mark.parametrize("truth_first", [True, False])
def test_many_target_picture_is_scored_as_eval_scores_it(tmp_path, truth_first):
    """Three crossing aircraft in clutter (SS): the recording's GOSPA, targets missed and
    false tracks per frame are the in-process scorer's (``zfusion eval``: scan groups,
    every target), at every frame with a confirmed track, whether the truth of a frame
    comes before its tracks (as in a run) or after all of them. No per-track error is
    logged: a ``T<n>`` names no target."""
    from fusion.metrics import gospa
    from sensors_sim import truth_events
    from services.evaluation import run_method
    from services.scoring import GOSPA_CUTOFF, track_steps

    sc = load_scenario(CROSSING)
    out = run_method(sc, "SS")
    samples = list(truth_events(sc))
    truth = [(x.t, KEYS.truth(x.target), encode("truth", "truth", k + 1, x.t, target=x.target, x=x.x))
             for k, x in enumerate(samples)]
    fused = [(e.t, KEYS.fused("fuser"), encode_estimate(e, "fuser", k + 1)) for k, e in enumerate(out)]
    if truth_first:  # each truth sample just before the estimates of its time
        stream = sorted(truth + fused, key=lambda r: (r[0], r[1] == KEYS.fused("fuser")))
    else:
        stream = fused + truth
    s = Session(tmp_path, scenario=sc)
    for _, key, data in stream:
        assert s.put(key, data) is not None
    rows = s.close()

    steps = [st for st in track_steps(sc, out) if st.tracks]
    want = [gospa(list(st.tracks.values()), list(st.truths.values()), GOSPA_CUTOFF) for st in steps]
    assert len(steps) > 50 and sum(g.n_missed for g in want) > 0
    got = rows["/metrics/gospa/SS"]
    assert [r["t"] for r in got] == [st.t for st in steps]
    np.testing.assert_allclose([r["Scalars:scalars"][0] for r in got], [g.distance for g in want], rtol=1e-12)
    for name, attr in (("missed", "n_missed"), ("false", "n_false")):
        assert [r["Scalars:scalars"][0] for r in rows[f"/metrics/picture/SS/{name}"]] == [getattr(g, attr) for g in want]
    assert not any(p.startswith("/metrics/error_pos") or p.startswith("/metrics/nees") for p in rows)


def test_traffic_picture_scored_against_the_aircraft_alive_and_departed_forgotten(tmp_path):
    """Random traffic (``[traffic]``: aircraft born and leaving, 40-75 s crossings over
    150 s): the recording's GOSPA per frame is the in-process scorer's, which takes the
    aircraft alive at each frame; an aircraft that has left is cleared from the drawing
    at the first truth frame without it and its truth is forgotten after
    ``TRUTH_GONE_FRAMES``, so the recorder holds only the aircraft of late."""
    from fusion.metrics import gospa
    from sensors_sim import truth_events
    from services.evaluation import run_method
    from services.scoring import GOSPA_CUTOFF, track_steps

    text = (ROOT / "sensors_sim/scenarios/air-picture-live.toml").read_text()
    for old, new in (("box_km = [10.0, 45.0, 10.0, 45.0]", "box_km = [15.0, 30.0, 15.0, 30.0]"),
                     ("speed_mps = [150.0, 250.0]", "speed_mps = [200.0, 250.0]"),
                     ("duration_s = 600.0", "duration_s = 150.0")):
        assert old in text
        text = text.replace(old, new)
    (tmp_path / "traffic.toml").write_text(text)
    sc = load_scenario(tmp_path / "traffic.toml")
    out = run_method(sc, "SS")
    samples = list(truth_events(sc))
    truth = [(x.t, KEYS.truth(x.target), encode("truth", "truth", k + 1, x.t, target=x.target, x=x.x))
             for k, x in enumerate(samples)]
    fused = [(e.t, KEYS.fused("fuser"), encode_estimate(e, "fuser", k + 1)) for k, e in enumerate(out)]
    s = Session(tmp_path, scenario=sc)
    held = []  # aircraft whose truth the recorder holds, after each truth frame
    for _, key, data in sorted(truth + fused, key=lambda r: (r[0], r[1] == KEYS.fused("fuser"))):
        assert s.put(key, data) is not None
        held.append(len(s.r.score._truth))
    last_seen = {}
    for x in samples:
        last_seen[x.target] = x.t
    t_end = samples[-1].t
    recent = {a for a, t in last_seen.items() if t_end - t < recorder_mod.TRUTH_GONE_FRAMES + 1}
    assert set(s.r.score._truth) == recent and len(last_seen) > len(recent) + 3, (len(last_seen), len(recent))
    rows = s.close()

    steps = [st for st in track_steps(sc, out) if st.tracks and st.truths]
    want = [gospa(list(st.tracks.values()), list(st.truths.values()), GOSPA_CUTOFF) for st in steps]
    got = rows["/metrics/gospa/SS"]
    assert [r["t"] for r in got] == [st.t for st in steps] and len(steps) > 100
    np.testing.assert_allclose([r["Scalars:scalars"][0] for r in got], [g.distance for g in want], rtol=1e-12)
    gone = sorted(set(last_seen) - {x.target for x in samples if x.t == t_end})
    for a in gone:  # cleared one truth frame after its last sample
        clears = [r["t"] for r in rows[f"/world/truth/{a}"] if r.get("Clear:is_recursive") is not None]
        assert clears == [last_seen[a] + 1.0], (a, clears, last_seen[a])


@pytest.mark.slow
def test_many_target_run_records_every_fused_track_by_id(crossing_run):
    """`zfusion run` on the crossing scenario: the recording has one entity per fused
    track id the fuser published, with one drawn row per published estimate."""
    doc, path, _, _, published = crossing_run
    verify(path)
    rows = read_rrd(path)
    drawn = {e.rsplit("/", 1)[1]: sum("Points3D:positions" in r for r in rs) for e, rs in rows.items()
             if e.startswith("/world/tracks/centre/") and e.count("/") == 4}
    assert len(published) >= 3 and drawn == published
    # the picture's GOSPA in the recording is the run summary's, at every frame it scored
    [(method, summary)] = doc["methods"].items()
    series = dict(zip(summary["series"]["t"], summary["series"]["gospa"]))
    scored = rows[f"/metrics/gospa/{method}"]
    assert len(scored) > 50
    np.testing.assert_allclose([r["Scalars:scalars"][0] for r in scored], [series[r["t"]] for r in scored], rtol=1e-12)


def test_a_path_gets_a_point_per_trail_step_whatever_the_update_rate(tmp_path):
    """A track updated at 100 Hz: one row per update, but its path (each row of it the
    whole path so far) gets a point, and is logged, every TRAIL_STEP_S only, so what the
    recorder sends does not grow with the update rate times the path."""
    s = Session(tmp_path)
    n, dt = 200, 0.01
    xs = [[6000.0 + 100 * k * dt, 8000.0, 2000.0, 100.0, 0, 0, 0, 0, 0] for k in range(n)]
    for k, x in enumerate(xs):
        s.put(KEYS.fused("fuser"), est_msg(k * dt, x, np.eye(9), seq=k + 1))
    rows = s.close()["/world/tracks/centre/T1"]
    assert len(rows) == n
    kept = list(range(0, n, round(draw.TRAIL_STEP_S / dt)))  # the first update of every step
    assert 1 < len(kept) < n / 10
    with_path = [r for r in rows if r.get("LineStrips3D:strips") is not None]
    assert [r["t"] for r in with_path] == pytest.approx([k * dt for k in kept])
    np.testing.assert_allclose(with_path[-1]["LineStrips3D:strips"][0], [xs[k][:3] for k in kept])


def test_an_estimate_older_than_the_truth_kept_is_counted_unscored_not_held(tmp_path, monkeypatch):
    """At --speed max the truth runs far ahead of the fused output: an estimate whose
    truth sample has come and been forgotten (beyond TRUTH_CACHE) can never be scored; it
    is drawn, counted as unscored, and not kept waiting. One still in the cache is scored."""
    monkeypatch.setattr(scoring, "TRUTH_CACHE", 20)
    s = Session(tmp_path)
    n = 50
    for k in range(n):  # all the truth first
        s.put(KEYS.truth("T1"), truth_msg(k + 1, float(k)))
    x = lambda t: [6000.0 + 100 * t + 10.0, 8000.0, 2000.0, 100.0, 0, 0, 0, 0, 0]  # 10 m east of the truth
    for k in range(n):
        s.put(KEYS.fused("fuser"), est_msg(float(k), x(float(k)), np.eye(9), seq=k + 1))
    assert s.r.unscored == n - 20 and s.r.score._n_pending == 0
    rows = s.close()
    assert len(rows["/world/tracks/centre/T1"]) == n  # every estimate drawn
    scored = rows["/metrics/error_pos/SS"]
    assert [r["t"] for r in scored] == [float(k) for k in range(n - 20, n)]
    np.testing.assert_allclose([r["Scalars:scalars"][0] for r in scored], 10.0)


def test_status_counters_are_thinned_to_what_a_plot_needs(tmp_path):
    """A process says its status once a second (the fuser more often): a row per counter
    per status made live recordings grow ~4.5 MB a minute. A counter that changes gets a
    row at most every COUNTER_ROW_S, one that does not every COUNTER_IDLE_S, and the
    final status (done, stopped) every counter's last value."""
    from services.recording.recorder import COUNTER_IDLE_S, COUNTER_ROW_S

    s = Session(tmp_path)
    n = 240  # two minutes of statuses every 0.5 s
    for k in range(n):
        s.put(KEYS.status("df1"), status_msg("df1", k + 1, 0.5 * k, counters={"received": k, "rejected": 0}))
    s.put(KEYS.status("df1"), status_msg("df1", n + 1, 0.5 * n, state="done", counters={"received": n, "rejected": 0}))
    rows = s.close()
    received = [(r["t"], r["Scalars:scalars"][0]) for r in rows["/status/df1/counters/received"]]
    times = [t for t, _ in received]
    assert len(received) <= 0.5 * n / COUNTER_ROW_S + 2, len(received)
    assert all(b - a >= COUNTER_ROW_S for a, b in zip(times[:-2], times[1:-1]))
    assert received[0] == (0.0, 0.0) and received[-1] == (0.5 * n, float(n))  # the first and the last value
    rejected = [r["t"] for r in rows["/status/df1/counters/rejected"]]
    assert rejected == [0.0, COUNTER_IDLE_S, 0.5 * n]  # unchanged: a row a minute, and the final one
