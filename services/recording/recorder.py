"""The recorder process: everything on the deployment's keys into one Rerun recording.

Timeline ``sim_time`` (scenario seconds); in a live session (``--site``) timeline
``utc``, a timestamp timeline (``t`` is UTC there), and stamps more than ``--max-skew``
ahead of this host's clock are refused. Entities live under ``world/`` (sites,
measurements as points or rays, truth, tracks per node with their 3σ ellipsoids or
ellipses, predictions, uplinks, feedback, jammers), ``metrics/`` (position error, NEES
and NIS against their χ² bounds, a many-target picture's GOSPA, missed and false
tracks) and ``status/`` (events and counters); ``map/`` holds sites, bearings, truth
and tracks in lat/lon for the map view (:mod:`services.recording.map`). docs/design.md
("Recording") lists them and docs/viewing.md says what each shows. A blueprint lays out
the panels.

Many targets: each track is an entity keyed by (node, id) and is cleared (``rr.Clear``,
recursively) once its stream has reported ``delete_misses`` frames without it, or at
once when the centre tells its node to ``drop`` it; a cleared track's path and frame
bookkeeping are forgotten, so state is held for the live tracks only. The ``metrics/``
panels draw what the scoring hands back (:class:`services.scoring.LiveScore`: errors and
NEES per estimate, the fused picture's GOSPA per frame, as ``zfusion eval`` scores
them); the recorder computes none of it. Targets come and go too
(``[traffic]``): a target missing from one truth frame is cleared from the drawing, and
one missing from ``TRUTH_GONE_FRAMES`` frames is forgotten (its truth samples, path and
duplicate bookkeeping), so truth is held for the targets alive of late only.

Bounded work per row: a path gets a point at most every ``TRAIL_STEP_S`` of scenario
time and keeps ``PATH_MAX`` points; a 3D path is logged only with the row that adds a
point; :class:`Recording` queues rows and sends each entity's in one ``send_columns``
call at least every ``SEND_PERIOD_S``. The recorder only listens
(:func:`services.listener.run_listener`): its subscription feeds a bounded queue
(overflow counted and dropped, never pushed back to a publisher; beyond
``BACKLOG_IN_MEMORY`` samples it waits in a temporary file, not in memory), and every
sample that fails to decode, arrives on the wrong key, repeats, or lies beyond the
scenario's end is counted by cause and dropped (:class:`services.intake.Intake`).
docs/notes.md ("Recorder paths") says why paths are thinned.
"""

from __future__ import annotations

import functools
import logging
import math
import time
from collections import deque
from functools import lru_cache

import numpy as np
import rerun as rr

from fusion.links import Drop, DropTrack, Init, InitRequest, LocalReport, MeasurementReport, PredictionReport
from fusion.mtt import AssociationConfig
from fusion.measurement.kinds import KINDS, SPHERE
from fusion.types import Estimate, Measurement
from schemas import KeySpace, Message, to_estimate, to_measurement
from schemas.links import downlink, uplink
from schemas.keys import DEFAULT_FUSER
from sensors_sim.spec import DF_KINDS

from . import draw
from . import map as recorder_map
from ..scoring import LiveScore, Scored, many_targets
from ..intake import HORIZON_SLACK_S, Intake
from ..listener import run_listener
from ..live import ClockGuard
from ..node import Node, RejectLog
from ..picture import Reports
from ..rotation import Rotation
from ..scenario import load, load_site
from .draw import TRAIL_STEP_S, Trail
from .stream import Part, Recording, open_recording, part, safe_flush, ui_points

log = logging.getLogger("zfusion")

DEFAULT_RAY_M = 20_000.0
TRUTH_GONE_FRAMES = 30  # truth frames a target may miss before its samples are forgotten (it has left)
BACKLOG_MAX = 50_000  # queued samples before the recorder starts dropping (and counting): seconds of traffic
BACKLOG_IN_MEMORY = 2_048  # ... of which in memory; the rest waits in a temporary file (ListenerInbox)
SEND_PERIOD_S = 0.2  # queued rows go out at least this often (wall clock) to a viewer ...
FILE_SEND_PERIOD_S = 2.0  # ... and to a file alone: each send is a chunk per entity, ~2 kB each on disk
SEND_ROWS_MAX = 2_000  # ... or once this many are queued (rows hold arrays: this bounds their memory)
CONTAMINATION = ("jammed", "outliers")  # sensor counters plotted under jamming/<sensor>/
COUNTER_ROW_S = 5.0  # a status counter that changes: a row at most this often (recording time)
COUNTER_IDLE_S = 60.0  # one that does not: a row this often

