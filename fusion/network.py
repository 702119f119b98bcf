r"""The distributed topologies as pure state machines: local nodes and a centre.

A *local node* runs beside one sensor; the *centre* fuses what the nodes send up. The
same classes run inside the tracker and fuser processes (which only move their inputs
and outputs over Zenoh) and inside :class:`NetworkMethod`, the in-process composition
the Monte Carlo evaluation uses — so a distributed run and the in-process evaluation
compute the very same thing.

Messages: an :class:`Uplink` (node → centre) carries a local estimate, a raw
measurement (an initialisation request, or DDHNV's measurement for the centre's
update), or both; a :class:`Downlink` (centre → node) an estimate the node takes as its
next prior (``init``, or PHHNV/DDHNV feedback).

=========  ===========  ==============================  ================================
method     topology     local node                      centre
=========  ===========  ==============================  ================================
HNV        distributed  EKF update per measurement      fuse the reports of a scan
PHHNV      feedback     update from the fed-back prior  fuse, feed the result back
DDHNV      two-stage    predict from the fed-back       fuse the predictions, update with
                        prior; send it + measurement    each measurement, fuse, feed back
KF+TR,     distributed  smooth each bearing             Torrieri on the latest smoothed
MKF+TR                                                  bearing of every station
=========  ===========  ==============================  ================================

Tracks are initialised at the centre from the nodes' first measurements; a fed-back
node waits for the centre's *horizon* so the result never depends on message timing
(or runs on alone, timing-dependent, when told so). With ``association`` the nodes and
centre track many targets (:class:`MultiTrackNode`, :class:`MultiTrackCentre`,
:class:`MultiStationNode`, :class:`StationCentre`). The protocol, its ordering argument
and the many-target rules in full: docs/network.md.
"""

from __future__ import annotations

import dataclasses
import math
from collections import deque
from dataclasses import dataclass

import numpy as np

from .angles import wrap_pi
from .association import CONFIRMED, DELETED, TrackIds, TrackLogic, gate_threshold, gnn, mahalanobis2, track_distance2
from .df.methods import DFConfig, SmootherTorrieriMethod, make_station_smoother
from .df.models import bearing_of
from .df.multi import MultiEmitterMethod
from .init3d import initial_state
from .grouping import TimeGrouper
from .guards import epoch_nis, gap_too_long, positive_definite
from .measurement.kinds import kinds_of, model_of
from .mtt import AssociationConfig, Initiator, scores_hit
from .patent import KINDS_3D, LocalTracker, TrackerConfig
from .topology import Scheme
from .track_fusion import TrackFuser
from .types import Estimate, Measurement



@dataclass(frozen=True)
class Uplink:
    """One item a local node sends to the centre (module docstring)."""

    t: float
    node: str
    seq: int
    estimate: Estimate | None = None
    measurement: Measurement | None = None
    drop: bool = False  # many targets: the node deleted its local track ``estimate.track``

    @property
    def sensor(self) -> str:  # the scan grouper's notion of "source"
        return self.node

    @property
    def order_key(self) -> tuple:
        return (self.t, self.node, self.seq)

    @property
    def init_request(self) -> bool:
        return self.estimate is None and self.measurement is not None

    @property
    def report(self) -> bool:
        """A local track's estimate (not a request, not a deletion notice)."""
        return self.estimate is not None and not self.drop


@dataclass(frozen=True)
class Downlink:
    """A prior sent down to one node; ``estimate.extra`` may carry the centre's own
    update with that node's measurement (``sensor_x``, ``sensor_P``; DDHNV). With many
    targets, ``init`` starts the local track ``estimate.track`` (named by the centre),
    and ``drop`` tells the node to delete its local track ``estimate.track``."""

    node: str
    estimate: Estimate
    init: bool
    drop: bool = False


def _before(t: float) -> float:
    """The largest time strictly before ``t``: "complete up to, not including, t"."""
    return math.nextafter(t, -math.inf)


