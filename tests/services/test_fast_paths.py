"""The hot paths of the fuser against their reference formulations: the single-track EKF
step (Python-float geometry, numpy Cholesky) against the vectorised model and the scipy
formulation it replaced; the wire fast paths against the strict checks (same messages,
same bytes, same rejections with the same cause); and the sensors' look-ahead watermarks."""

from __future__ import annotations

import math

import msgpack
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.linalg import cho_factor, cho_solve

from fusion import batch, kalman
from fusion.angles import wrap_pi
from fusion.ekf import TrackEKF, ekf_predict
from fusion.measurement.models import MIN_HORIZONTAL_RANGE, SphericalModel, _wrap_pi
from fusion.motion import ConstantAcceleration
from fusion.types import Estimate
from schemas import SchemaError, decode, encode, encode_estimate, messages
from schemas.messages import _encode_estimate_fast, _estimate_payload, _validate_fast, _validate_strict

# S of 1-3 rows is factorised on Python floats, 4 rows by numpy (kalman.SMALL_S)
ROWS = [("az", "el", "range"), ("az", "range"), ("az", "el"), ("el",), ("range", "az", "el", "az")]
coord = st.floats(-5e4, 5e4, allow_nan=False)


def _reference_update(x, P, nu, H, R):
    """The update as it was written before (scipy Cholesky solves), for comparison."""
    PHt = P @ H.T
    S = kalman.symmetrise(H @ PHt + R)
    c = cho_factor(S, lower=True)
    K = cho_solve(c, PHt.T).T
    IKH = np.eye(P.shape[0]) - K @ H
    return x + K @ nu, kalman.symmetrise(IKH @ P @ IKH.T + K @ R @ K.T), float(nu @ cho_solve(c, nu))


@settings(max_examples=150, deadline=None)
@given(rows=st.sampled_from(ROWS), pos=st.lists(coord, min_size=3, max_size=3),
       sites=st.lists(coord, min_size=12, max_size=12), noise=st.lists(st.floats(-4.0, 4.0), min_size=4, max_size=4),
       seed=st.integers(0, 2**32 - 1))
