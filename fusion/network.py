r"""The distributed topologies as pure state machines: local nodes and a centre.

A *local node* runs beside one sensor; the *centre* fuses what the nodes send up. The
same classes run inside the tracker and fuser processes (which only move their inputs
and outputs over Zenoh) and inside :class:`NetworkMethod`, the in-process composition
the Monte Carlo evaluation uses — so a distributed run and the in-process evaluation
compute the very same thing.

Messages: one frozen class each (:mod:`fusion.links`). Up: an initialisation request,
a local report (an update; DDHNV's prediction with its measurement), a DF station's
smoothed bearing, a deletion notice; down: an init, feedback, a deletion order.

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

(KF+TR and MKF+TR's nodes and centre: :mod:`fusion.df.stations`.)

Tracks are initialised at the centre from the nodes' first measurements; a fed-back
node waits for the centre's *horizon* so the result never depends on message timing
(or runs on alone, timing-dependent, when told so). With ``association`` the nodes and
centre track many targets (:class:`MultiTrackNode`, :class:`MultiTrackCentre`; the
centre a configuration of :class:`fusion.tracking.manager.MultiTargetTracker`). The
protocol, its ordering argument and the many-target rules in full: docs/network.md.
"""

from __future__ import annotations

import dataclasses
import math
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from .tracking.config import AssociationConfig
from .tracking.hypotheses import Hypotheses, PlotHypothesiser, gate_threshold, track_distance2
from .tracking.initiators import Initiator
from .tracking.jipda import ExistenceLogic
from .tracking.manager import Frame, MultiTargetTracker, Taken
from .tracking.table import DELETED, Track, TrackIds, TrackTable, scores_hit
from .init3d import initial_state
from .grouping import TimeGrouper
from .guards import epoch_nis, gap_too_long, positive_definite
from .links import (Downlink, Drop, DropTrack, Feedback, Gaussian, Init, InitRequest, LocalReport, ModelStates,
                    ModelTerms, PredictionReport, Report, Uplink)