# Local nodes ---------------------------------------------------------------------------
class LocalNode:
    """Base: a queue of the sensor's measurements, released by :meth:`step` when the
    node may process them; subclasses say when (:meth:`_blocked`) and how (:meth:`_process`)."""

    def __init__(self, node: str, pair_tol: float):
        self.node = node
        self.pair_tol = float(pair_tol)
        self.pending: deque[Measurement] = deque()
        self.horizon = -math.inf
        self._seq = 0

    kinds: frozenset = frozenset()

    def offer(self, m: Measurement) -> None:
        """The sensor's next measurement, in time order."""
        if m.kind not in self.kinds:
            raise ValueError(f"{self.node}: cannot use a {m.kind!r} measurement (takes {', '.join(sorted(self.kinds))})")
        if self.pending and m.order_key <= self.pending[-1].order_key:
            raise ValueError(f"{self.node}: measurement {m.order_key} out of order")
        self.pending.append(m)

    def receive(self, d: Downlink) -> None:
        raise ValueError(f"{self.node}: this node takes no downlink")

    def set_horizon(self, w: float) -> None:
        self.horizon = max(self.horizon, float(w))

    def set_watermark(self, w: float) -> None:
        """The sensor's watermark (nothing at or before ``w`` will come); a one-target
        node needs none (each measurement is its own scan)."""

    @property
    def waiting_for(self) -> str | None:
        """``"init"``/``"feedback"`` if the next pending measurement waits on the centre."""
        return self._blocked(self.pending[0]) if self.pending else None

    def step(self, alone: bool = False) -> list[Uplink]:
        """Process every pending measurement that may be processed now; ``alone`` ignores
        the centre (downlink lost)."""
        out: list[Uplink] = []
        while self.pending:
            if not alone and self._blocked(self.pending[0]):
                break
            out += self._process(self.pending.popleft(), alone)
        return out

    def upstream_watermark(self, sensor_watermark: float) -> float:
        """What this node may promise the centre: the sensor's watermark, but nothing at
        or after a measurement it still holds."""
        if self.pending:
            return min(sensor_watermark, _before(self.pending[0].t))
        return sensor_watermark

    def centre_restarted(self) -> bool:
        """A new centre knows nothing of this node: drop the tracks it gave this node and
        start again as a node that has just joined (the pending measurements kept).
        Returns whether there was anything to drop."""
        self.horizon = -math.inf
        return False

    def _uplink(self, t: float, estimate=None, measurement=None, drop: bool = False) -> Uplink:
        self._seq += 1
        return Uplink(float(t), self.node, self._seq, estimate, measurement, drop)

    def _blocked(self, m: Measurement) -> str | None:
        return None

    def _process(self, m: Measurement, alone: bool) -> list[Uplink]:
        raise NotImplementedError


class TrackNode(LocalNode):
    """The local tracker of HNV, PHHNV and DDHNV (their :class:`~fusion.topology.Scheme`)
    around a :class:`~fusion.patent.LocalTracker`."""

    kinds = KINDS_3D

    def __init__(self, sensor: str, config: TrackerConfig, method: str, scheme: Scheme, track: str = "T1"):
        super().__init__(sensor, config.pair_tol)
        self.config = config
        self.scheme = scheme
        motion = config.motion_model()
        self.tracker = LocalTracker(sensor, motion, method, track, config.new_filter(motion))
        self._requested = False

    def centre_restarted(self) -> bool:
        super().centre_restarted()
        self._start_afresh()
        return True

    def _start_afresh(self) -> None:
        """Drop the track: the next measurement asks the centre for an initial state."""
        old = self.tracker
        self.tracker = LocalTracker(self.node, old.motion, old.method, old.track, old.new_filter)
        self._requested = False

    def receive(self, d: Downlink) -> None:
        e = d.estimate
        if d.drop:  # the centre dropped the track (fusion.guards), unless this node has already
            if self.tracker.initialised:
                self._start_afresh()
            return
        if not d.init and not self.tracker.initialised:
            return  # feedback for the track this node dropped (fusion.guards); it waits for an init
        if d.init or self.scheme.feeds_back:
            if self.tracker.initialised and e.t < self.tracker.t:
                return  # older than where this node already is (it ran alone meanwhile)
            if d.init:
                self.tracker.initialise(e.x, e.P, e.t)
            else:
                self.tracker.accept_prior(e.x, e.P, e.t, e.extra)
            self._requested = False

    def _blocked(self, m):
        if not self.tracker.initialised:
            return "init" if self._requested else None
        if self.scheme.waits_for_horizon and m.t - self.horizon > self.pair_tol:
            return "feedback"
        return None

    def _process(self, m, alone):
        # A track more than max_gap_s old, or left not positive definite, starts afresh
        # (fusion.guards); the centre, as old, starts afresh from the nodes' requests.
        if self.tracker.initialised and gap_too_long(m.t - self.tracker.t, self.config.max_gap_s):
            self._start_afresh()
        if not self.tracker.initialised:
            if alone:  # no centre: start from this sensor's own measurement
                x, P = initial_state([m], self.tracker.motion.n_x, self.config.priors())
                self.tracker.initialise(x, P, m.t)
                return []
            self._requested = True
            return [self._uplink(m.t, measurement=m)]
        if self.scheme.predicts:
            return [self._uplink(m.t, self.tracker.predict(m.t), m)]
        e = self.tracker.update(m)
        if not all(map(positive_definite, _covariances(e))):
            self._start_afresh()
            return self._process(m, alone)
        return [self._uplink(m.t, e)]


class StationNode(LocalNode):
    """A DF station of KF+TR / MKF+TR: smooths its bearings, sends each smoothed
    bearing (a ``bearing`` measurement with the smoothed std) up."""

    kinds = kinds_of("df")

    def __init__(self, sensor: str, config: dict | None, cross_fed: bool):
        c = DFConfig.from_dict(config)
        super().__init__(sensor, c.pair_tol)
        self.smoother = make_station_smoother(c, cross_fed)

    def _process(self, m, alone):
        return [self._uplink(m.t, measurement=self.smoother.update(m))]