FUSED_NODE = "centre"


@lru_cache(maxsize=4096)  # a run draws a few hundred entities, row after row
def _p(*parts: object) -> str:
    """An entity path from unescaped parts (ids may hold '+', '.', ...)."""
    return rr.new_entity_path([str(p) for p in parts])


def _level(text: str) -> str:
    t = text.lower()
    if any(w in t for w in ("error", "fail", "crash")):
        return "ERROR"
    if any(w in t for w in ("dead", "timeout", "timed out", "gave up", "silent", "lost", "alone", "stopped",
                                "jammer on")):
        return "WARN"
    return "INFO"


class Recorder:
    """Turns samples off the wire into Rerun log calls on one recording stream.

    :meth:`offer` is the whole behaviour without Zenoh (key + bytes in, rows out), so tests
    can feed it encoded messages and read the file back.

    Args:
        rec: the recording stream (its sinks already set; see :func:`open_recording`).
        keys: the deployment's key space.
        reject: where rejected samples are counted (a fresh :class:`RejectLog` if omitted).
        scenario: the scenario, if known: sites are drawn from the start, DF sensors are
            known in advance, and data beyond its end is rejected as "future" (a site,
            live: no end; sites drawn with their first report).
        clock_guard: live: the guard that refuses stamps from the future
            (:class:`services.live.ClockGuard`; :meth:`offer` then takes ``utc``).
    """

    def __init__(self, rec: Recording, keys: KeySpace, reject: RejectLog | None = None, scenario=None,
                 clock_guard=None, fuser: str = DEFAULT_FUSER):
        self.rec = rec
        self.keys = keys
        self.reject = reject if reject is not None else RejectLog("recorder")
        self.now = 0.0  # latest time of validity seen in data: the time of undated status
        self.started = False  # whether any data has been seen (then ``now`` is on the session's time base)
        self.fused_t = -math.inf  # latest time of the fused output
        self.scenario_run = scenario is not None
        self.finished: set[str] = set()  # processes that reported done/stopped
        self.uplinked = 0  # measurements local trackers sent up on local/* (drawn as the node's)
        self.horizon = math.inf
        self.df_sensors: set[str] = set()
        self.default_ray = DEFAULT_RAY_M
        # per-entity state
        self._styled: set[str] = set()
        self._sites: dict[str, np.ndarray] = {}
        self._site_paths: dict[str, Trail] = {}
        self._scan: dict[str, tuple[float, dict[str, list[np.ndarray]]]] = {}  # by entity path
        self._bearings: deque[tuple[np.ndarray, np.ndarray]] = deque(maxlen=32)
        self._counter_rows: dict[str, tuple[float, float]] = {}  # a counter's last row: (t, value)
        self._ref_pos: np.ndarray | None = None  # latest fused (else any) estimate: scales rays
        self._truth_paths: dict[str, Trail] = {}
        self._truth_drawn = Reports()  # truth frames: a target missing from one is no longer drawn
        self._truth_kept = Reports()  # ... one missing from TRUTH_GONE_FRAMES is forgotten
        self._track_paths: dict[str, Trail] = {}
        self.delete_misses = AssociationConfig.delete_misses  # the trackers' default; the scenario may set it
        self._reports: dict[tuple[str, str], Reports] = {}  # by stream (family, key id)
        self._node_of: dict[str, str] = {}  # local/<id> -> the node its estimates name
        self.score = LiveScore()  # what the panels plot: scored against the truth as both arrive
        self._states: dict[str, str] = {}
        self._jam: dict[str, tuple] = {}
        self._jam_victims: dict[str, set[str]] = {}
        self.geo: recorder_map.MapLayer | None = None  # the map, where the session has a geodetic origin
        self.clock_guard = clock_guard  # live: no end, and the scenario (if any) is only its site
        duration = getattr(scenario, "duration", None) if clock_guard is None else None
        if duration is not None:
            self.horizon = float(duration) + HORIZON_SLACK_S
        # everything on the deployment's keys; a row's time is never before 0 nor past the end
        self._handlers = {"meas": self._on_measurement, "fused": self._on_estimate, "local": self._on_uplink,
                          "feedback": self._on_feedback, "truth": self._on_truth, "jam": self._on_jam_state,
                          "status": self._on_status}
        # what it draws; a regional fuser's frames are its system fuser's input, drawn as that fuser's tracks
        self.intake = Intake(keys, self.reject, list(self._handlers), horizon=self.horizon, earliest=0.0,
                             clock=clock_guard, only={"fused": fuser, "regional": None}, dedup=True)
        self.clock_events = self.intake.events  # what the clock guard says of the sources' clocks
        rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        if scenario is not None:
            self._from_scenario(scenario)

    # -- input ---------------------------------------------------------------------------------

    def offer(self, key: str, data: bytes, utc: float | None = None) -> Message | None:
        """One sample off the wire (``utc``: this host's clock, live). Bad input is counted
        and dropped (:class:`services.intake.Intake`); never raises."""
        sample = self.intake.offer(key, data, utc)
        if sample is None:
            return None
        family, ident, msg = sample.family, sample.ident, sample.msg
        handler = self._handlers[family]
        if msg.kind == "watermark":
            handler = self._on_watermark
        try:
            handler(family, ident, msg)
        except Exception as e:  # the schema let it through but it cannot be drawn: count, go on
            self.reject(ident or family, "unrecordable", f"{msg.kind} from {msg.src}: {type(e).__name__}: {e}")
            return None
        if msg.kind == "status" and msg.body["state"] in ("done", "stopped"):
            self.finished.add(msg.src)
        return msg

    # -- logging ---------------------------------------------------------------------------------

    def _log(self, path: str, t: float, *parts: Part) -> None:
        self.rec.row(path, t, parts)  # one row per call

    def _style(self, path: str, *parts: Part) -> None:
        """Static properties of an entity, logged once (built only then)."""
        if path not in self._styled:
            self._styled.add(path)
            self.rec.log(path, *[archetype(**components) for archetype, components in parts], static=True)

    def _advance(self, t: float) -> None:
        self.started = True
        if t > self.now:
            self.now = t

    @property
    def clock(self) -> float:
        """The recording's time: the fused output's (sources may run far ahead of it at
        ``--speed max``); without one yet, the latest time seen, unless a scenario's run,
        which has a fuser, is being recorded (-inf: not started)."""
        if math.isfinite(self.fused_t):
            return self.fused_t
        return -math.inf if self.scenario_run else self.now

    def reopen(self, rec: Recording, t: float) -> None:
        """Rotation: go on in ``rec``, whose window starts at ``t``; the sites are drawn
        again there, so the file shows them on its own."""
        self.rec = rec
        for sensor, pos in list(self._sites.items()):
            del self._sites[sensor]
            self._site(sensor, pos, t, "")

    @staticmethod
    def _trail(store: dict[str, Trail], key: str) -> Trail:
        trail = store.get(key)
        if trail is None:
            trail = store[key] = Trail()
        return trail

    def _path(self, store: dict[str, Trail], key: str, t: float, pos: np.ndarray) -> tuple[np.ndarray, bool]:
        """The path so far, and whether it gained a point: it does once ``TRAIL_STEP_S`` has
        passed since its last one, and at most ``PATH_MAX`` points are kept."""
        trail = self._trail(store, key)
        if t < trail.t + TRAIL_STEP_S - 1e-9:  # (scenario times are sums of float steps)
            return trail.points, False
        trail.t = t
        return trail.add(pos), True

    # -- scenario --------------------------------------------------------------------------------

    def _from_scenario(self, sc) -> None:
        duration = getattr(sc, "duration", None) if self.clock_guard is None else None  # a site (live): no end
        association, _ = AssociationConfig.split(sc.tracker)
        if association is not None:
            self.delete_misses = association.delete_misses
        self.df_sensors = {sid for sid, s in sc.sensors.items() if s.kind in DF_KINDS}
        self.score.many = many_targets(sc) if hasattr(sc, "targets") else None  # a site: judged from the truth seen
        self.geo = recorder_map.MapLayer.at(sc.origin, self._log)
        # The scenario's scale, from where its sensors and jammers are during the run (not its targets).
        times = np.linspace(0.0, float(duration or 0.0), 9)
        pts = [site.position(float(t)) for site in [s.site for s in sc.sensors.values() if s.site is not None]
               + [j.site for j in getattr(sc, "jammers", {}).values()] for t in (times if not site.fixed else [0.0])]
        if len(pts) > 1:
            span = max(float(np.linalg.norm(a[:2] - b[:2])) for a in pts for b in pts)
            self.default_ray = draw.clamp_ray(max(DEFAULT_RAY_M, 1.5 * span))
        if duration is not None:  # live: drawn with their first report, on the UTC timeline
            for sid, s in sc.sensors.items():
                self._site(sid, s.site.position(float(s.start)), float(s.start), s.kind)
        self.rec.send_recording_name(f"{sc.name}")

    # -- measurements ------------------------------------------------------------------------------

    def _site(self, sensor: str, pos: np.ndarray, t: float, kind: str) -> np.ndarray:
        """Draw a sensor's site the first time and whenever it has moved; returns where it is drawn."""
        pos = np.asarray(pos, dtype=float).copy()
        if sensor in self.df_sensors or (kind in KINDS and KINDS[kind].family == "df"):  # (kind: a sensor's or a measurement's)
            pos[2] = 0.0  # DF lives on the map plane
        prev = self._sites.get(sensor)
        if prev is not None and np.linalg.norm(prev - pos) <= 1.0:
            return prev
        self._sites[sensor] = pos
        path = self._trail(self._site_paths, sensor).add(pos)
        c = draw.color_of(sensor)
        parts = [part(rr.Points3D, positions=[pos], labels=[sensor], colors=[c], radii=ui_points(7.0), show_labels=[True])]
        if len(path) > 1:
            parts.append(part(rr.LineStrips3D, strips=[path], colors=[draw.dim(c)], radii=ui_points(1.5)))
        self._log(_p("world", "sites", sensor), t, *parts)
        if self.geo is not None:
            self.geo.site(_p("world", "sites", sensor), t, pos, self._site_paths[sensor], c)
        return pos

    def _ray_length(self, site: np.ndarray, u: np.ndarray, planar: bool) -> float:
        """How far to draw an angle-only report: past the latest estimate, else past where
        it crosses recent bearings from elsewhere, else the scenario's scale. Never truth."""
        if self._ref_pos is not None:
            d = self._ref_pos - site
            dist = float(np.linalg.norm(d[:2] if planar else d))
            if dist > draw.MIN_RAY_M / 2:
                return draw.clamp_ray(1.5 * dist)
        if planar:
            hits = [h for p, v in self._bearings if (h := draw.ray_hit(site, u, p, v)) is not None]
            if hits:
                return draw.clamp_ray(1.3 * float(np.median(hits)))
        return self.default_ray

    def _on_measurement(self, family: str, ident: str | None, msg: Message) -> None:
        m = to_measurement(msg)
        self._advance(m.t)
        site = self._site(m.sensor, m.site, m.t, m.kind)
        self._draw_measurement(_p("world", "meas", m.sensor), m, site, draw.color_of(m.sensor), learn=True)

    def _on_uplink(self, family: str, ident: str | None, msg: Message) -> None:
        """A local tracker's uplink: its estimate (a prediction in two-stage) and/or the
        measurement it sent up."""
        u = uplink(msg)
        if isinstance(u, (LocalReport, PredictionReport)):
            self._estimate(family, ident, u.estimate, isinstance(u, PredictionReport))
        if isinstance(u, (InitRequest, PredictionReport, MeasurementReport)):
            self._uplinked(u.measurement)
        if isinstance(u, Drop):  # the node deleted its local track: so does the picture
            self._advance(u.t)
            self._forget_local(ident or "", u.track, u.t)

    def _uplinked(self, m: Measurement) -> None:
        """A measurement a local tracker sent up (raw in two-stage, a smoothed bearing in
        KF+TR): drawn as the node's, never again as the sensor's."""
        self.uplinked += 1
        self._advance(m.t)
        site = self._sites.get(m.sensor)
        if site is None:
            site = self._site(m.sensor, m.site, m.t, m.kind)
        self._draw_measurement(_p("world", "tracks", m.sensor, "uplink"), m, site, draw.dim(draw.color_of(m.sensor),
                                                                                        0.8), learn=False)

    def _draw_measurement(self, path: str, m, site: np.ndarray, c: tuple[int, int, int], learn: bool) -> None:
        """One row: every report of this scan so far (a scan may see several targets)."""
        kind = KINDS[m.kind]
        z = dict(zip(kind.names, (float(v) for v in m.z)))
        t0, scan = self._scan.get(path, (None, None))
        if t0 != m.t or scan is None:
            scan = {"points": [], "rays": [], "arcs": []}
            self._scan[path] = (m.t, scan)
        points, rays, arcs = scan["points"], scan["rays"], scan["arcs"]
        u = None if not kind.sited else draw.unit(z["az"], z.get("el", 0.0))
        if u is None:  # a position report: the point itself
            points.append(np.asarray(m.z, dtype=float))
        elif "range" in z:
            points.append(site + z["range"] * u)
            if kind.start == SPHERE:  # no elevation: the target is anywhere on this arc
                arcs.append(draw.vertical_arc(site, z["az"], z["range"]))
        else:
            planar = kind.family == "df"
            rays.append(np.array([site, site + self._ray_length(site, u, planar) * u]))
            if planar and learn:
                self._bearings.append((site, u))
        parts = []
        if points:
            parts.append(part(rr.Points3D, positions=list(points), colors=[c], radii=ui_points(4.0)))
        if rays or arcs:
            strips = rays + arcs
            colors = [c] * len(rays) + [draw.dim(c)] * len(arcs)
            parts.append(part(rr.LineStrips3D, strips=strips, colors=colors, radii=ui_points(1.0)))
        self._log(path, m.t, *parts)
        if self.geo is not None and kind.family == "df":
            self.geo.bearings(path, m.t, rays, c)

    def _on_watermark(self, family: str, ident: str | None, msg: Message) -> None:
        self._advance(msg.t)

    # -- truth, tracks, metrics ------------------------------------------------------------------

    def _on_truth(self, family: str, ident: str | None, msg: Message) -> None:
        tgt, x = msg.body["target"], np.asarray(msg.body["x"], dtype=float)
        self._advance(msg.t)
        missed = self._truth_drawn.t  # the frame a target gone at this one is missing from: cleared there
        for gone in self._truth_drawn.report(tgt, msg.t, 1):
            self._log(_p("world", "truth", gone), missed, part(rr.Clear, is_recursive=[True]))
            if self.geo is not None:
                self.geo.clear(_p("world", "truth", gone), missed)
        for gone in self._truth_kept.report(tgt, msg.t, TRUTH_GONE_FRAMES):
            self._forget_truth(gone)
        self._plot(self.score.truth(tgt, msg.t, x))
        pos = x[:3] if x.size >= 3 else np.array([x[0], x[1], 0.0])
        parts = [part(rr.Points3D, positions=[pos], labels=[tgt], colors=[draw.TRUTH_COLOR], radii=ui_points(5.0))]
        path, grew = self._path(self._truth_paths, tgt, msg.t, pos)
        if grew:  # else the path drawn last still shows
            parts.append(part(rr.LineStrips3D, strips=[path], colors=[draw.TRUTH_COLOR], radii=ui_points(1.0)))
        self._log(_p("world", "truth", tgt), msg.t, *parts)
        if self.geo is not None:
            self.geo.truth(_p("world", "truth", tgt), msg.t, pos, self._truth_paths[tgt], grew, draw.TRUTH_COLOR)

    def _forget_truth(self, tgt: str) -> None:
        """``tgt`` has left: its truth samples, path and duplicate bookkeeping go."""
        self.score.forget(tgt)
        self._truth_paths.pop(tgt, None)
        self.intake.forget("truth", tgt)

    def _draw_estimate(self, path: str, e: Estimate, color: tuple[int, int, int], label: str) -> np.ndarray | None:
        """Point + 3σ ellipsoid / ellipse + path so far; a smoothed bearing as a ray with its
        ±3σ wedge from the node's site. Returns the drawn position (None for a bearing)."""
        layout = draw.state_layout(e.x.size)
        radius = ui_points(5.0)
        line = ui_points(1.0)
        if layout == "bearing":
            site = self._sites.get(e.node)
            if site is None:
                return None
            az, s = float(e.x[0]) % (2 * math.pi), draw.N_SIGMA * math.sqrt(max(float(e.P[0, 0]), 0.0))
            L = self._ray_length(site, draw.unit(az), True)
            strips = [[site, site + L * draw.unit(a)] for a in (az, az - s, az + s)]
            self._log(path, e.t, part(rr.LineStrips3D, strips=strips, colors=[color, draw.dim(color), draw.dim(color)],
                                      radii=line, labels=[label, "", ""]))
            return None
        if layout is None:
            return None
        pos = draw.position3(e.x)
        trail, grew = self._path(self._track_paths, path, e.t, pos)
        parts = [part(rr.Points3D, positions=[pos], labels=[label], colors=[color], radii=radius)]
        if layout == "3d":
            half, quat = draw.ellipsoid(e.P[:3, :3])
            parts.append(part(rr.Ellipsoids3D, centers=[pos], half_sizes=[half], quaternions=[quat], colors=[color],
                              line_radii=ui_points(0.75)))
            if grew:  # else the path drawn last still shows
                parts.append(part(rr.LineStrips3D, strips=[trail], colors=[draw.dim(color)], radii=line))
        else:  # the ellipse shares the component with the path: both, every row (map-plane fixes are slow)
            ring = draw.ellipse(pos, e.P[:2, :2])
            parts.append(part(rr.LineStrips3D, strips=[ring, trail], colors=[color, draw.dim(color)], radii=line))
        self._log(path, e.t, *parts)
        if self.geo is not None:
            self.geo.estimate(path, e.t, e, color, self._track_paths[path], grew)
        return pos

    def _on_estimate(self, family: str, ident: str | None, msg: Message) -> None:
        self._estimate(family, ident, to_estimate(msg), False)

    def _estimate(self, family: str, ident: str | None, e: Estimate, prediction: bool) -> None:
        self._advance(e.t)
        fused = e.node == FUSED_NODE
        if fused and family == "fused":
            self.fused_t = max(self.fused_t, e.t)
        if family == "local" and ident:
            self._node_of[ident] = e.node  # drops on feedback/<ident> name this node's tracks
        track = _p("world", "tracks", e.node, e.track)
        self._reported((family, ident or ""), track, e.t)
        color = draw.CENTRE_COLOR if fused else draw.color_of(e.node)
        if prediction:
            self._draw_estimate(_p("world", "tracks", e.node, e.track, "prediction"), e, draw.dim(color),
                                f"{e.node} {e.track} (pred.)")
            return
        label = f"{e.method} {e.track}" if fused else f"{e.node} {e.track}"
        pos = self._draw_estimate(track, e, color, label)
        if e.existence is not None:  # a JIPDA track's probability that its target exists
            self._log(_p("metrics", "existence", e.node, e.track), e.t, part(rr.Scalars, scalars=[e.existence]))
        if pos is not None and (fused or self._ref_pos is None):
            self._ref_pos = pos
        self._plot(self.score.estimate(e, fused))

    def _on_feedback(self, family: str, ident: str | None, msg: Message) -> None:
        d = downlink(ident or "", msg)
        if isinstance(d, DropTrack):  # the node deletes its local track: so does the picture
            self._advance(d.t)
            self._forget_local(ident or "", d.track, d.t)
            return
        e = d.estimate
        self._advance(e.t)
        path = _p("world", "feedback", ident or e.node, e.track)
        self._reported((family, ident or ""), path, e.t)
        self._draw_estimate(path, e, draw.FEEDBACK_COLOR, f"{e.track} to {ident}" + (" (init)" if isinstance(d, Init) else ""))

    def _forget_local(self, ident: str, track: str, t: float) -> None:
        """The local track ``track`` of the node on ``local/<ident>`` is gone: clear it."""
        node = self._node_of.get(ident)
        reports = self._reports.get(("local", ident))
        path = _p("world", "tracks", node, track) if node is not None else None
        if reports is not None and path is not None and reports.forget(path):
            self._clear(path, t)

    def _reported(self, stream: tuple[str, str], track: str, t: float) -> None:
        """A report of a track's entity on its stream: clears the tracks the stream has stopped reporting."""
        reports = self._reports.get(stream)
        if reports is None:
            reports = self._reports[stream] = Reports()
        for gone in reports.report(track, t, self.delete_misses):
            self._clear(gone, t)

    def _clear(self, track: str, t: float) -> None:
        """The track is gone: from ``t`` on it is not drawn (nor its prediction), and its paths are forgotten."""
        self._log(track, t, part(rr.Clear, is_recursive=[True]))
        if self.geo is not None:
            self.geo.clear(track, t)
        for path in [p for p in self._track_paths if p == track or p.startswith(track + "/")]:
            del self._track_paths[path]

    def finish(self) -> None:
        """The recording ends: the frames still open are scored."""
        self._plot(self.score.finish())

    @property
    def unscored(self) -> int:
        return self.score.unscored

    def _plot(self, points: list[Scored]) -> None:
        """Draw what the scoring handed back: a series per metric and estimates, a NEES or
        NIS with its 95 % χ² interval."""
        for pt in points:
            base = ("metrics", "picture", pt.prefix[0], pt.metric) if pt.metric in ("missed", "false") \
                else ("metrics", pt.metric, *pt.prefix)
            name = "/".join(pt.prefix) if pt.metric not in ("missed", "false") else f"{pt.prefix[0]} {pt.metric}"
            self._style(_p(*base), part(rr.SeriesLines, names=[name]))
            self._log(_p(*base), pt.t, part(rr.Scalars, scalars=[pt.value]))
            if pt.bounds is not None:
                for end, level, bound in (("lo", "2.5%", pt.bounds[0]), ("hi", "97.5%", pt.bounds[1])):
                    self._style(_p(*base, end), part(rr.SeriesLines, colors=[draw.BOUND_COLOR], widths=[1.0],
                                                     names=[f"{name} χ²({pt.dof}) {level}"]))
                    self._log(_p(*base, end), pt.t, part(rr.Scalars, scalars=[bound]))

    # -- jamming and status ------------------------------------------------------------------------

    def _on_jam_state(self, family: str, ident: str | None, msg: Message) -> None:
        b, jid, t = msg.body, msg.src, msg.t
        self._advance(t)
        on = bool(b["on"])
        pos = np.asarray(b["pos"], dtype=float)
        affects = [s for s in b["affects"]]
        color = draw.JAM_ON_COLOR if on else draw.JAM_OFF_COLOR
        parts = [part(rr.Points3D, positions=[pos], labels=[f"{jid} ({b['mode']}, {'ON' if on else 'off'})"],
                      colors=[color], radii=ui_points(8.0), show_labels=[True])]
        victims = [self._sites[s] for s in affects if s in self._sites] if on else []
        # always log the strips component, so "no one jammed" clears the previous lines
        parts.append(part(rr.LineStrips3D, strips=[[pos, v] for v in victims], colors=[draw.JAM_ON_COLOR],
                          radii=ui_points(0.75)))
        self._log(_p("world", "jam", jid), t, *parts)
        self._style(_p("jamming", jid, "on"), part(rr.SeriesLines, colors=[draw.JAM_ON_COLOR], names=[f"{jid} on"]))
        self._log(_p("jamming", jid, "on"), t, part(rr.Scalars, scalars=[1.0 if on else 0.0]))
        known = self._jam_victims.setdefault(jid, set())
        known.update(affects)
        known.update(self._sites)
        for s in sorted(known):
            self._log(_p("jamming", jid, "affects", s), t, part(rr.Scalars, scalars=[1.0 if (on and s in affects) else 0.0]))
        state = (on, b["mode"], b["law"], b["power"], tuple(affects))
        if self._jam.get(jid) != state:
            self._jam[jid] = state
            text = (f"jammer {jid} on: {b['mode']}, {b['law']} outliers, power {b['power']:g}; "
                    f"jams {', '.join(affects) if affects else 'no sensor'}") if on else f"jammer {jid} off"
            self._log(_p("status", jid, "events"), t, part(rr.TextLog, text=[text], level=["WARN" if on else "INFO"]))

    def _on_status(self, family: str, ident: str | None, msg: Message) -> None:
        b, src = msg.body, msg.src
        # Processes stamp status with their scenario time when they have one; else it is "now".
        t = msg.t if msg.t > 0 else self.now
        t = min(t, self.horizon)
        events = _p("status", src, "events")
        if self._states.get(src) != b["state"]:
            self._states[src] = b["state"]
            self._log(events, t, part(rr.TextLog, text=[f"{b['role']} {src}: {b['state']}"],
                                      level=["WARN" if b["state"] == "stopped" else "INFO"]))
        for ev in b["events"]:
            self._log(events, t, part(rr.TextLog, text=[f"{src}: {ev}"], level=[_level(ev)]))
        final = b["state"] in ("done", "stopped")
        for name, v in b["counters"].items():
            path = _p("jamming", src, name) if name in CONTAMINATION else _p("status", src, "counters", name)
            if final or self._counter_due(path, t, float(v)):
                self._log(path, t, part(rr.Scalars, scalars=[float(v)]))

    def _counter_due(self, path: str, t: float, v: float) -> bool:
        """Whether a counter's row is worth a row: its first, a change at least
        ``COUNTER_ROW_S`` after its last row, or the same value ``COUNTER_IDLE_S`` on (the
        plot's line reaches the present). A process says its status once a second or
        more often; a plot needs far fewer points (docs/viewing.md, "Recording size")."""
        last = self._counter_rows.get(path)
        if last is not None:
            t_last, v_last = last
            if t - t_last < (COUNTER_ROW_S if v != v_last else COUNTER_IDLE_S):
                return False
        self._counter_rows[path] = (t, v)
        return True