def test_single_track_step_equals_reference_formulations(rows, pos, sites, noise, seed):
    n_z = len(rows)
    sites = np.reshape(sites, (4, 3))[:n_z]
    x = np.r_[pos, np.random.default_rng(seed).normal(size=6) * [50, 50, 5, 1, 1, 0.1]]
    d = x[:3] - sites
    if np.hypot(d[:, 0], d[:, 1]).min() < 1.0:
        return  # near-singular geometry: covered by the test below
    std = np.array([0.01 if c != "range" else 20.0 for c in rows])
    model = SphericalModel(rows, sites, std)
    z = model.h(x) + std * np.array(noise[:n_z])
    z = np.where(model.angles, np.mod(z, 2 * np.pi), z)  # azimuths near 0 / 2π wrap in ν
    nu, H = model.innovation_and_jacobian(z, x)
    # the vectorised model (h, angle wrap) and the batch module's gradients, written separately
    # (to 1e-12 of the measurement: math.hypot and np.hypot may round the last bit differently)
    np.testing.assert_allclose(nu, model.innovation(z, x), rtol=0, atol=1e-12 * max(1.0, np.abs(z).max()))
    zp, Hp = batch.spherical(model, x[None])
    np.testing.assert_allclose(H[:, :3], Hp[0], rtol=1e-12, atol=1e-15)
    assert not H[:, 3:].any()
    np.testing.assert_array_equal(model.jacobian(x), H)
    # the Kalman step, against the scipy formulation it replaced
    A = np.random.default_rng(seed + 1).normal(size=(9, 9))
    P = A @ A.T + np.diag([1e4] * 3 + [1e2] * 3 + [1.0] * 3)
    res = kalman.update(x, P, nu, H, model.R)
    x_ref, P_ref, nis_ref = _reference_update(x, P, nu, H, model.R)
    np.testing.assert_allclose(res.x, x_ref, rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(res.P, P_ref, rtol=1e-12, atol=1e-12 * np.abs(P_ref).max())
    assert res.nis == pytest.approx(nis_ref, rel=1e-10, abs=1e-12)
    assert np.array_equal(res.P, res.P.T) and res.nis >= 0.0


def test_track_ekf_uses_the_shared_step_and_keeps_its_checks():
    motion = ConstantAcceleration(0.01)
    model = SphericalModel(("az", "el", "range"), [100.0, -200.0, 5.0], [0.02, 0.02, 20.0])
    x0 = np.array([5000.0, 8000.0, 1000.0, 100.0, -50.0, 2.0, 0.1, 0.2, 0.0])
    P0 = np.diag([1e4] * 3 + [1e2] * 3 + [1.0] * 3)
    ekf = TrackEKF(motion, x0, P0, 0.0)
    ekf.predict(1.0)
    z = model.h(ekf.x) + [0.01, -0.01, 30.0]
    res = ekf.update(model, z)
    xp, Pp = ekf_predict(motion, x0, P0, 1.0)
    x_ref, P_ref, nis_ref = _reference_update(xp, Pp, model.innovation(z, xp), model.jacobian(xp), model.R)
    np.testing.assert_allclose(ekf.x, x_ref, rtol=1e-12)
    np.testing.assert_allclose(ekf.P, P_ref, rtol=1e-10, atol=1e-12 * np.abs(P_ref).max())
    assert res.nis == pytest.approx(nis_ref, rel=1e-10)
    # singular geometry and bad shapes raise as the vectorised model does
    above = np.r_[100.0 + MIN_HORIZONTAL_RANGE / 4, -200.0, 900.0, np.zeros(6)]
    with pytest.raises(ValueError, match="straight above"):
        model.h(above)
    with pytest.raises(ValueError, match="straight above"):
        model.innovation_and_jacobian(z, above)
    with pytest.raises(ValueError, match="shape"):
        model.innovation_and_jacobian(z[:2], xp)
    with pytest.raises(ValueError, match="one state vector"):
        model.jacobian(np.stack([xp, xp]))
    for n in (1, 2, 3, 4):  # S not positive definite, on either side of SMALL_S
        S = np.eye(n)
        S[-1, -1] = -1e-9
        with pytest.raises(np.linalg.LinAlgError):
            kalman.inverse_cholesky_factor(S)
        S[-1, -1] = math.nan  # garbage in, NaN out: on both sides, as numpy's cholesky does
        assert np.isnan(kalman.inverse_cholesky_factor(S)[-1, -1])
    with pytest.raises(np.linalg.LinAlgError):
        kalman.update(xp, Pp, np.zeros(3), model.jacobian(xp), -np.eye(3) * 1e12)


@given(st.floats(-50.0, 50.0) | st.sampled_from([math.pi, -math.pi, 3 * math.pi, -3 * math.pi, 0.0, -0.0]))
def test_scalar_angle_wrap_equals_wrap_pi(a):
    assert _wrap_pi(a) == wrap_pi(a)


# Wire format -------------------------------------------------------------------------------
def _good_measurement() -> dict:
    return {"v": 1, "kind": "az_el_range", "src": "r1", "seq": 7, "t": 2.5, "sensor": "r1",
            "site": [1.0, -2.0, 3.0], "az": 1.0, "std_az": 0.02, "el": -0.1, "std_el": 0.02,
            "range": 5e3, "std_range": 10.0}


def _good_watermark() -> dict:
    return {"v": 1, "kind": "watermark", "src": "r1", "seq": 3, "t": 2.5, "final": False}


def _good_track() -> dict:
    return {"v": 1, "kind": "track", "src": "r1", "seq": 4, "t": 2.5, "track": "T1", "node": "centre",
            "method": "SS", "x": [1.0, -2.0, 3.0], "P": [[4.0, 0.5, 0.0], [0.5, 9.0, -1.0], [0.0, -1.0, 1.0]],
            "nis": 1.5, "nis_dof": 3, "extra": {}}


BAD_VALUES = [[[4.0, 0.5, 0.0], [0.5, 9.0, -1.0], [0.0, -1.0, 1.0]], [[4.0, 0.5, 0.0], [0.6, 9.0, -1.0],
              [0.0, -1.0, 1.0]], [[4, 0, 0], [0, 9, 0], [0, 0, True]], [[1.0, 0.0], [0.0, 1.0]],
              [[-1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]], [[1.0, 0.0, 0.0], [0.0, "1", 0.0], [0.0, 0.0, 1.0]],
              [[1.0, 0.0, math.nan], [0.0, 1.0, 0.0], [math.nan, 0.0, 1.0]], [[1.0, 2.0, 3.0]], 3, "centre", "T1",
              None, True, False, 0, 1, -1, 2**63, 0.0, -0.0, 1.5, -1.0, 7.0, math.pi / 2, -math.pi / 2,
              2 * math.pi, math.nan, math.inf, -math.inf, "r1", "a b", "", "x" * 65, [], [1.0, 2.0],
              [1.0, 2.0, 3.0], [1, 2, 3], [1.0, math.nan, 2.0], [True, 1.0, 2.0], {"a": 1}, "az_el_range",
              "watermark", "range_az"]


def _same_outcome(d: dict) -> None:
    """validate (fast path first) and the strict checks alone give the same message or the
    same error."""
    try:
        want = _validate_strict(d)
    except SchemaError as e:
        with pytest.raises(SchemaError) as got:
            messages.validate(d)
        assert (got.value.cause, got.value.field, str(got.value)) == (e.cause, e.field, str(e))
        assert _validate_fast(d) is None
        return
    got = messages.validate(d)
    assert (got.kind, got.src, got.seq, got.t, got.v) == (want.kind, want.src, want.seq, want.t, want.v)
    assert type(got.t) is type(want.t) and got.body.keys() == want.body.keys()
    for k, v in want.body.items():
        if isinstance(v, np.ndarray):
            assert got.body[k].dtype == v.dtype and np.array_equal(got.body[k], v)
        else:
            assert type(got.body[k]) is type(v) and got.body[k] == v


@settings(max_examples=400, deadline=None)
@given(base=st.sampled_from(["meas", "wm", "track"]), data=st.data())
def test_fast_decode_equals_strict_decode(base, data):
    d = {"meas": _good_measurement, "wm": _good_watermark, "track": _good_track}[base]()
    decode(msgpack.packb(d))  # ids become known once the strict path has seen them
    for _ in range(data.draw(st.integers(0, 3))):
        field = data.draw(st.sampled_from(sorted(d) + ["extra", "final", "az", "bearing", "kind"]))
        if data.draw(st.booleans()) and field in d:
            del d[field]
        else:
            d[field] = data.draw(st.sampled_from(BAD_VALUES) | st.floats())
    _same_outcome(d)
    assert _same_decode(msgpack.packb(d, use_bin_type=True))


def _same_decode(data: bytes) -> bool:
    try:
        a = decode(data)
    except SchemaError as e:
        try:
            _validate_strict(msgpack.unpackb(data, strict_map_key=False))
        except SchemaError as e2:
            return e.cause == e2.cause
        return False
    return a.kind == _validate_strict(msgpack.unpackb(data, strict_map_key=False)).kind


def test_fast_decode_takes_the_common_messages_and_leaves_the_rest():
    decode(msgpack.packb(_good_measurement()))  # ids become known once the strict path has seen them
    assert _validate_fast(_good_measurement()) is not None
    assert _validate_fast(_good_watermark()) is not None
    decode(msgpack.packb(_good_track()))
    assert _validate_fast(_good_track()) is not None
    almost = _good_track()
    almost["P"][0][1] += 1e-15  # symmetric within the strict tolerance only: the strict path accepts it
    assert _validate_fast(almost) is None and messages.validate(almost).body["P"][0, 1] == almost["P"][0][1]
    assert _validate_fast({**_good_measurement(), "range": 5000}) is None  # an int: the strict path converts
    assert messages.validate({**_good_measurement(), "range": 5000}).body["range"] == 5000.0
    assert _validate_fast({**_good_measurement(), "src": "never-seen"}) is None
    with pytest.raises(SchemaError, match="range"):
        decode(msgpack.packb({**_good_measurement(), "el": 2.0}))


def _estimate(P, x=None, nis=1.5, dof=3, track="T1", node="centre", t=4.0, extra=None) -> Estimate:
    x = np.arange(1.0, 4.0) if x is None else x
    return Estimate(t, x, P, "SS", node, track, nis, dof, extra or {})


def _strict_encode(e: Estimate) -> bytes:
    return encode("track", "fuser", 9, e.t, **_estimate_payload(e))


@settings(max_examples=300, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), flaw=st.sampled_from(
    ["none", "asym-tiny", "asym", "nan", "inf", "neg-var", "x-nan", "nis-neg", "nis-nan", "dof-0", "dof-np",
     "track-bad", "node-new", "t-inf", "int-x", "extra", "extra-none", "nis-np", "shape"]))
