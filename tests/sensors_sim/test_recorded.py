"""Recorded trajectories (sensors_sim/recorded.py).

References: FilterPy's Kalman filter and RTS smoother (the banded solve must give its
smoothed means), exact straight flight, finite differences of the trajectory itself,
pymap3d (the velocity rotation against finite differences of positions), and a known
truth behind the fixture tests/data/adsb/recorded.jsonl: ``make_fixture`` below writes it
from one of the scenario emulators' own trajectories (a straight leg, a 1.72°/s turn, a
descent) sampled as a state-vector recording is (README.md there); ``python
tests/sensors_sim/test_recorded.py`` rewrites the files.
"""

from __future__ import annotations

import gzip
import importlib.metadata
import json
import math
import sys
from pathlib import Path

import numpy as np
import pymap3d
import pytest
from filterpy.kalman import KalmanFilter

from fusion.geodetic import LocalFrame
from sensors_sim import recorded
from sensors_sim.recorded import (
    FPM,
    FT,
    KT,
    Recording,
    SmoothingOptions,
    read_jsonl,
    read_traffic_json,
    records_from_dicts,
    smooth_axis,
    traffic_sample,
)
from sensors_sim.spec import TargetSpec
from sensors_sim.segments import ConstantVelocity, CoordinatedTurn
from sensors_sim.trajectories import Trajectory

DATA = Path(__file__).resolve().parents[1] / "data" / "adsb"
FRAME = LocalFrame(48.85, 2.35, 0.0, deg=True)
T0 = 1633608000  # 2021-10-07 12:00:00 UTC
N = 180  # records of the turning aircraft, one per second
GAP = range(120, 140)  # no records: a coverage hole of 20 s
GLITCH_ALT, GLITCH_POS = 50, 100  # an altitude 21,000 ft off, a position 0.05° off
FROZEN = 6  # the last records repeat the last position heard
TRUTH = Trajectory(TargetSpec("T", np.array([-20e3, -10e3, 3000.0, 120.0, 0.0, -5.0, 0, 0, 0]),
                              (ConstantVelocity(30.0), CoordinatedTurn(rate=0.03, duration=90.0), ConstantVelocity())))


# ------------------------------------------------------------------ the fixture


def local_velocity(lat, lon, v_enu):
    """The truth's velocity (origin ENU axes) in the aircraft's local ENU axes."""
    x, y, z = pymap3d.enu2uvw(*v_enu, FRAME.lat0, FRAME.lon0, deg=True)
    return np.array(pymap3d.uvw2enu(x, y, z, lat, lon, deg=True))


def make_fixture() -> list[dict]:
    """The records, in traffic's form: a turning aircraft with timing jitter, stale
    repeats, two glitches, a gap, a frozen tail and a surface stretch; a second aircraft
    with too few positions."""
    rng = np.random.default_rng(7)
    out = []
    last = None
    for k in range(N):
        tag = k  # scenario seconds after T0
        jitter = rng.uniform(-0.4, 0.4)  # the position's own time, around the tag
        p = TRUTH.position(tag + jitter)
        lat, lon, alt = (float(x) for x in FRAME.to_geodetic(p))
        e, n, u = local_velocity(lat, lon, TRUTH.state(tag)[3:6])
        rec = {"timestamp": (T0 + tag) * 1000, "icao24": "39b002", "callsign": "FHMAC",
               "latitude": round(lat, 7), "longitude": round(lon, 7), "altitude": 25.0 * round(alt / FT / 25.0),
               "groundspeed": float(round(math.hypot(e, n) / KT)), "track": round(math.degrees(math.atan2(e, n)) % 360, 2),
               "vertical_rate": 64.0 * round(u / FPM / 64.0), "onground": False}
        if k % 7 == 3 or k >= N - FROZEN:  # no new position heard: the last one again
            rec.update(latitude=last["latitude"], longitude=last["longitude"], altitude=last["altitude"])
        if k == GLITCH_ALT:
            rec["altitude"] += 21000.0
        if k == GLITCH_POS:
            rec["latitude"] += 0.05
        if k not in GAP:
            out.append(rec)
        if k % 7 != 3 and k < N - FROZEN and k not in (GLITCH_ALT, GLITCH_POS):
            last = rec
    for j in range(8):  # taxiing after landing: on the ground, no altitude
        out.append({"timestamp": (T0 + N + 30 + j) * 1000, "icao24": "39b002", "callsign": "FHMAC",
                    "latitude": 49.0 + j * 1e-4, "longitude": 2.55, "altitude": None, "groundspeed": 20.0,
                    "track": 0.0, "vertical_rate": None, "onground": True})
    for j, lat in enumerate([48.9, 48.9, 48.901]):  # two new positions: too short to smooth
        out.append({"timestamp": (T0 + 10 + j) * 1000, "icao24": "4CA7B1", "callsign": "", "latitude": lat,
                    "longitude": 2.1, "altitude": 24000.0, "groundspeed": 410.0, "track": 150.3,
                    "vertical_rate": 0.0, "onground": False})
    return out