# Centres -----------------------------------------------------------------------------
class Centre:
    """Streaming interface of a centre: uplinks in ``(t, node, seq)`` order in,
    estimates out (``process``/``advance``/``finish``, like every method), downlinks
    collected for :meth:`take_downlinks`, and the feedback :attr:`horizon`."""

    def __init__(self):
        self._down: list[Downlink] = []

    def take_downlinks(self) -> list[Downlink]:
        out, self._down = self._down, []
        return out

    def _send(self, node: str, e: Estimate, init: bool, drop: bool = False) -> None:
        self._down.append(Downlink(node, e, init, drop))

    @property
    def horizon(self) -> float:
        return -math.inf


class GroupedCentre(Centre):
    """A centre that processes its uplinks in groups (one target's scans, many targets'
    frames) closed by a grouper; its horizon stops before the group it still holds.
    Subclasses set ``_grouper`` and implement :meth:`_group`."""

    _watermark = -math.inf

    def process(self, u: Uplink) -> list[Estimate]:
        return self._run(self._grouper.push(u))

    def advance(self, t: float) -> list[Estimate]:
        self._watermark = max(self._watermark, float(t))
        return self._run(self._grouper.advance(t))

    def finish(self) -> list[Estimate]:
        self._watermark = math.inf
        return self._run(self._grouper.finish())

    @property
    def horizon(self) -> float:
        held = self._grouper.held_since()
        return self._watermark if held is None else min(self._watermark, _before(held))

    def _run(self, groups) -> list[Estimate]:
        out: list[Estimate] = []
        for group in groups:
            out += self._group(group)
        return out

    def _group(self, group: list[Uplink]) -> list[Estimate]:
        raise NotImplementedError


class TrackCentre(GroupedCentre):
    """The centre of HNV / PHHNV / DDHNV: scans of uplinks, a
    :class:`~fusion.track_fusion.TrackFuser`, and the downlinks."""

    def __init__(self, name: str, config: TrackerConfig, scheme: Scheme, track: str = "T1"):
        super().__init__()
        self.name = name
        self.config = config
        self.scheme = scheme
        self.track = track
        self.motion = config.motion_model()
        self._new_filter = config.new_filter(self.motion)
        self.fuser = TrackFuser(config.fusion_rule, self.motion, config.ci_criterion, name, track)
        self.nodes: set[str] = set()
        self.restarts = 0  # tracks started afresh (fusion.guards)
        self._grouper = TimeGrouper(config.pair_tol, one_per_sensor=True)

    # -- scans ----------------------------------------------------------------------------
    def _group(self, scan: list[Uplink]) -> list[Estimate]:
        t = scan[0].t
        if self.fuser.initialised and gap_too_long(t - self.fuser.t, self.config.max_gap_s):
            self._start_afresh(t)
        requests = [u for u in scan if u.init_request]
        # A report of a node that is no member was sent before it heard that the track was dropped.
        reports = [u for u in scan if not u.init_request and u.node in self.nodes]
        out = self._fuse(t, reports) if reports else []
        if not requests:
            return out
        if not self.fuser.initialised:
            x, P = initial_state([u.measurement for u in requests], self.motion.n_x, self.config.priors())
            self.fuser.initialise(x, P, t)
            e = Estimate(t, x, P, self.name, "centre", self.track)
            out.append(e)
        else:  # late joiners start from the latest fused state
            e = Estimate(self.fuser.t, self.fuser.x, self.fuser.P, self.name, "centre", self.track)
        for u in requests:
            self._join(u.node, e)
        return out

    def _start_afresh(self, t: float) -> None:
        """Drop the fused track (:mod:`fusion.guards`): a new fuser with no member nodes;
        each node is told to drop its track (a ``drop`` downlink, which carries no state)
        and asks for an initial state with its next measurement."""
        n = self.motion.n_x
        for node in sorted(self.nodes):
            self._send(node, Estimate(t, np.zeros(n), np.eye(n), self.name, "centre", self.track), False, drop=True)
        self.fuser = TrackFuser(self.config.fusion_rule, self.motion, self.config.ci_criterion, self.name, self.track)
        self.nodes = set()
        self.restarts += 1

    def _join(self, node: str, e: Estimate) -> None:
        self.nodes.add(node)
        self.fuser.add_node(node)
        self._send(node, e, init=True)

    def _fuse(self, t: float, reports: list[Uplink]) -> list[Estimate]:
        """The scan's fused estimate; a scan the rules cannot fuse (a covariance that is
        not positive definite), or whose fused covariance is not, drops the track."""
        try:
            centre, per_node = fuse_reports(self.fuser, self.scheme, t, reports, self.track, self._new_filter)
        except ValueError:  # (np.linalg.LinAlgError is one)
            centre = None
        if centre is None or not all(map(positive_definite, _covariances(centre, self.fuser.model_extra()))):
            self._start_afresh(t)
            return []
        if self.scheme.feeds_back:
            for node in sorted(self.nodes):
                self._send(node, _feedback(centre, per_node.get(node), self.track, self.fuser.model_extra()), False)
        return [centre]