def test_fast_encode_equals_strict_encode(seed, flaw):
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(3, 3)) * rng.choice([1e-3, 1.0, 1e4])
    P = kalman.symmetrise(A @ A.T + np.eye(3))
    kw: dict = {}
    x = rng.normal(size=3) * 1e3
    if flaw == "asym-tiny":
        P[0, 1] += 1e-13 * abs(P[0, 1])  # within the strict tolerance: accepted by the strict path
    elif flaw == "asym":
        P[0, 1] += 1.0 + abs(P[0, 1])
    elif flaw in ("nan", "inf"):
        P[1, 2] = P[2, 1] = math.nan if flaw == "nan" else math.inf
    elif flaw == "neg-var":
        P[2, 2] = -1.0
    elif flaw == "x-nan":
        x[1] = math.nan
    elif flaw == "int-x":
        x = np.arange(3)
    elif flaw == "shape":
        x = np.zeros(4)
    kw = {"nis-neg": {"nis": -1.0}, "nis-nan": {"nis": math.nan}, "dof-0": {"dof": 0}, "dof-np": {"dof": np.int64(3)},
          "track-bad": {"track": "a/b"}, "node-new": {"node": f"n{seed}"}, "t-inf": {"t": math.inf},
          "extra": {"extra": {"KH": np.eye(3)}}, "extra-none": {"extra": {"feedback_t": None}},
          "nis-np": {"nis": np.float64(2.0)}}.get(flaw, {})
    e = _estimate(P, x, **kw)
    try:
        want = _strict_encode(e)
    except SchemaError as err:
        with pytest.raises(SchemaError) as got:
            encode_estimate(e, "fuser", 9)
        assert (got.value.cause, got.value.field) == (err.cause, err.field)
        return
    assert encode_estimate(e, "fuser", 9) == want