def as_jsonl(items: list[dict]) -> str:
    """The same records in our JSON lines (SI units)."""
    lines = []
    for d in items:
        rec = {"t": d["timestamp"] / 1000, "id": d["icao24"], "callsign": d["callsign"], "lat_deg": d["latitude"],
               "lon_deg": d["longitude"], "on_ground": d["onground"]}
        for key, name, k in [("altitude", "alt_m", FT), ("groundspeed", "gs_m_s", KT), ("track", "track_deg", 1.0),
                             ("vertical_rate", "vrate_m_s", FPM)]:
            if d[key] is not None:
                rec[name] = d[key] * k
        lines.append(json.dumps(rec))
    return "\n".join(lines) + "\n"


def write_fixture() -> None:
    items = make_fixture()
    (DATA / "recorded_traffic.json").write_text(json.dumps(items, indent=0) + "\n")
    (DATA / "recorded.jsonl").write_text(as_jsonl(items))


@pytest.fixture(scope="module")
def fixture_recording() -> Recording:
    return Recording(read_jsonl(DATA / "recorded.jsonl"), FRAME)


def test_the_fixture_files_are_what_the_generator_writes():
    items = make_fixture()
    assert json.loads((DATA / "recorded_traffic.json").read_text()) == items
    assert (DATA / "recorded.jsonl").read_text() == as_jsonl(items)


# ------------------------------------------------------------------ reading


def same_records(a, b) -> None:
    for k in ("t", "lat", "lon", "alt", "gs", "track", "vrate"):
        np.testing.assert_allclose(getattr(a, k), getattr(b, k), rtol=1e-12, atol=0, equal_nan=True)
    assert a.id.tolist() == b.id.tolist() and a.callsign.tolist() == b.callsign.tolist()
    assert a.ground.tolist() == b.ground.tolist()


def test_both_forms_read_alike(tmp_path):
    traffic, ours = read_traffic_json(DATA / "recorded_traffic.json"), read_jsonl(DATA / "recorded.jsonl")
    same_records(traffic, ours)
    assert len(ours) == len(make_fixture()) and not ours.rejected
    gz = tmp_path / "r.json.gz"
    gz.write_bytes(gzip.compress((DATA / "recorded_traffic.json").read_bytes()))
    same_records(read_traffic_json(gz), traffic)
    # sorted by aircraft, then time
    assert ours.id.tolist() == sorted(ours.id.tolist())
    one = ours.id == "39b002"
    assert np.all(np.diff(ours.t[one]) > 0)


def test_units():
    (r,) = [records_from_dicts([{"timestamp": 1633608000500, "icao24": "ABC123", "callsign": " AF1 ", "latitude": 48.0,
                                 "longitude": 2.0, "altitude": 1000, "groundspeed": 100, "track": 90.0,
                                 "vertical_rate": -600, "onground": False}])]
    assert (r.t[0], r.alt[0], r.gs[0], r.vrate[0]) == (1633608000.5, 304.8, pytest.approx(51.4444444444),
                                                       pytest.approx(-3.048))
    assert r.id[0] == "abc123" and r.callsign[0] == "AF1"


def test_malformed_records_are_counted_by_cause(tmp_path):
    good = {"t": T0, "id": "39b002", "lat_deg": 48.0, "lon_deg": 2.0}
    bad = ["not json", json.dumps([1, 2]), json.dumps({**good, "altitude": 3}), json.dumps({**good, "t": None}),
           json.dumps({**good, "lat_deg": "48"}), json.dumps({**good, "lat_deg": 91.0}),
           json.dumps({**good, "gs_m_s": float("nan")}), json.dumps({**good, "on_ground": "yes"}),
           json.dumps({**good, "id": ""}), json.dumps({**good, "callsign": 5}), json.dumps({**good, "t": True}),
           json.dumps({**good, "alt_m": 10 ** 400}), "[" * 100_000, json.dumps(good)]
    path = tmp_path / "bad.jsonl"
    path.write_text("\n".join(bad) + "\n\n")
    r = read_jsonl(path)
    assert len(r) == 1
    assert r.rejected == {"json": 2, "record": 1, "unknown-field": 1, "missing": 2, "value": 4, "range": 3}


