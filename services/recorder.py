"""The recorder process: everything on the deployment's keys into one Rerun recording.

Timeline ``sim_time`` (scenario seconds). Entity layout::

    world/sites/<sensor>                 labelled sensor positions
    world/truth/<target>                 true position (+ its path so far)
    world/meas/<sensor>                  measurements: points (with range) or rays (angles only)
    world/tracks/<node>/<track>          estimates with their 3σ ellipsoid / ellipse
    world/jam/<jammer>                   jammer position, on/off
    metrics/error_pos/<method>           position error against truth
    metrics/nees/<method>[/lo|/hi]       NEES against its two-sided 95 % χ² bounds
    metrics/nis/<method>[/lo|/hi]        NIS against its bounds
    status/<process>/events              text log (source declared dead, rejoined, ...)
    status/<process>/<counter>           counters

The recorder is only a listener: the fusion path never waits on it (its subscription is
served by Zenoh's threads into a queue; the fuser's publishers do not know it exists).
"""

from __future__ import annotations

import math
import queue
import time
from collections import OrderedDict

import numpy as np
import rerun as rr
import rerun.blueprint as rrb
from scipy.stats import chi2

from fusion.types import KIND_COMPONENTS
from schemas import KeySpace, Message, SchemaError, decode, to_estimate, to_measurement

from .node import Node

DEFAULT_RAY_M = 20_000.0
TRUTH_CACHE = 4096  # truth samples kept per target, to score estimates against


def blueprint() -> rrb.Blueprint:
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Spatial3DView(origin="world", name="Scene"),
            rrb.Vertical(
                rrb.TimeSeriesView(origin="metrics/error_pos", name="Position error (m)"),
                rrb.TimeSeriesView(origin="metrics/nees", name="NEES vs 95% χ² bounds"),
                rrb.TimeSeriesView(origin="metrics/nis", name="NIS vs 95% χ² bounds"),
            ),
            rrb.TextLogView(origin="status", name="Events"),
            column_shares=[3, 2, 1],
        ),
        collapse_panels=True,
    )


def _unit(az: float, el: float = 0.0) -> np.ndarray:
    """ENU unit vector of a compass azimuth and an elevation."""
    return np.array([math.sin(az) * math.cos(el), math.cos(az) * math.cos(el), math.sin(el)])


def ellipsoid(P: np.ndarray, n_sigma: float = 3.0) -> tuple[np.ndarray, np.ndarray]:
    """Half-sizes and rotation quaternion (x, y, z, w) of the n-σ ellipsoid of a 3×3 covariance."""
    w, V = np.linalg.eigh(0.5 * (P + P.T))
    if np.linalg.det(V) < 0:
        V[:, 0] = -V[:, 0]
    half = n_sigma * np.sqrt(np.clip(w, 0.0, None))
    from scipy.spatial.transform import Rotation

    return half, Rotation.from_matrix(V).as_quat()