def _covariances(e: Estimate, models: dict | None = None) -> list[np.ndarray]:
    """The covariances an estimate (and an IMM's per-model terms) carries: its ``P`` and
    each model's ``imm_Ps`` block on the coordinates the model has (a model of fewer
    states, CV among CA ones, has none on the others)."""
    out = [e.P]
    for extra in (e.extra, models or {}):
        if "imm_Ps" in extra:
            Ps = np.asarray(extra["imm_Ps"], dtype=float)
            n = Ps.shape[1]
            for P in (Ps[k:k + n] for k in range(0, Ps.shape[0], n)):
                has = np.diagonal(P) != 0.0
                out.append(P[np.ix_(has, has)])
    return out


def fuse_reports(fuser: TrackFuser, scheme: Scheme, t: float, reports: list[Uplink], track: str, new_filter):
    """One fusion at the centre of the local reports of one track (all at ``t``):
    ``(centre estimate, DDHNV's updates per node)``. A scheme whose nodes predict: stage 1 fuses the
    local predictions, the centre updates that with each node's measurement (a filter
    from ``new_filter``, started from stage 1: for an IMM centre fusing per model, from
    its per-model estimates and mode probabilities), stage 2 fuses those updates (module
    docstring)."""
    local = [_at(u.estimate, t) for u in reports]
    per_node: dict[str, Estimate] = {}
    if scheme.predicts:
        stage1 = fuser.fuse(t, local)
        updates = []
        for u in reports:  # the centre's updates of the fused prediction
            c = LocalTracker(u.measurement.sensor, fuser.motion, fuser.method, track, new_filter)
            c.accept_prior(stage1.x, stage1.P, t, fuser.model_extra())
            per_node[u.node] = c.update(u.measurement, t)
            updates.append(per_node[u.node])
        fused = fuser.fuse(t, updates)
        nis_from = updates
    else:
        fused = fuser.fuse(t, local)
        nis_from = [e for e in local if e.nis is not None]
    nis, dof = epoch_nis((e.nis, e.nis_dof) for e in nis_from)
    extra = {"omega": fused.extra["omega"]} if "omega" in fused.extra else {}  # CI weights
    return Estimate(t, fused.x, fused.P, fuser.method, "centre", track, nis, dof, extra), per_node


def _feedback(centre: Estimate, update: Estimate | None, track: str, models: dict | None = None) -> Estimate:
    """The fused estimate sent down as a node's next prior (with the centre's update of
    that node's measurement, DDHNV; with an IMM centre's per-model estimates, ``models``)."""
    extra = {"sensor_x": update.x, "sensor_P": update.P} if update else {}
    extra.update(models or {})
    return Estimate(centre.t, centre.x, centre.P, centre.method, "centre", track, extra=extra)


def _at(e: Estimate, t: float) -> Estimate:
    """A local estimate re-stamped to the scan time (offsets within pair_tol neglected)."""
    return e if e.t == t else Estimate(t, e.x, e.P, e.method, e.node, e.track, e.nis, e.nis_dof, e.extra)


class StationCentre(Centre):
    """The centre of KF+TR / MKF+TR: Torrieri on the latest smoothed bearings
    (:class:`fusion.df.methods.SmootherTorrieriMethod` with the smoothing done upstream);
    with ``association`` in the table, on each emitter's: the smoothed bearings are
    associated into emitters as raw ones are (:class:`fusion.df.multi.MultiEmitterMethod`)."""

    def __init__(self, name: str, config: dict | None):
        super().__init__()
        self.name = name
        association, rest = AssociationConfig.split(config)

        def make() -> SmootherTorrieriMethod:
            return SmootherTorrieriMethod(name == "MKF+TR", rest, smoothed_upstream=True)

        self.method = make() if association is None else MultiEmitterMethod(name, make, association)

    def process(self, u: Uplink) -> list[Estimate]:
        return self.method.process(u.measurement)

    def advance(self, t: float) -> list[Estimate]:
        # t = inf is the end, which finish() closes (the DF methods take finite watermarks)
        return self.method.advance(t) if math.isfinite(t) else []

    def finish(self) -> list[Estimate]:
        return self.method.finish()


# Many targets --------------------------------------------------------------------------
class FramedNode(LocalNode):
    """Base of the many-target nodes: the sensor's reports are grouped into frames
    (:class:`fusion.grouping.TimeGrouper`, closed by the sensor's watermark), and a frame,
    not a measurement, is the unit :meth:`_process` takes."""

    def __init__(self, node: str, pair_tol: float):
        super().__init__(node, pair_tol)
        self._frames = TimeGrouper(pair_tol)

    def offer(self, m: Measurement) -> None:
        if m.kind not in self.kinds:
            raise ValueError(f"{self.node}: cannot use a {m.kind!r} measurement (takes {', '.join(sorted(self.kinds))})")
        self.pending.extend(self._frames.push(m))

    def set_watermark(self, w: float) -> None:
        self.pending.extend(self._frames.advance(w))

    def step(self, alone: bool = False) -> list[Uplink]:
        if alone:  # the stream has ended or the centre is gone: no frame will complete otherwise
            self.pending.extend(self._frames.finish())
        return super().step(alone)

    def upstream_watermark(self, sensor_watermark: float) -> float:
        held = [self.pending[0][0].t] if self.pending else []
        if self._frames.held_since() is not None:
            held.append(self._frames.held_since())
        return min([sensor_watermark, *(_before(t) for t in held)])