@pytest.mark.parametrize("body", [b"{}", b"[" * 100_000, b"\xff\xfe", b"not json"])
def test_a_traffic_file_that_is_not_a_list_is_a_value_error(tmp_path, body):
    path = tmp_path / "x.json"
    path.write_bytes(body)
    with pytest.raises(ValueError, match="x.json"):
        read_traffic_json(path)


def test_traffic_sample_without_traffic(monkeypatch):
    def missing(name):
        raise importlib.metadata.PackageNotFoundError(name)

    monkeypatch.setattr(importlib.metadata, "distribution", missing)
    with pytest.raises(FileNotFoundError, match="pip install --no-deps traffic"):
        traffic_sample()


# ------------------------------------------------------------------ smoothing


def filterpy_rts(t, z, wz, u, wu, q):
    """The RTS smoother of the same model, with a diffuse prior, as FilterPy runs it."""
    kf = KalmanFilter(dim_x=2, dim_z=2)
    kf.x, kf.P = np.zeros(2), np.eye(2) * 1e12
    xs, ps, fs, qs = [], [], [np.eye(2)], [np.zeros((2, 2))]
    for k in range(len(t)):
        if k:
            h = t[k] - t[k - 1]
            F, Q = np.array([[1.0, h], [0.0, 1.0]]), q * np.array([[h ** 3 / 3, h ** 2 / 2], [h ** 2 / 2, h]])
            kf.predict(F=F, Q=Q)
            fs.append(F)
            qs.append(Q)
        rows = [i for i, w in enumerate((wz[k], wu[k])) if w > 0]
        if rows:
            H = np.eye(2)[rows]
            R = np.diag([1.0 / (wz[k], wu[k])[i] for i in rows])
            kf.update(np.array([(z[k], u[k])[i] for i in rows]), R=R, H=H)
        xs.append(kf.x.copy())
        ps.append(kf.P.copy())
    x, _, _, _ = kf.rts_smoother(np.array(xs), np.array(ps), np.array(fs), np.array(qs))
    return x[:, 0], x[:, 1]


def test_smoother_equals_filterpys_rts():
    rng = np.random.default_rng(3)
    t = np.cumsum(rng.uniform(0.3, 4.0, 60))
    z, u = 200.0 * t + 30 * np.sin(t / 7) + rng.normal(0, 20, 60), 200.0 + rng.normal(0, 2, 60)
    wz = np.where(rng.random(60) < 0.3, 0.0, 1 / 20.0 ** 2)
    wu = np.where(rng.random(60) < 0.3, 0.0, 1 / 2.0 ** 2)
    wz[0] = 1 / 20.0 ** 2
    p, v = smooth_axis(t, z[:, None], wz, u[:, None], wu, q=0.7)
    p_ref, v_ref = filterpy_rts(t, z, wz, u, wu, 0.7)
    np.testing.assert_allclose(p[:, 0], p_ref, rtol=0, atol=1e-4)
    np.testing.assert_allclose(v[:, 0], v_ref, rtol=0, atol=1e-6)


def test_straight_flight_is_reproduced_exactly():
    t = np.cumsum(np.r_[0.0, np.random.default_rng(1).uniform(0.5, 3.0, 30)])
    p0, v = np.array([1000.0, -2000.0]), np.array([150.0, -80.0])
    z = p0 + np.outer(t, v)
    p, vel = smooth_axis(t, z, np.full(len(t), 1e-3), np.tile(v, (len(t), 1)), np.full(len(t), 0.25), q=0.5)
    np.testing.assert_allclose(p, z, atol=1e-6)
    np.testing.assert_allclose(vel, np.tile(v, (len(t), 1)), atol=1e-9)


def test_too_few_positions_do_not_fix_a_path():
    with pytest.raises(np.linalg.LinAlgError):
        smooth_axis(np.array([0.0, 1.0, 2.0]), np.zeros((3, 1)), np.array([1.0, 0, 0]), np.zeros((3, 1)),
                    np.zeros(3), q=1.0)


def test_velocity_goes_to_the_origins_axes():
    lat, lon, alt = 48.85, 4.0, 3000.0  # 120 km east of the origin: north there is not north here
    north = recorded._to_origin(FRAME, np.array([lat]), np.array([lon]), np.zeros(1), np.ones(1), np.zeros(1))[0]
    eps = 1e-6
    fd = FRAME.to_enu(lat + eps, lon, alt) - FRAME.to_enu(lat - eps, lon, alt)
    np.testing.assert_allclose(north, fd / np.linalg.norm(fd), atol=1e-6)
    assert math.degrees(math.atan2(north[0], north[1])) == pytest.approx(-(4.0 - 2.35) * math.sin(math.radians(48.85)),
                                                                         abs=0.01)  # meridian convergence, −1.24°