def test_fast_encode_takes_a_fused_track():
    P = np.diag([4.0, 9.0, 1.0])
    e = _estimate(P)
    first = encode_estimate(e, "fuser", 9)  # the strict path learns the ids
    fast = _encode_estimate_fast(e, "fuser", 9)
    assert fast is not None and fast == first == _strict_encode(e)
    assert decode(fast).body["P"].tolist() == P.tolist()
    P_off = P.copy()
    P_off[0, 1] = 1e-15  # not exactly symmetric: the strict path decides (and accepts, within tolerance)
    assert _encode_estimate_fast(_estimate(P_off), "fuser", 1) is None
    assert decode(encode_estimate(_estimate(P_off), "fuser", 1)).kind == "track"


# Look-ahead watermarks ---------------------------------------------------------------------
class _FakeNode:
    """What a sensor's play loop uses of :class:`services.node.Node`, recording the puts."""

    def __init__(self, sensor_id: str):
        from schemas import KeySpace

        self.id = sensor_id
        self.keys = KeySpace("fast")
        self.sent: list[bytes] = []
        self.counters: dict[str, int] = {}

    def publisher(self, key, reliable=True):
        node = self

        class _Pub:
            def put(self, data):
                node.sent.append(data)

        return _Pub()

    def count(self, name, n=1):
        self.counters[name] = self.counters.get(name, 0) + n

    def publish_status(self, *a, **k):
        pass


def test_sensor_watermarks_look_ahead_to_the_next_scan():
    import threading

    from sensors_sim import load_scenario, sensor_events
    from services import source

    sc = load_scenario("patent-3d")
    sid = next(iter(sc.sensors))
    node = _FakeNode(sid)
    node.stop = threading.Event()
    source._play_sensor(node, sc, source.Pacer(node, 0.0, math.inf), 0)
    msgs = [decode(b) for b in node.sent]
    scans = sorted({ev.t for ev in sensor_events(sc, sid)})
    wms = [m for m in msgs if m.kind == "watermark"]
    # one watermark right after each scan's data, promising everything up to just before the next scan
    assert [m.t for m in wms[:-1]] == [math.nextafter(t, -math.inf) for t in scans[1:]]
    assert wms[-1].body["final"] and not any(m.body["final"] for m in wms[:-1])
    promised = -math.inf
    for m in msgs:  # the promise holds: nothing arrives at or before a published watermark
        if m.kind == "watermark":
            assert m.t >= promised
            promised = m.t
        else:
            assert m.t > promised
    meas_t = [m.t for m in msgs if m.kind != "watermark"]
    assert meas_t and meas_t == sorted(meas_t)