from .patent import KINDS_3D, LocalTracker, TrackerConfig
from .topology import Scheme
from .track_fusion import TrackFuser
from .types import Estimate, Measurement



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
        # Measurements (frames) dropped as older than a prior the centre sent: it fused past
        # them while this node was cut off or stopped, so what the node would send on them
        # is late there, and its track cannot be predicted back to them.
        self.stale = 0

    kinds: frozenset = frozenset()

    def offer(self, m: Measurement) -> None:
        """The sensor's next measurement, in time order."""
        if m.kind not in self.kinds:
            raise ValueError(f"{self.node}: cannot use a {m.kind!r} measurement (takes {', '.join(sorted(self.kinds))})")
        if self.pending and m.order_key <= self.pending[-1].order_key:
            raise ValueError(f"{self.node}: measurement {m.order_key} out of order")
        self.pending.append(m)

    def receive(self, d: Downlink) -> None:
        raise ValueError(f"{self.node}: this node takes no {type(d).__name__}")

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

    @property
    def ran_alone(self) -> bool:
        """Whether this node holds a track it started alone that no centre has answered
        (its request lost, e.g. late at a restarted centre): the centre refuses its
        reports, so it must start again (:meth:`centre_restarted`) once the centre is
        heard again."""
        return False

    def _next_seq(self) -> int:
        """The number of the node's next message up."""
        self._seq += 1
        return self._seq

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
        self._joined = False  # the centre has answered this node's track (an init)
        self._asked_at: float | None = None  # the time of its latest request

    def centre_restarted(self) -> bool:
        super().centre_restarted()
        self._start_afresh()
        return True

    def _start_afresh(self) -> None:
        """Drop the track: the next measurement asks the centre for an initial state."""
        old = self.tracker
        self.tracker = LocalTracker(self.node, old.motion, old.method, old.track, old.new_filter)
        self._requested = self._joined = False
        self._asked_at = None

    @property
    def ran_alone(self) -> bool:
        # unanswered: the centre's horizon has passed its request, or it never asked
        return self.tracker.initialised and not self._joined and (self._asked_at is None or self._unanswered)

    def receive(self, d: Downlink) -> None:
        if isinstance(d, DropTrack):  # the centre dropped the track (fusion.guards), unless this node has already
            if self.tracker.initialised:
                self._start_afresh()
            return
        if isinstance(d, Feedback) and not (self.scheme.feeds_back and self.tracker.initialised):
            return  # no feedback scheme, or feedback for the track this node dropped (fusion.guards): it waits for an init
        e = d.estimate
        self._joined |= isinstance(d, Init)
        if self.tracker.initialised and e.t < self.tracker.t:
            return  # older than where this node already is (it ran alone meanwhile)
        if isinstance(d, Init):
            self.tracker.initialise(e.x, e.P, e.t)
        else:
            self.tracker.accept_prior(e.x, e.P, e.t, d.models)
        self._requested = False

    @property
    def _unanswered(self) -> bool:
        """Its request was passed over: the centre's horizon is past it and no init came
        (the centre sends a scan's inits before the horizon that passes the scan), so the
        request was refused (late at a restarted centre) or lost, and nothing will answer it."""
        return self._asked_at is not None and self.horizon >= self._asked_at

    def _blocked(self, m):
        if not self.tracker.initialised:  # a request passed over is made again with this measurement
            return "init" if self._requested and not self._unanswered else None
        if self.scheme.waits_for_horizon and m.t - self.horizon > self.pair_tol:
            return "feedback"
        return None

    def _process(self, m, alone):
        if self.tracker.initialised and m.t < self.tracker.t:  # (attribute ``stale``)
            self.stale += 1
            return []
        # A track more than max_gap_s old, or left not positive definite, starts afresh
        # (fusion.guards); the centre, as old, starts afresh from the nodes' requests.
        if self.tracker.initialised and gap_too_long(m.t - self.tracker.t, self.config.max_gap_s):
            self._start_afresh()
        if not self.tracker.initialised:
            if alone:  # no centre: start from this sensor's own measurement
                x, P = initial_state([m], self.tracker.motion.n_x, self.config.priors())
                self.tracker.initialise(x, P, m.t)
                return []
            self._requested, self._asked_at = True, m.t
            return [InitRequest(m.t, self.node, self._next_seq(), m)]
        if self.scheme.predicts:
            return [self.tracker.predict(m, self._next_seq())]
        r = self.tracker.update(m, self._next_seq())
        if not all(map(positive_definite, _covariances(r.estimate, r.models))):
            self._start_afresh()
            return self._process(m, alone)
        return [r]


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

    def _send(self, d: Downlink) -> None:
        self._down.append(d)

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
        requests = [u for u in scan if isinstance(u, InitRequest)]
        # A report of a node that is no member was sent before it heard that the track was dropped.
        reports = [u for u in scan if not isinstance(u, InitRequest) and u.node in self.nodes]
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
        each node is told to drop its track (:class:`~fusion.links.DropTrack`) and asks
        for an initial state with its next measurement."""
        for node in sorted(self.nodes):
            self._send(DropTrack(node, t, self.track))
        self.fuser = TrackFuser(self.config.fusion_rule, self.motion, self.config.ci_criterion, self.name, self.track)
        self.nodes = set()
        self.restarts += 1

    def _join(self, node: str, e: Estimate) -> None:
        self.nodes.add(node)
        self.fuser.add_node(node)
        self._send(Init(node, e))

    def _fuse(self, t: float, reports: list[Report]) -> list[Estimate]:
        """The scan's fused estimate; a scan the rules cannot fuse (a covariance that is
        not positive definite), or whose fused covariance is not, drops the track."""
        try:
            centre, per_node = fuse_reports(self.fuser, self.scheme, t, reports, self.track, self._new_filter)
        except ValueError:  # (np.linalg.LinAlgError is one)
            centre = None
        if centre is None or not all(map(positive_definite, _covariances(centre, self.fuser.model_states()))):
            self._start_afresh(t)
            return []
        if self.scheme.feeds_back:
            for node in sorted(self.nodes):
                self._send(_feedback(node, centre, per_node.get(node), self.track, self.fuser.model_states()))
        return [centre]


def _covariances(e: Estimate, models: ModelTerms | ModelStates | None = None) -> list[np.ndarray]:
    """The covariances an estimate (and a filter's per-model terms) carries: its ``P`` and
    each model's block of ``models.Ps`` on the coordinates the model has (a model of fewer
    states, CV among CA ones, has none on the others)."""
    out = [e.P]
    for P in () if models is None else np.asarray(models.Ps, dtype=float):
        has = np.diagonal(P) != 0.0
        out.append(P[np.ix_(has, has)])
    return out


def fuse_reports(fuser: TrackFuser, scheme: Scheme, t: float, reports: list[Report], track: str, new_filter):
    """One fusion at the centre of the local reports of one track (all at ``t``):
    ``(centre estimate, DDHNV's updates per node)``. A scheme whose nodes predict: stage 1 fuses the
    local predictions, the centre updates that with each node's measurement (a filter
    from ``new_filter``, started from stage 1: for an IMM centre fusing per model, from
    its per-model estimates and mode probabilities), stage 2 fuses those updates (module
    docstring)."""
    local = [_at(u, t) for u in reports]
    per_node: dict[str, LocalReport] = {}
    if scheme.predicts:
        stage1 = fuser.fuse(t, local)
        updates = []
        for u in reports:  # the centre's updates of the fused prediction
            c = LocalTracker(u.node, fuser.motion, fuser.method, track, new_filter)
            c.accept_prior(stage1.x, stage1.P, t, fuser.model_states())
            per_node[u.node] = c.update(u.measurement, u.seq, t)
            updates.append(per_node[u.node])
        fused = fuser.fuse(t, updates)
        nis_from = [u.estimate for u in updates]
    else:
        fused = fuser.fuse(t, local)
        nis_from = [u.estimate for u in local if u.estimate.nis is not None]
    nis, dof = epoch_nis((e.nis, e.nis_dof) for e in nis_from)
    extra = {"omega": fused.extra["omega"]} if "omega" in fused.extra else {}  # CI weights
    return Estimate(t, fused.x, fused.P, fuser.method, "centre", track, nis, dof, extra), per_node


def _feedback(node: str, centre: Estimate, update: LocalReport | None, track: str,
              models: ModelStates | None) -> Feedback:
    """The fused estimate sent down as the next prior of ``node``'s local track ``track``
    (with the centre's update of that node's measurement, DDHNV; with an IMM centre's
    per-model states, ``models``)."""
    return Feedback(node, Estimate(centre.t, centre.x, centre.P, centre.method, "centre", track),
                    None if update is None else Gaussian(update.estimate.x, update.estimate.P), models)


def _at(u: Report, t: float) -> Report:
    """A local report re-stamped to the scan time (offsets within pair_tol neglected)."""
    if u.t == t:
        return u
    return dataclasses.replace(u, t=t, estimate=dataclasses.replace(u.estimate, t=t))


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
        self._hypothesiser = PlotHypothesiser(self.motion.n_x, association.gate_prob, sequential=False)
        # JIPDA (weights, existence) where the node updates its own tracks; DDHNV's nodes
        # send one plot per track for the centre's update, which weights do not give.
        self._associator = association.associator(weighted=not scheme.predicts)
        self.tracks: dict[str, LocalTracker] = {}  # local id -> tracker, in creation order
        self.misses: dict[str, int] = {}
        self.existence: dict[str, ExistenceLogic] = {}  # local id -> its existence (JIPDA)
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
        self.existence.clear()
        return True

    def receive(self, d: Downlink) -> None:
        if isinstance(d, DropTrack):
            self.tracks.pop(d.track, None)
            self.misses.pop(d.track, None)
            self.existence.pop(d.track, None)
            return
        e = d.estimate
        if isinstance(d, Init):  # a new local track on one of the centre's tracks, named by the centre
            self._start(e.track, e.x, e.P, e.t)
        elif self.scheme.feeds_back and e.track in self.tracks:
            tr = self.tracks[e.track]
            if e.t >= tr.t:  # not older than where the track already is
                tr.accept_prior(e.x, e.P, e.t, d.models)

    def _blocked(self, frame):
        # Every scheme waits for the centre's answers to the earlier frames (inits, drops,
        # feedback): the local tracks then do not depend on message timing.
        return "centre" if frame[0].t - self.horizon > self.pair_tol else None

    def _process(self, frame: list[Measurement], alone: bool) -> list[Uplink]:
        t = frame[0].t
        if any(tr.t > t for tr in self.tracks.values()):  # (attribute ``stale``)
            self.stale += 1
            return []
        out: list[Uplink] = []
        for lid in [i for i, tr in self.tracks.items() if gap_too_long(t - tr.t, self.config.max_gap_s)]:
            out.append(self._delete(lid, t))  # too old to predict (fusion.guards): the frame starts afresh
        ids = list(self.tracks)
        for lid in ids:
            if lid in self.existence:
                self.existence[lid].survive(t)
        existence = np.array([self.existence[i].existence for i in ids]) if self.existence else None
        hyp = self._hypothesiser.hypotheses([self.tracks[i].predicted(t) for i in ids], frame, [True] * len(ids),
                                            existence)
        association = self._associator.associate(hyp)
        if association.existence is not None:
            for r, e in enumerate(association.existence):
                self.existence[ids[r]].existence = float(e)
        hit = set()
        for r, cols, beta, miss in association.per_row():
            lid, tr = ids[r], self.tracks[ids[r]]
            hit.add(lid)
            if association.existence is not None:  # JIPDA: the weighted update with the frame's plots
                out.append(tr.update_weighted(hyp.model, np.array([frame[c].z for c in cols]), beta, miss, t,
                                              self._next_seq(), self.existence[lid].existence))
                continue
            m = frame[cols[0]]
            out.append(tr.predict(m, self._next_seq()) if self.scheme.predicts else tr.update(m, self._next_seq()))
        taken = association.used
        for lid in ids:
            self.misses[lid] = 0 if lid in hit else self.misses[lid] + 1
            tr = self.tracks[lid]
            if lid in self.existence:
                gone = self.existence[lid].record(lid in hit, tr.P[:3, :3]) == DELETED
            else:
                gone = self.misses[lid] >= self.association.delete_misses or \
                    math.sqrt(float(np.trace(tr.P[:3, :3]))) > self._max_pos_std
            if gone:
                out.append(self._delete(lid, t))
        for c, m in enumerate(frame):
            if c in taken:
                continue
            if alone:  # no centre: a local track from this plot alone
                self._start(self._alone_ids.next(), *initial_state([m], self.motion.n_x, self.config.priors()), m.t,
                            confirmed=False)
            else:
                out.append(InitRequest(m.t, self.node, self._next_seq(), m))
        return out

    def _delete(self, lid: str, t: float) -> Drop:
        """Delete a local track on the node's own account; the notice tells the centre,
        which would otherwise keep it as its fused track's member."""
        del self.tracks[lid], self.misses[lid]
        self.existence.pop(lid, None)
        return Drop(t, self.node, self._next_seq(), lid)

    def _start(self, lid: str, x: np.ndarray, P: np.ndarray, t: float, confirmed: bool = True) -> None:
        """A local track; with JIPDA its existence starts at ``existence_confirm`` on the
        centre's (confirmed) track, at ``existence_birth`` on a plot alone."""
        self.tracks[lid] = LocalTracker(self.node, self.motion, self.method, lid, self._new_filter)
        self.tracks[lid].initialise(x, P, t)
        self.misses[lid] = 0
        if self.association.weighted:
            rule = self.association.existence_rule()
            self.existence[lid] = ExistenceLogic(rule, self._max_pos_std, existence=rule.existence_confirm
                                                 if confirmed else rule.existence_birth, t=t)