class MultiTrackNode(FramedNode):
    """A local node tracking many targets on its own sensor's plots (module docstring,
    "Many targets"): frames of plots, χ²/GNN association to its local tracks, one
    uplink per updated track (``track`` = its local id), one initialisation request
    per plot no local track took, and one deletion notice (``drop``) per local track
    it deletes on its own."""

    kinds = KINDS_3D

    def __init__(self, sensor: str, config: TrackerConfig, method: str, scheme: Scheme, association):
        super().__init__(sensor, config.pair_tol)
        self.config = config
        self.scheme = scheme
        self.method = method
        self.association = association
        self.motion = config.motion_model()
        self._new_filter = config.new_filter(self.motion)
        self.tracks: dict[str, LocalTracker] = {}  # local id -> tracker, in creation order
        self.misses: dict[str, int] = {}
        # The centre names the local tracks it starts (the init's ``track``); a track the
        # node starts alone is ``A<n>``, a name the centre never gives, so it is never
        # taken for one of the centre's.
        self._alone_ids = TrackIds("A")
        # Without feedback (HNV) a local track drifts along what its sensor does not
        # measure; it rejoins from the fused track past its own limit. A fed-back track
        # is re-anchored every frame (and DDHNV's holds only predictions).
        self._max_pos_std = association.max_pos_std if scheme.anchored else association.local_pos_std_limit

    def centre_restarted(self) -> bool:
        super().centre_restarted()
        self.tracks.clear()
        self.misses.clear()
        return True

    def receive(self, d: Downlink) -> None:
        e = d.estimate
        if d.drop:
            self.tracks.pop(e.track, None)
            self.misses.pop(e.track, None)
        elif d.init:  # a new local track on one of the centre's tracks, named by the centre
            self._start(e.track, e.x, e.P, e.t)
        elif self.scheme.feeds_back and e.track in self.tracks:
            tr = self.tracks[e.track]
            if e.t >= tr.t:  # not older than where the track already is
                tr.accept_prior(e.x, e.P, e.t, e.extra)

    def _blocked(self, frame):
        # Every scheme waits for the centre's answers to the earlier frames (inits, drops,
        # feedback): the local tracks then do not depend on message timing.
        return "centre" if frame[0].t - self.horizon > self.pair_tol else None

    def _process(self, frame: list[Measurement], alone: bool) -> list[Uplink]:
        t = frame[0].t
        ids = list(self.tracks)
        model = model_of(frame[0], self.motion.n_x)
        pairs = []
        if ids:
            Z = np.array([m.z for m in frame])
            d2 = np.array([mahalanobis2(model, *self.tracks[i].predicted(t), Z) for i in ids])
            pairs = gnn(d2, gate_threshold(model.n_z, self.association.gate_prob))
        out: list[Uplink] = []
        taken = {}
        for r, c in pairs:
            lid, m = ids[r], frame[c]
            taken[c] = lid
            tr = self.tracks[lid]
            out.append(self._uplink(m.t, tr.predict(m.t), m) if self.scheme.predicts else self._uplink(m.t, tr.update(m)))
        hit = set(taken.values())
        for lid in ids:
            self.misses[lid] = 0 if lid in hit else self.misses[lid] + 1
            tr = self.tracks[lid]
            if self.misses[lid] >= self.association.delete_misses or \
                    math.sqrt(float(np.trace(tr.P[:3, :3]))) > self._max_pos_std:
                del self.tracks[lid], self.misses[lid]
                # Tell the centre, which would otherwise keep it as its fused track's member.
                out.append(self._uplink(t, Estimate(t, tr.x, tr.P, self.method, self.node, lid), drop=True))
        for c, m in enumerate(frame):
            if c in taken:
                continue
            if alone:  # no centre: a local track from this plot alone
                self._start(self._alone_ids.next(), *initial_state([m], self.motion.n_x, self.config.priors()), m.t)
            else:
                out.append(self._uplink(m.t, measurement=m))
        return out

    def _start(self, lid: str, x: np.ndarray, P: np.ndarray, t: float) -> None:
        self.tracks[lid] = LocalTracker(self.node, self.motion, self.method, lid, self._new_filter)
        self.tracks[lid].initialise(x, P, t)
        self.misses[lid] = 0