# Recorder: rows sent as columns ----------------------------------------------------------
def test_recorder_rows_sent_as_columns_equal_rows_logged_one_by_one(tmp_path):
    """The same samples recorded through the batching stream and through one ``log`` per
    row read back the same, entity by entity and row by row."""
    import rerun as rr

    from schemas import KeySpace
    from services.recording import recorder as rec_mod, stream
    from services.recording.draw import PATH_MAX
    from _recording import est_msg, meas_msg, read_rrd, status_msg, truth_msg, verify

    class OneByOne(stream.Recording):
        def row(self, path, t, parts):
            self.set_time(stream.TIMELINE, duration=t)
            self.log(path, *[archetype(**components) for archetype, components in parts])

    keys = KeySpace("rtest")
    samples = []
    for k in range(PATH_MAX // 50 + 60):  # trails of many points; a few runs of different shapes
        t = 0.5 * k
        x = np.array([6000.0 + 100 * t, 8000.0, 2000.0, 100.0, 0, 0, 0, 0, 0])
        samples.append((keys.truth("T1"), truth_msg(k + 1, t)))
        samples.append((keys.meas("radar2d"), meas_msg("radar2d", "range_az", [0.64, 10200.0 + k], [0.017, 20.0], t, k)))
        samples.append((keys.meas("angle"), meas_msg("angle", "azel", [0.64, 0.19], [1e-3, 1e-3], t, k)))
        if k % 7:  # some scans without a 3D radar report: the entity's runs change shape
            samples.append((keys.meas("r3"), meas_msg("r3", "az_el_range", [0.6, 0.2, 9000.0 + k], [1e-3, 1e-3, 9.0],
                                                   t, k, site=(10.0, 0.0, 0.0))))
        P = np.diag([400.0, 300.0, 200.0] + [10.0] * 6)
        P[0, 1] = P[1, 0] = 50.0 + k
        samples.append((keys.fused("fuser"), est_msg(t, x + [30.0, -40.0, 0, 0, 0, 0, 0, 0, 0], P, nis=1.0 + k % 5, dof=3,
                                           seq=k + 1)))
        if k % 10 == 0:
            samples.append((keys.status("fuser"), status_msg("fuser", k, t, role="fuser", counters={"held": k},
                                                          events=[f"event {k}"] if k % 20 == 0 else [])))
    files = {}
    for name, cls in (("columns", stream.Recording), ("rows", OneByOne)):
        path = tmp_path / f"{name}.rrd"
        rec = cls("zfusion")
        rec.set_sinks(rr.FileSink(str(path)))
        r = rec_mod.Recorder(rec, keys)
        for i, (key, data) in enumerate(samples):
            assert r.offer(key, data) is not None
            if i % 97 == 0:
                rec.send_rows()  # sent in several batches, as the process does
        rec.flush()
        rec.disconnect()
        verify(path)
        files[name] = read_rrd(path)
    got, want = files["columns"], files["rows"]
    assert got.keys() == want.keys() and len(want) >= 15
    for entity, rows in want.items():
        assert len(got[entity]) == len(rows), entity
        for a, b in zip(got[entity], rows):
            assert a.keys() == b.keys() and a["t"] == b["t"], entity
            for col in b:
                assert np.array_equal(np.asarray(a[col], dtype=object), np.asarray(b[col], dtype=object)), (entity, col)
    trail = got["/world/tracks/centre/T1"][-1]["LineStrips3D:strips"][0]
    assert len(trail) == len([s for s in samples if s[0] == keys.fused("fuser")])


def test_trail_views_are_never_changed_by_later_points():
    from services.recording.draw import PATH_MAX, Trail

    trail = Trail()
    views = []
    for k in range(3 * PATH_MAX):  # two points a step; keep the second view
        trail.add(np.array([k, 0.0, 0.0]))
        views.append((k, trail.add(np.array([k + 0.5, 0.0, 0.0]))))
    for k, view in views[::97] + views[-3:]:
        n = min(2 * k + 2, PATH_MAX)
        assert len(view) == n and view[-1, 0] == k + 0.5
        np.testing.assert_array_equal(np.diff(view[:, 0]), 0.5)  # consecutive points, none overwritten


def test_ellipsoid_quaternion_equals_scipy():
    from scipy.spatial.transform import Rotation

    from services.recording.draw import quaternion

    mats = list(Rotation.random(500, random_state=3).as_matrix())
    mats += [np.eye(3), np.diag([1.0, -1.0, -1.0]), np.diag([-1.0, 1.0, -1.0]), np.diag([-1.0, -1.0, 1.0])]
    for R in mats:
        q, ref = quaternion(R), Rotation.from_matrix(R).as_quat()
        assert min(np.abs(q - ref).max(), np.abs(q + ref).max()) < 1e-12