class _Fused(Track):
    """One track of the centre's picture: its fuser (``filter``), its life, and its local tracks."""

    __slots__ = ("members", "joins")

    def __init__(self, fuser: TrackFuser, last: Estimate):
        super().__init__(fuser, last)
        self.members: dict[str, str] = {}  # node -> its local id on this track
        self.joins: set[str] = set()  # nodes to send an init after this frame

    @property
    def fuser(self) -> TrackFuser:
        return self.filter

    @property
    def key(self) -> str:
        """The centre's own name of the track, from birth (``F<n>``)."""
        return f"F{self.birth}"


class MultiTrackCentre(GroupedCentre):
    """The centre of HNV / PHHNV / DDHNV with many targets (module docstring, "Many
    targets"): frames of uplinks through a :class:`~fusion.tracking.manager.MultiTargetTracker`
    whose plots are the nodes' local tracks (track-to-track costs) and their
    initialisation requests, one :class:`~fusion.track_fusion.TrackFuser` per fused
    track, initiation from the requests no fused track took, M-of-N management.

    The tracker's parts are this centre's methods: :meth:`predict`, :meth:`scans`,
    :meth:`hypothesise`, :meth:`condition`, :meth:`unclaimed` (hypothesiser),
    :meth:`update`, :meth:`position_cov`, :meth:`start` (updater), :meth:`review`."""

    def __init__(self, name: str, config: TrackerConfig, scheme: Scheme, association):
        super().__init__()
        self.name = name
        self.config = config
        self.scheme = scheme
        self.association = association
        self.motion = config.motion_model()
        self._new_filter = config.new_filter(self.motion)
        self._grouper = TimeGrouper(config.pair_tol)
        self._plots = PlotHypothesiser(self.motion.n_x, association.gate_prob, sequential=False)
        self._duplicates = association.duplicate_watch()
        self.tracker = MultiTargetTracker(self, association.associator(confirmed_first=False),
                                          Initiator(self.motion.n_x, config.priors(), association.gate_prob),
                                          self, association.table(), self)
        self._mapped: dict[tuple[str, str], _Fused] = {}  # (node, local id) -> fused track
        self._local_ids: dict[str, TrackIds] = {}  # node -> the names of the local tracks it is sent
        self._kinds: dict[str, str] = {}  # node -> its sensor's measurement kind
        self._node_of: dict[str, str] = {}  # sensor -> the node that sent its requests
        self._t = -math.inf  # this frame's time
        self._predicted: dict[int, tuple[np.ndarray, np.ndarray]] = {}  # birth -> prediction, this frame

    @property
    def table(self) -> TrackTable:
        return self.tracker.table

    @property
    def tracks(self) -> list[_Fused]:
        """The fused tracks, in priority order."""
        return self.tracker.tracks

    # -- one frame -------------------------------------------------------------------------
    def _group(self, frame: list[Uplink]) -> list[Estimate]:
        for u in frame:
            if isinstance(u, Drop):  # the node deleted a local track: it is no member any more
                self._forget(u.node, u.track)
            elif isinstance(u, (InitRequest, PredictionReport)):
                self._kinds[u.node] = u.measurement.kind
                self._node_of[u.measurement.sensor] = u.node
        return [dataclasses.replace(f.last, track=f.id) for f in self.tracker.frame(frame)]

    # -- hypothesiser ----------------------------------------------------------------------
    def predict(self, tracks: list[_Fused], frame: Frame) -> list[tuple[np.ndarray, np.ndarray]]:
        """Every fused track predicted to the frame's time."""
        states = self._plots.predict(tracks, frame)
        self._t = frame.t
        self._predicted = {f.birth: s for f, s in zip(tracks, states)}
        return states

    @staticmethod
    def scans(frame: Frame) -> list[list[Uplink]]:
        """Each node's local-track reports, then each node's initialisation requests."""
        return [*_by_node(u for u in frame.plots if isinstance(u, (LocalReport, PredictionReport))).values(),
                *_by_node(u for u in frame.plots if isinstance(u, InitRequest)).values()]

    def hypothesise(self, states, tracks: list[_Fused], scan: list[Uplink]) -> Hypotheses:
        """Requests: their plots against the fused tracks (χ²). Reports: each local
        track against the fused track it is a member of, and no other — every local
        track the centre knows was started by its init, so it is mapped from birth; it
        keeps its fused track while the pair stays in the track-to-track χ² gate (of
        the rank of their difference's covariance)."""
        if isinstance(scan[0], InitRequest):
            return self._plots.hypothesise(states, tracks, [u.measurement for u in scan])
        t = self._t
        row = {f.birth: r for r, f in enumerate(tracks)}
        d2 = np.full((len(tracks), len(scan)), np.inf)
        gate = np.ones(len(tracks))  # rank 0 (identical tracks): d² = 0, inside a gate of 1
        for c, u in enumerate(scan):
            f = self._mapped.get((u.node, u.track))
            if f is None or f.birth not in row:
                continue
            r = row[f.birth]
            e = _at(u, t)
            d2[r, c], rank = track_distance2(e.estimate.x, e.estimate.P, *states[r], f.fuser.cross_covariance(t, e),
                                             _COMPARED)
            if rank:
                gate[r] = gate_threshold(rank, self.association.gate_prob)
        return Hypotheses(scan, range(len(tracks)), d2, gate, np.array([f.confirmed for f in tracks], dtype=bool))

    @staticmethod
    def condition(states, hyp: Hypotheses, association) -> None:
        """No sequential gating at the centre: every node is gated at the predictions."""

    def unclaimed(self, hyp: Hypotheses, columns) -> list[Measurement]:
        """Requests no fused track took: left for initiation. Reports no fused track
        took: a local id the centre does not know (its fused track was deleted, or the
        node started it alone) is dropped; a mapped local track that left its gate is
        dropped and its node is sent the fused track again."""
        if isinstance(hyp.plots[0], Measurement):  # the requests' plots
            return [hyp.plots[c] for c in columns]
        for c in columns:
            u = hyp.plots[c]
            f = self._mapped.get((u.node, u.track))
            self._drop(u.node, u.track, u.t)
            if f is not None:
                f.joins.add(u.node)
        return []

    # -- updater ---------------------------------------------------------------------------
    def update(self, f: _Fused, taken: list[Taken], frame: Frame) -> bool:
        """Fuse the fused track's reports (feeding the result back), or predict it. The
        nodes whose requests it took join it after the frame. Scores a hit by
        :meth:`_hit` on the nodes that measured it (reports that used a measurement,
        requests)."""
        t = frame.t
        ups = [u for tk in taken for u in tk.plots]
        reports = [u for u in ups if isinstance(u, (LocalReport, PredictionReport))]
        requests = [u for u in ups if isinstance(u, InitRequest)]
        f.joins |= {u.node for u in requests}
        if reports:
            f.last, per_node = fuse_reports(f.fuser, self.scheme, t, reports, f.key, self._new_filter)
            if self.scheme.feeds_back:
                for node, lid in sorted(f.members.items()):
                    self._send(_feedback(node, f.last, per_node.get(node), lid, f.fuser.model_states()))
        else:
            x, P = self._predicted[f.birth]
            f.last = Estimate(t, x, P, self.name, "centre", f.key)
        seen = {u.node for u in reports if _hit(u)} | {u.node for u in requests}
        return self._hit(seen, f.confirmed, min(2, frame.sensors))

    @staticmethod
    def position_cov(f: _Fused) -> np.ndarray:
        return f.fuser.P[:3, :3]

    def start(self, group, frame: Frame) -> _Fused:
        """A fused track from :meth:`Initiator.groups`' ``(first, more, x, P)``; the
        nodes of its plots are invited at once."""
        first, more, x, P = group
        fuser = TrackFuser(self.config.fusion_rule, self.motion, self.config.ci_criterion, self.name, "")
        fuser.initialise(x, P, frame.t)
        f = _Fused(fuser, Estimate(frame.t, x, P, self.name, "centre"))
        for node in sorted({self._node_of[m.sensor] for m in (*first, *more)}):
            self._join(node, f)
        return f

    def review(self, tracks: list[_Fused]) -> None:
        """After the updates: duplicates deleted; the members of every deleted track
        told to drop their local tracks, and the nodes a track took requests from (or
        lost a member of) invited, from the latest fused state."""
        self._duplicates.review(tracks)
        for f in tracks:
            if f.deleted:
                for node, lid in sorted(f.members.items()):
                    self._drop(node, lid, f.last.t)
                continue
            for node in sorted(f.joins):
                self._join(node, f)
            f.joins = set()

    def _hit(self, nodes: set[str], confirmed: bool, evidence: int) -> bool:
        """:func:`fusion.tracking.table.scores_hit` on the kinds of the nodes' sensors. Here the
        ghost along an angle sensor's ray is a local angle track alone holding a fused
        track (fed back to it under PHHNV/DDHNV) whose range drifts away from the radar
        plots, which then start a second track on the target."""
        return scores_hit([self._kinds.get(n, "azel") for n in nodes], confirmed, evidence)

    def _join(self, node: str, f: _Fused) -> None:
        """Send ``node`` a new local track on ``f`` from the latest fused state, named
        here (``L<n>``, never reused for that node: not after a drop, nor by a
        restarted node), so it is ``f``'s member from now on; it replaces the node's
        local track on ``f`` before, if any (one per node per fused track)."""
        if node in f.members:
            self._drop(node, f.members[node], f.last.t)
        lid = self._local_ids.setdefault(node, TrackIds("L")).next()
        f.members[node] = lid
        self._mapped[(node, lid)] = f
        f.fuser.add_node(node)
        self._send(Init(node, Estimate(f.fuser.t, f.fuser.x, f.fuser.P, self.name, "centre", lid)))

    def _forget(self, node: str, lid: str) -> None:
        """The node's local track ``lid`` is no member of its fused track any more."""
        f = self._mapped.pop((node, lid), None)
        if f is not None and f.members.get(node) == lid:
            del f.members[node]

    def _drop(self, node: str, lid: str, t: float) -> None:
        """Forget the node's local track ``lid`` and tell the node to delete it (as of ``t``)."""
        self._forget(node, lid)
        self._send(DropTrack(node, t, lid))