class MultiStationNode(FramedNode):
    """A DF station of KF+TR / MKF+TR with many emitters (module docstring, "Many
    targets"): the bearings of a scan are plots of *bearing tracks*, one smoother each
    (:func:`fusion.df.methods.make_station_smoother`), taken by χ²(1) gate on the
    smoother's prediction and global nearest neighbour. A bearing no track takes starts
    one; a track without a bearing for ``delete_misses`` scans is deleted. Every track's
    smoothed bearing goes up as a bearing of the station: nothing says which emitter,
    the centre associates them as it does raw bearings."""

    kinds = kinds_of("df")

    def __init__(self, sensor: str, config: dict | None, cross_fed: bool, association):
        c = DFConfig.from_dict(config)
        super().__init__(sensor, c.pair_tol)
        self.config, self.cross_fed, self.association = c, cross_fed, association
        self.tracks: list = []  # bearing smoothers, in birth order
        self.misses: list[int] = []

    def _process(self, frame: list[Measurement], alone: bool) -> list[Uplink]:
        betas = np.array([bearing_of(m)[1] for m in frame])
        sigmas = np.array([self.config.sigma_of(m) for m in frame])
        taken: dict[int, int] = {}  # bearing -> track
        if self.tracks:
            x = np.array([tr.x[0] for tr in self.tracks])
            var = np.array([tr.P[0, 0] + tr.q for tr in self.tracks])  # the smoother's predicted variance
            r = wrap_pi(betas[None, :] - x[:, None])
            taken = {c: k for k, c in gnn(r * r / (var[:, None] + sigmas[None, :] ** 2),
                                          gate_threshold(1, self.association.gate_prob))}
        old = len(self.tracks)
        self.misses = [0 if k in taken.values() else n + 1 for k, n in enumerate(self.misses)]
        out = []
        for c, m in enumerate(frame):
            if c not in taken:
                taken[c] = len(self.tracks)
                self.tracks.append(make_station_smoother(self.config, self.cross_fed))
                self.misses.append(0)
            out.append(self._uplink(m.t, measurement=self.tracks[taken[c]].update(m)))
        keep = [k for k in range(len(self.tracks)) if k >= old or self.misses[k] < self.association.delete_misses]
        self.tracks = [self.tracks[k] for k in keep]
        self.misses = [self.misses[k] for k in keep]
        return out


class _Fused:
    """One track of the centre's picture: its fuser, its life, and its local tracks."""

    def __init__(self, key: str, fuser: TrackFuser, logic, last: Estimate):
        self.key, self.fuser, self.logic, self.last = key, fuser, logic, last
        self.id: str | None = None  # published id, given at confirmation
        self.members: dict[str, str] = {}  # node -> its local id on this track
        self.joins: set[str] = set()  # nodes to send an init after this frame