# ------------------------------------------------------------------ the trajectories


def test_segments_gaps_ground_and_ends(fixture_recording):
    rec = fixture_recording
    a, b = rec.of("39b002")
    assert rec.aircraft() == ["39b002"] and len(rec.segments) == 2
    assert (a.start, a.end) == (T0, T0 + GAP[0] - 1)  # the gap ends the first segment
    last_new = max(k for k in range(GAP[-1] + 1, N - FROZEN) if k % 7 != 3)
    assert (b.start, b.end) == (T0 + GAP[-1] + 1, T0 + last_new)  # the frozen tail is not flown
    assert a.callsign == "FHMAC"
    assert rec.counts["dropped.ground"] == 1 and rec.counts["dropped.short"] == 1  # taxiing; 4ca7b1
    assert rec.counts["outliers"] >= 2  # the altitude and the position glitch
    assert [s.id for s in rec.alive(T0 + 60.5)] == ["39b002"]
    assert rec.alive(T0 + 130) == [] and rec.alive(T0 - 1) == [] and rec.alive(T0 + N) == []
    assert len(rec.alive(a.end)) == 1 and len(rec.alive(b.start)) == 1
    assert np.all(np.isnan(a.position(a.end + 0.01))) and np.all(np.isnan(b.position(b.start - 0.01)))
    assert (rec.start, rec.end) == (a.start, b.end)


def test_keep_ground_and_window():
    r = read_jsonl(DATA / "recorded.jsonl")
    kept = Recording(r, FRAME, SmoothingOptions(keep_ground=True))
    assert kept.counts["dropped.no-altitude"] == 1 and "dropped.ground" not in kept.counts
    early = Recording(r, FRAME, window=(T0, T0 + 60))
    (seg,) = early.segments
    assert (seg.start, seg.end) == (T0, T0 + 60)


def test_glitches_are_dropped(fixture_recording):
    seg = fixture_recording.of("39b002")[0]
    truth = TRUTH.position(GLITCH_ALT)
    assert abs(seg.position(T0 + GLITCH_ALT)[2] - truth[2]) < 10.0  # not dragged 6.4 km up
    seg = fixture_recording.of("39b002")[0]
    t = T0 + GLITCH_POS
    assert np.linalg.norm(seg.position(t)[:2] - TRUTH.position(GLITCH_POS)[:2]) < 30.0  # not 5.5 km north


def test_trajectory_is_nearer_the_truth_than_the_records(fixture_recording):
    """The records' positions are off by their timing jitter (up to 0.4 s × 120 m/s); the
    smoothed trajectory, everywhere within its segments, is several times closer."""
    items = [d for d in make_fixture() if d["icao24"] == "39b002" and not d["onground"]]
    raw = []
    for d in items:
        k = d["timestamp"] / 1000 - T0
        p = FRAME.to_enu(d["latitude"], d["longitude"], d["altitude"] * FT)
        if k not in (GLITCH_ALT, GLITCH_POS) and k < N - FROZEN:
            raw.append(np.linalg.norm(p[:2] - TRUTH.position(k)[:2]))
    raw_rms = math.sqrt(np.mean(np.square(raw)))
    errs_h, errs_v = [], []
    for seg in fixture_recording.segments:
        for t in np.arange(seg.start, seg.end, 0.25):
            d = seg.position(t) - TRUTH.position(t - T0)
            errs_h.append(np.linalg.norm(d[:2]))
            errs_v.append(abs(d[2]))
    rms_h = math.sqrt(np.mean(np.square(errs_h)))
    assert raw_rms > 20.0 and rms_h < raw_rms / 3, (raw_rms, rms_h)
    assert max(errs_h) < 30.0 and max(errs_v) < 10.0, (max(errs_h), max(errs_v))
    # velocity: the recorded one is exact to its rounding, but the model (white
    # acceleration) rounds off the turn's acceleration step at 30 s and the end of the
    # first segment inside the turn (119 s): up to ~5.5 m/s there, within 3 s of them
    vel, far = [], []
    for seg in fixture_recording.segments:
        for t in np.arange(seg.start, seg.end, 0.25):
            vel.append(np.linalg.norm(seg.velocity(t) - TRUTH.state(t - T0)[3:6]))
            far.append(min(t - seg.start, seg.end - t, abs(t - T0 - 30)) > 3.0)
    vel, far = np.array(vel), np.array(far)
    assert math.sqrt(np.mean(vel ** 2)) < 1.0 and vel[far].max() < 2.0 and vel.max() < 7.0, (vel.max(), vel[far].max())