# -- the process ----------------------------------------------------------------------------------


class RecordingSink:
    """The recorder as a listener's sink (:func:`services.listener.run_listener`): a
    :class:`Recorder` on a recording file (rotated every ``rotate_s`` of session time),
    whose rows go out (and whose file is flushed) at least every ``SEND_PERIOD_S`` with a
    viewer, ``FILE_SEND_PERIOD_S`` to a file alone (each send writes a chunk per entity:
    fewer, larger chunks make a smaller file), so a killed recorder loses little. Done once every process of ``expect``
    has reported done."""

    def __init__(self, node: Node, rrd_path: str, expect: list[str], sc, live, app: str, spawn: bool,
                 rotate_s: float | None, fuser: str = DEFAULT_FUSER):
        df = sc is not None and bool(sc.sensors) and all(s.kind in DF_KINDS for s in sc.sensors.values())
        self.rotation = Rotation(rrd_path, rotate_s) if rotate_s else None
        self.opener = functools.partial(open_recording, app=app, spawn=spawn, df=df,
                                        many=hasattr(sc, "targets") and many_targets(sc), geo=sc is not None,
                                        live=live is not None,
                                        map_zoom=recorder_map.zoom_of(sc, DEFAULT_RAY_M) if sc is not None else None)
        self.rec, viewer = self.opener(str(self.rotation.first()) if self.rotation else rrd_path)
        self.send_period = SEND_PERIOD_S if viewer else FILE_SEND_PERIOD_S
        guard = ClockGuard(live.max_skew) if live is not None else None
        self.recorder = Recorder(self.rec, node.keys, node.reject, sc, clock_guard=guard, fuser=fuser)
        self.events = self.recorder.clock_events
        self.expect = set(expect)
        self._sent = self._flushed = time.monotonic()

    def offer(self, key: str, data: bytes, utc: float | None) -> Message | None:
        msg = self.recorder.offer(key, data, utc)
        at = self.rotation.due(self.recorder.clock) if self.rotation and self.recorder.started else None
        if at is not None:
            new, _ = self.opener(str(self.rotation.next()), recording_id=self.rec.get_recording_id())
            self.rec.hand_over(new, at)
            self.rec = new
            self.recorder.reopen(new, at)
        if self.rec.queued >= SEND_ROWS_MAX:
            self._send()
        return msg

    def _send(self) -> None:
        self.rec.send_rows()
        self._sent = time.monotonic()

    def tick(self, final: bool = False) -> None:
        if final:
            self.recorder.finish()
            safe_flush(self.rec, 10.0)
            return
        if time.monotonic() - self._sent >= self.send_period:
            self._send()
        if time.monotonic() - self._flushed >= self.send_period:
            safe_flush(self.rec, 0.0)  # keep the file current: a killed recorder loses little
            self._flushed = time.monotonic()

    def done(self) -> bool:
        return bool(self.expect) and self.expect <= self.recorder.finished

    def now(self) -> float:
        return self.recorder.now

    def counters(self) -> dict[str, float]:
        return {"uplinked": self.recorder.uplinked, "unscored": self.recorder.unscored}

    def close(self) -> None:
        safe_flush(self.rec, 10.0)
        self.rec.disconnect()  # writes the file's footer; gives an unreachable viewer at most a few seconds


def run(process_id: str, keys: KeySpace, zopts, rrd_path: str, expect: list[str], app: str = "zfusion", *,
        spawn: bool = False, scenario: str | None = None, seed: int | None = None,
        rotate_s: float | None = None, live=None, duration: float | None = None, fuser: str = DEFAULT_FUSER) -> int:
    """``live`` (:class:`services.live.LiveOptions`): a live session; ``scenario`` is then
    a site (or a scenario taken as its site), optional. ``fuser``: the fuser whose tracks
    it records (everything else on the deployment's keys is recorded whoever sends it)."""
    sc = None
    if scenario is not None:
        sc = load(scenario, seed, duration) if live is None else load_site(scenario)
    # The file is opened once SIGTERM/SIGINT are handled, so a stop at any time leaves a whole file.
    return run_listener(process_id, "recorder", keys, zopts,
                        lambda node: RecordingSink(node, rrd_path, expect, sc, live, app, spawn, rotate_s, fuser),
                        subscribe=keys.all(), fuser=fuser, live=live is not None, backlog=BACKLOG_MAX,
                        in_memory=BACKLOG_IN_MEMORY, counted="recorded")