class MultiTrackCentre(GroupedCentre):
    """The centre of HNV / PHHNV / DDHNV with many targets (module docstring, "Many
    targets"): frames of uplinks; track-to-track association of every node's local
    tracks with the fused tracks; one :class:`~fusion.track_fusion.TrackFuser` per
    fused track; initiation from the initialisation requests; M-of-N management."""

    def __init__(self, name: str, config: TrackerConfig, scheme: Scheme, association):
        super().__init__()
        self.name = name
        self.config = config
        self.scheme = scheme
        self.association = association
        self.rule = association.rule()
        self.motion = config.motion_model()
        self._new_filter = config.new_filter(self.motion)
        self.tracks: list[_Fused] = []  # confirmed in id order, then tentative in birth order
        self._initiator = Initiator(self.motion.n_x, config.priors(), association.gate_prob)
        self._grouper = TimeGrouper(config.pair_tol)
        self._ids = TrackIds()
        self._births = 0
        self._duplicates = association.duplicate_watch()
        self._mapped: dict[tuple[str, str], _Fused] = {}  # (node, local id) -> fused track
        self._local_ids: dict[str, TrackIds] = {}  # node -> the names of the local tracks it is sent
        self._kinds: dict[str, str] = {}  # node -> its sensor's measurement kind

    # -- one frame -------------------------------------------------------------------------
    def _group(self, frame: list[Uplink]) -> list[Estimate]:
        t = frame[0].t
        predicted = {f.key: f.fuser.predicted(t) for f in self.tracks}
        reports: dict[str, list[Uplink]] = {f.key: [] for f in self.tracks}
        for u in frame:
            if u.drop:  # the node deleted a local track: it is no member any more
                self._forget(u.node, u.estimate.track)
        for node, ups in _by_node(u for u in frame if u.report).items():
            for f, u in self._associate_reports(node, ups, t, predicted):
                reports[f.key].append(u)
        seen: dict[str, set[str]] = {f.key: {u.node for u in reports[f.key] if _hit(u)} for f in self.tracks}
        left = []
        for u in frame:
            if u.measurement is not None:
                self._kinds[u.node] = u.measurement.kind
        for node, ups in _by_node(u for u in frame if u.init_request).items():
            rest, gated = self._associate_requests(node, [u.measurement for u in ups], t, predicted)
            left += rest
            for f in gated:
                seen[f.key].add(node)
        evidence = min(2, len({u.node for u in frame}))
        for f in self.tracks:
            if reports[f.key]:
                f.last, per_node = fuse_reports(f.fuser, self.scheme, t, reports[f.key], f.key, self._new_filter)
                if self.scheme.feeds_back:
                    for node, lid in sorted(f.members.items()):
                        self._send(node, _feedback(f.last, per_node.get(node), lid, f.fuser.model_extra()), False)
            else:
                x, P = predicted[f.key]
                f.last = Estimate(t, x, P, self.name, "centre", f.key)
            f.logic.record(self._hit(seen[f.key], f.logic.status == CONFIRMED, evidence), f.fuser.P[:3, :3])
        live = {f.key: f for f in self.tracks if f.logic.status != DELETED}  # in priority order
        for key in self._duplicates.duplicates([(k, f.last.x, f.last.P) for k, f in live.items()]):
            live[key].logic.status = DELETED
        for first, more, x, P in self._initiator.groups(sorted(left, key=lambda m: m.order_key)):
            self._births += 1
            fuser = TrackFuser(self.config.fusion_rule, self.motion, self.config.ci_criterion, self.name, "")
            fuser.initialise(x, P, t)
            f = _Fused(f"F{self._births}", fuser, TrackLogic(self.rule), Estimate(t, x, P, self.name, "centre"))
            f.joins = {m.sensor for m in (*first, *more)}
            self.tracks.append(f)
        for f in self.tracks:
            if f.logic.status == DELETED:
                for node, lid in sorted(f.members.items()):
                    self._drop(node, lid, f.last)
                continue
            if f.logic.status == CONFIRMED and f.id is None:
                f.id = self._ids.next()
            for node in sorted(f.joins):  # from the latest fused state (late joiners too)
                self._join(node, f)
            f.joins = set()
        self.tracks = [f for f in self.tracks if f.logic.status != DELETED]
        confirmed = sorted((f for f in self.tracks if f.id is not None), key=lambda f: int(f.id[1:]))
        self.tracks = confirmed + [f for f in self.tracks if f.id is None]
        return [dataclasses.replace(f.last, track=f.id) for f in confirmed]

    def _hit(self, nodes: set[str], confirmed: bool, evidence: int) -> bool:
        """:func:`fusion.mtt.scores_hit` on the kinds of the nodes' sensors. Here the
        ghost along an angle sensor's ray is a local angle track alone holding a fused
        track (fed back to it under PHHNV/DDHNV) whose range drifts away from the radar
        plots, which then start a second track on the target."""
        return scores_hit([self._kinds.get(n, "azel") for n in nodes], confirmed, evidence)

    def _associate_reports(self, node: str, ups: list[Uplink], t: float, predicted) -> list[tuple[_Fused, Uplink]]:
        """Track-to-track association of one node's reports with the fused tracks. Every
        local track the centre knows was started by its init, so it is mapped from
        birth; it keeps its fused track while the pair stays in the χ² gate
        (``d²/G ≤ 1``). A mapped track leaving its gate is dropped and the node is sent
        the fused track again; a local id the centre does not know (its fused track was
        deleted, or the node started it alone) is dropped."""
        out = []
        for u in ups:
            lid = u.estimate.track
            f = self._mapped.get((node, lid))
            if f is None:
                self._drop(node, lid, u.estimate)
                continue
            e = _at(u.estimate, t)
            d2, rank = track_distance2(e.x, e.P, *predicted[f.key], f.fuser.cross_covariance(t, e), _COMPARED)
            if not rank or d2 <= gate_threshold(rank, self.association.gate_prob):
                out.append((f, u))
            else:  # left its gate: the node starts again from the fused track
                self._drop(node, lid, u.estimate)
                f.joins.add(node)
        return out

    def _join(self, node: str, f: _Fused) -> None:
        """Send ``node`` a new local track on ``f`` from the latest fused state, named
        here (``L<n>``, never reused for that node: not after a drop, nor by a
        restarted node), so it is ``f``'s member from now on; it replaces the node's
        local track on ``f`` before, if any (one per node per fused track)."""
        if node in f.members:
            self._drop(node, f.members[node], f.last)
        lid = self._local_ids.setdefault(node, TrackIds("L")).next()
        f.members[node] = lid
        self._mapped[(node, lid)] = f
        f.fuser.add_node(node)
        self._send(node, Estimate(f.fuser.t, f.fuser.x, f.fuser.P, self.name, "centre", lid), True)

    def _forget(self, node: str, lid: str) -> None:
        """The node's local track ``lid`` is no member of its fused track any more."""
        f = self._mapped.pop((node, lid), None)
        if f is not None and f.members.get(node) == lid:
            del f.members[node]

    def _drop(self, node: str, lid: str, e: Estimate) -> None:
        """Forget the node's local track ``lid`` and tell the node to delete it (the
        downlink carries ``e``, whose state does not matter)."""
        self._forget(node, lid)
        self._send(node, Estimate(e.t, e.x, e.P, self.name, "centre", lid), False, drop=True)

    def _associate_requests(self, node: str, plots: list[Measurement], t: float, predicted):
        """χ²/GNN of one node's request plots with the fused tracks: a plot in a track's
        gate makes the node join it (the request initialises, as in the one-target
        handshake, and is not used again). A track the node is a member of takes part:
        a plot its local track did not take says that track may be lost, and the new
        one replaces it. Returns the plots left for initiation and the tracks joined."""
        free = self.tracks
        if not free:
            return plots, []
        model = model_of(plots[0], self.motion.n_x)
        Z = np.array([m.z for m in plots])
        d2 = np.array([mahalanobis2(model, *predicted[f.key], Z) for f in free])
        pairs = gnn(d2, gate_threshold(model.n_z, self.association.gate_prob))
        for r, _ in pairs:
            free[r].joins.add(node)
        used = {c for _, c in pairs}
        return [m for c, m in enumerate(plots) if c not in used], [free[r] for r, _ in pairs]