def test_held_out_records_are_interpolated(fixture_recording):
    """Every fourth new position left out: the trajectory through the others passes the
    left-out ones as closely as the full fit passes all of them."""
    r = read_jsonl(DATA / "recorded.jsonl")
    fresh = np.r_[True, (np.diff(r.lat) != 0) | (np.diff(r.lon) != 0)] & (r.id == "39b002") & ~r.ground
    held = np.flatnonzero(fresh)[2::4]
    held = held[(r.t[held] - T0 != GLITCH_ALT) & (r.t[held] - T0 != GLITCH_POS)]
    keep = np.ones(len(r), bool)
    keep[held] = False
    sub = recorded.Records(**{k: getattr(r, k)[keep] for k in ("id", "callsign", "t", "lat", "lon", "alt", "gs",
                                                               "track", "vrate", "ground")})
    rec = Recording(sub, FRAME)

    def miss(recording, rows):
        out = []
        for i in rows:
            (seg,) = [s for s in recording.alive(r.t[i]) if s.id == "39b002"] or [None]
            if seg is not None:
                out.append(np.linalg.norm(seg.position(r.t[i]) - FRAME.to_enu(r.lat[i], r.lon[i], r.alt[i])))
        return math.sqrt(np.mean(np.square(out))), len(out)

    held_rms, n = miss(rec, held)
    full_rms, _ = miss(fixture_recording, held)
    assert n >= 25 and held_rms < 1.3 * full_rms and held_rms < 60.0, (held_rms, full_rms, n)


def test_velocity_and_acceleration_are_the_derivatives(fixture_recording):
    rng = np.random.default_rng(5)
    h = 1e-2  # the times are UTC seconds (~1.6e9): float64 resolves 2.4e-7 s
    for seg in fixture_recording.segments:
        for t in seg.t[:-1] + rng.uniform(0.1, 0.9, len(seg.t) - 1) * np.diff(seg.t):
            fd_v = (seg.position(t + h) - seg.position(t - h)) / (2 * h)
            fd_a = (seg.velocity(t + h) - seg.velocity(t - h)) / (2 * h)
            np.testing.assert_allclose(seg.velocity(t), fd_v, atol=2e-3)
            np.testing.assert_allclose(seg.acceleration(t), fd_a, atol=2e-3)
        x = seg.state(seg.t[3])
        np.testing.assert_allclose(x[:3], seg.p[3], atol=1e-9)  # through the smoothed states
        np.testing.assert_allclose(x[3:6], seg.v[3], atol=1e-9)


# ------------------------------------------------------------------ the Paris recording


def test_paris_recording():
    """traffic's quickstart collection, when installed (pip install --no-deps traffic)."""
    try:
        path = traffic_sample()
    except FileNotFoundError:
        pytest.skip("traffic is not installed")
    assert "traffic" not in sys.modules  # found without importing it
    r = read_traffic_json(path)
    assert len(r) == 284_505 and not r.rejected and len(set(r.id.tolist())) == 213
    rec = Recording(r, FRAME, window=(r.t.min(), r.t.min() + 1800))
    assert 45 <= len(rec.segments) and rec.counts["outliers"] < 0.01 * rec.counts["used"]
    peak, res = 0.0, []
    for seg in rec.segments:
        mid = (seg.t[1:] + seg.t[:-1]) / 2
        peak = max(peak, float(np.abs(seg.acceleration(np.r_[seg.t[1:-1], mid])).max()))
    assert peak < 10.0, peak  # no 1 g jolt from the recording's timing
    for seg in rec.segments[::5]:
        rows = np.flatnonzero((r.id == seg.id) & (r.t >= seg.start) & (r.t <= seg.end))
        fresh = rows[np.r_[True, np.diff(r.lat[rows]) != 0]]
        ok = np.isfinite(r.alt[fresh])
        p = FRAME.to_enu(r.lat[fresh][ok], r.lon[fresh][ok], r.alt[fresh][ok])
        res.append(np.linalg.norm((seg.position(r.t[fresh][ok]) - p)[:, :2], axis=1))
    res = np.concatenate(res)
    assert np.percentile(res, 50) < 40.0 and np.percentile(res, 99) < 200.0, np.percentile(res, [50, 99])


if __name__ == "__main__":
    write_fixture()