_COMPARED = (0, 1, 2, 3, 4, 5)  # position, velocity: what track-to-track association compares


def _hit(u: Report) -> bool:
    """A report that used a measurement (an update, or DDHNV's prediction + measurement)."""
    return isinstance(u, PredictionReport) or u.estimate.nis is not None


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
    node: object  # (node id, config) -> LocalNode
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
        return MultiTrackCentre(name, TrackerConfig.from_dict(rest), scheme, association.track_to_track())

    return Split(name, node, centre)


# In-process composition -----------------------------------------------------------------
class NetworkMethod:
    """A split method run in one process: the nodes and the centre wired back to back,
    with exactly the message semantics of the distributed run.

    Implements the streaming method interface; emits every local report as it goes up,
    and the centre's estimates (``node = "centre"``). A sensor's measurements go to the
    node ``node_of(sensor)`` (default: a node per sensor, named after it).
    """

    def __init__(self, split: Split, config: dict | None, node_of: Callable[[str], str] | None = None):
        self.name = split.name
        self._split = split
        self._config = dict(config or {})
        self._node_of = node_of or (lambda sensor: sensor)
        self.centre = self._split.centre(self._config)
        self.nodes: dict[str, LocalNode] = {}  # node id -> node
        self._out: list[Estimate] = []

    @property
    def config(self) -> dict:
        return dict(self._config)

    def _node(self, sensor: str) -> LocalNode:
        name = self._node_of(sensor)
        node = self.nodes.get(name)
        if node is None:
            node = self.nodes[name] = self._split.node(name, self._config)
        return node

    def _pump(self) -> bool:
        """Deliver downlinks and let the nodes send what they can, until quiet; True if
        anything moved."""
        moved = False
        centre, nodes, out = self.centre, self.nodes, self._out
        while True:
            delivered = sent = False
            horizon = centre.horizon  # (changes only when the centre processes an uplink)
            # in the order of their uplinks' keys (t, node, seq), as the fuser merges them:
            # not the order the nodes were created in, which a node joining later changes
            for node in [nodes[name] for name in sorted(nodes)]:
                # a scan's downlinks before the horizon that passes it, as the fuser sends them
                downs = centre.take_downlinks()
                if downs:
                    for d in downs:
                        nodes[d.node].receive(d)
                    delivered = True
                node.set_horizon(horizon)
                if not node.pending:  # (what step() would find)
                    continue
                ups = node.step()
                for u in ups:
                    if isinstance(u, (LocalReport, PredictionReport)):
                        out.append(u.estimate)
                    out += centre.process(u)
                if ups:
                    sent = True
                    horizon = centre.horizon
            if not delivered and not sent:
                return moved
            moved = True

    def _settle(self, t: float) -> list[Estimate]:
        """Every node is complete up to ``t`` (except what it holds, as its watermark
        would say): advance the centre and pump until nothing moves."""
        for node in self.nodes.values():
            node.set_watermark(t)
        while True:
            w = t
            for n in self.nodes.values():
                w = min(w, n.upstream_watermark(t))
            self._out += self.centre.advance(w)
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
                if isinstance(u, (LocalReport, PredictionReport)):
                    out.append(u.estimate)
                out += self.centre.process(u)
        return out + self.centre.finish()