class Recorder:
    """Turns validated messages into Rerun log calls on one recording stream."""

    def __init__(self, rec: rr.RecordingStream, keys: KeySpace):
        self.rec = rec
        self.keys = keys
        self.truth: dict[str, OrderedDict[float, np.ndarray]] = {}
        self.paths: dict[str, list[list[float]]] = {}
        self.sites_logged: set[str] = set()
        self.last_fix: np.ndarray | None = None
        self.rows: dict[str, int] = {}
        # Truth and estimates come from different processes, so either may arrive first:
        # estimates wait here (bounded) for the truth sample of their time.
        self.unscored: OrderedDict[tuple[float, str, str], object] = OrderedDict()

    def _log(self, path: str, t: float, *archetypes: object) -> None:
        self.rec.set_time("sim_time", duration=t)
        self.rec.log(path, *archetypes)  # one row per message
        self.rows[path] = self.rows.get(path, 0) + 1

    def handle(self, family: str, msg: Message) -> None:
        getattr(self, f"_on_{msg.kind}", self._on_measurement if family == "meas" else lambda m: None)(msg)

    # -- measurements ------------------------------------------------------------------------

    def _on_measurement(self, msg: Message) -> None:
        m = to_measurement(msg)
        site = np.asarray(m.site, dtype=float)
        if m.sensor not in self.sites_logged:
            self.sites_logged.add(m.sensor)
            self.rec.set_time("sim_time", duration=m.t)
            self.rec.log(f"world/sites/{m.sensor}", rr.Points3D([site], labels=[m.sensor], radii=[150.0]),
                         static=True)
        path = f"world/meas/{m.sensor}"
        z = dict(zip(KIND_COMPONENTS[m.kind], m.z))
        if "range" in z:
            # A 2D radar gives no elevation: its slant range is drawn in the site's horizontal plane.
            p = site + z["range"] * _unit(z["az"], z.get("el", 0.0))
            self._log(path, m.t, rr.Points3D([p], radii=[60.0]))
        else:
            length = DEFAULT_RAY_M
            if self.last_fix is not None:
                length = 1.5 * float(np.linalg.norm(self.last_fix[: len(site)] - site[: len(self.last_fix)]))
            end = site + length * _unit(z["az"], z.get("el", 0.0))
            self._log(path, m.t, rr.LineStrips3D([[site, end]], radii=[20.0]))

    def _on_watermark(self, msg: Message) -> None:
        pass

    # -- truth, tracks, metrics ------------------------------------------------------------------

    def _on_truth(self, msg: Message) -> None:
        tgt, x = msg.body["target"], msg.body["x"]
        cache = self.truth.setdefault(tgt, OrderedDict())
        cache[msg.t] = x
        while len(cache) > TRUTH_CACHE:
            cache.popitem(last=False)
        for key in [k for k in self.unscored if k[0] == msg.t]:
            self._score(self.unscored.pop(key), cache)
        pos = _pos3(x)
        self.paths.setdefault(tgt, []).append(pos.tolist())
        self._log(f"world/truth/{tgt}", msg.t, rr.Points3D([pos], labels=[tgt], radii=[80.0], colors=[[0, 200, 0]]),
                  rr.LineStrips3D([self.paths[tgt]], colors=[[0, 160, 0]]))

    def _on_track(self, msg: Message) -> None:
        e = to_estimate(msg)
        pos = _pos3(e.x)
        d = 3 if e.x.size >= 6 else 2
        Pp = np.zeros((3, 3))
        Pp[:d, :d] = e.P[:d, :d]
        if d == 2:
            self.last_fix = pos
            Pp[2, 2] = 1.0  # flat ellipse on the map plane
        half, quat = ellipsoid(Pp)
        self._log(f"world/tracks/{e.node}/{e.track}", e.t,
                  rr.Points3D([pos], labels=[f"{e.method}:{e.track}"], radii=[60.0]),
                  rr.Ellipsoids3D(centers=[pos], half_sizes=[half], quaternions=[quat]))
        if e.node != "centre":
            return  # metrics are for fused output; local tracks are drawn only
        if e.nis is not None and e.nis_dof:
            self._series(f"metrics/nis/{e.method}", e.t, e.nis, e.nis_dof)
        truth = self.truth.get(e.track) or (next(iter(self.truth.values())) if len(self.truth) == 1 else None)
        if truth is not None and e.t in truth:
            self._score(e, truth)
        else:
            self.unscored[(e.t, e.method, e.track)] = e
            while len(self.unscored) > TRUTH_CACHE:
                self.unscored.popitem(last=False)

    def _score(self, e, truth: OrderedDict) -> None:
        err = e.x - truth[e.t][: e.x.size]
        d = 3 if e.x.size >= 6 else 2
        self._log(f"metrics/error_pos/{e.method}", e.t, rr.Scalars([float(np.linalg.norm(err[:d]))]))
        try:
            nees = float(err @ np.linalg.solve(e.P, err))
        except np.linalg.LinAlgError:
            return
        self._series(f"metrics/nees/{e.method}", e.t, nees, e.x.size)

    _on_prediction = _on_track

    def _series(self, path: str, t: float, value: float, dof: int) -> None:
        lo, hi = chi2.ppf([0.025, 0.975], dof)
        self._log(path, t, rr.Scalars([value]))
        self._log(f"{path}/lo", t, rr.Scalars([float(lo)]))
        self._log(f"{path}/hi", t, rr.Scalars([float(hi)]))

    def _on_jam_state(self, msg: Message) -> None:
        b = msg.body
        self._log(f"world/jam/{msg.src}", msg.t,
                  rr.Points3D([b["pos"]], labels=[f"{msg.src} ({b['mode']}, {'on' if b['on'] else 'off'})"],
                              radii=[200.0], colors=[[220, 0, 0] if b["on"] else [120, 120, 120]]))
        self._log(f"status/{msg.src}/on", msg.t, rr.Scalars([1.0 if b["on"] else 0.0]))

    def _on_status(self, msg: Message) -> None:
        b = msg.body
        for ev in b["events"]:
            self._log(f"status/{msg.src}/events", msg.t, rr.TextLog(ev, level="WARN" if "dead" in ev else "INFO"))
        for name, v in b["counters"].items():
            self._log(f"status/{msg.src}/{name}", msg.t, rr.Scalars([float(v)]))


def _pos3(x: np.ndarray) -> np.ndarray:
    x = np.asarray(x, dtype=float)
    return x[:3].copy() if x.size >= 6 else np.array([x[0], x[1], 0.0])


def run(process_id: str, keys: KeySpace, zopts, rrd_path: str, expect: list[str], app: str = "zfusion") -> int:
    inbox: queue.SimpleQueue[tuple[str, bytes]] = queue.SimpleQueue()
    rec = rr.RecordingStream(app)
    rec.save(rrd_path, default_blueprint=blueprint())
    recorder = Recorder(rec, keys)
    finished: set[str] = set()
    with Node(process_id, "recorder", keys, zopts) as node:
        node.subscribe(keys.all(), lambda s: inbox.put((str(s.key_expr), s.payload.to_bytes())))
        node.announce()
        node.publish_status("ready")
        last_status = time.monotonic()
        while not node.stop.is_set():
            try:
                key, data = inbox.get(timeout=0.1)
            except queue.Empty:
                pass
            else:
                try:
                    family, ident = keys.family_and_id(key)
                    msg = decode(data)
                except (SchemaError, ValueError) as e:
                    node.reject(key.rsplit("/", 1)[-1], getattr(e, "cause", "key"), str(e))
                    continue
                recorder.handle(family, msg)
                node.count("recorded")
                if msg.kind == "status" and msg.body["state"] in ("done", "stopped"):
                    finished.add(msg.src)
            if expect and set(expect) <= finished and inbox.empty():
                break
            if time.monotonic() - last_status >= 1.0:
                node.publish_status("running")
                last_status = time.monotonic()
        rec.flush()
        node.publish_status("done")
    rec.flush()
    rec.disconnect()
    return 0