_COMPARED = (0, 1, 2, 3, 4, 5)  # position, velocity: what track-to-track association compares


def _hit(u: Uplink) -> bool:
    """A report that used a measurement (an update, or DDHNV's prediction + measurement)."""
    return u.measurement is not None or u.estimate.nis is not None


def _by_node(ups) -> dict[str, list[Uplink]]:
    out: dict[str, list[Uplink]] = {}
    for u in ups:
        out.setdefault(u.node, []).append(u)
    return out


# The split of a method into nodes and a centre ---------------------------------------
@dataclass(frozen=True)
class Split:
    """How a distributed method is split into a node per sensor and a centre; its
    topology is the method's registry record's (:mod:`fusion.methods`)."""

    name: str
    node: object  # (sensor, config) -> LocalNode
    centre: object  # (config) -> Centre


def track_split(name: str, scheme: Scheme) -> Split:
    """HNV / PHHNV / DDHNV (their :class:`~fusion.topology.Scheme`): one target, or many
    with ``association`` in the table."""

    def node(sensor, config):
        association, rest = AssociationConfig.split(config)
        if association is None:
            return TrackNode(sensor, TrackerConfig.from_dict(rest), name, scheme)
        return MultiTrackNode(sensor, TrackerConfig.from_dict(rest), name, scheme, association)

    def centre(config):
        association, rest = AssociationConfig.split(config)
        if association is None:
            return TrackCentre(name, TrackerConfig.from_dict(rest), scheme)
        return MultiTrackCentre(name, TrackerConfig.from_dict(rest), scheme, association)

    return Split(name, node, centre)


def station_split(name: str, cross_fed: bool) -> Split:
    """KF+TR (``cross_fed=False``) / MKF+TR: one emitter, or many with ``association``
    in the table."""

    def node(sensor, config):
        association, rest = AssociationConfig.split(config)
        if association is None:
            return StationNode(sensor, rest, cross_fed)
        return MultiStationNode(sensor, rest, cross_fed, association)

    return Split(name, node, lambda c: StationCentre(name, c))


# In-process composition -----------------------------------------------------------------
class NetworkMethod:
    """A split method run in one process: the nodes and the centre wired back to back,
    with exactly the message semantics of the distributed run.

    Implements the streaming method interface; emits every local report (``node`` =
    sensor) as it goes up, and the centre's estimates (``node = "centre"``).
    """

    def __init__(self, split: Split, config: dict | None):
        self.name = split.name
        self._split = split
        self._config = dict(config or {})
        self.centre = self._split.centre(self._config)
        self.nodes: dict[str, LocalNode] = {}
        self._out: list[Estimate] = []

    @property
    def config(self) -> dict:
        return dict(self._config)

    def _node(self, sensor: str) -> LocalNode:
        node = self.nodes.get(sensor)
        if node is None:
            node = self.nodes[sensor] = self._split.node(sensor, self._config)
        return node

    def _pump(self) -> bool:
        """Deliver downlinks and let the nodes send what they can, until quiet; True if
        anything moved."""
        moved = False
        while True:
            downs = self.centre.take_downlinks()
            for d in downs:
                self.nodes[d.node].receive(d)
            sent = False
            for node in self.nodes.values():
                node.set_horizon(self.centre.horizon)
                for u in node.step():
                    sent = True
                    if u.report:
                        self._out.append(u.estimate)
                    self._out += self.centre.process(u)
            if not downs and not sent:
                return moved
            moved = True

    def _settle(self, t: float) -> list[Estimate]:
        """Every node is complete up to ``t`` (except what it holds, as its watermark
        would say): advance the centre and pump until nothing moves."""
        for node in self.nodes.values():
            node.set_watermark(t)
        while True:
            self._out += self.centre.advance(min([t, *(n.upstream_watermark(t) for n in self.nodes.values())]))
            if not self._pump():
                out, self._out = self._out, []
                return out

    def process(self, m: Measurement) -> list[Estimate]:
        out = self._settle(_before(m.t))
        self._node(m.sensor).offer(m)
        return out + self._settle(_before(m.t))

    def advance(self, t: float) -> list[Estimate]:
        return self._settle(float(t))

    def finish(self) -> list[Estimate]:
        out = self._settle(math.inf)
        for node in self.nodes.values():  # nothing can answer a node that still waits now
            for u in node.step(alone=True):
                if u.report:
                    out.append(u.estimate)
                out += self.centre.process(u)
        return out + self.centre.finish()
