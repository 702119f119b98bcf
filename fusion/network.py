r"""The distributed topologies as pure state machines: local nodes and a centre.

A *local node* runs beside one sensor; the *centre* fuses what the nodes send up. The
same two classes run inside the tracker and fuser processes (which only move their
inputs and outputs over Zenoh) and inside :class:`NetworkMethod`, the in-process
composition the Monte Carlo evaluation uses — so a distributed run and the in-process
evaluation compute the very same thing.

Messages::

    Uplink   node → centre   a local estimate (track or prediction), a raw measurement
                             (an *initialisation request*, or DDHNV's measurement for the
                             centre's update), or both (DDHNV), stamped with its time
    Downlink centre → node   an estimate the node takes as its next prior: ``init``
                             (the shared initial state, or the fused state for a node
                             that joins later) or feedback (PHHNV, DDHNV)

Topologies (DESIGN.md; ``mode`` of :class:`TrackNode`):

==========  ==========  ==================================================================
method      topology    local node                        centre
==========  ==========  ==================================================================
HNV         distributed EKF update per measurement        fuse the reports of a scan
PHHNV       feedback    EKF update from the fed-back prior fuse, feed the result back
DDHNV       two-stage   predict from the fed-back prior;  fuse the predictions (stage 1),
                        send prediction + measurement     update it with each measurement,
                                                          fuse those (stage 2), feed back
KF+TR,      distributed smooth each bearing (KF / MKF)     Torrieri on the latest smoothed
MKF+TR                                                    bearing of every station
==========  ==========  ==================================================================

**Initialisation.** A 3D node without a prior sends its first measurement up as an
initialisation request and waits. The centre groups requests into a scan like any
other input; its first scan gives the shared initial state
(:func:`fusion.init3d.initial_state`), sent down to every node of that scan. A request
arriving later (a sensor that joins or a tracker that restarts) is answered with the
centre's latest fused state. The request's measurement initialises, it is not used
again.

**Scans at the centre** are those of :class:`fusion.patent.ScanGrouper`, over uplinks
(one per node per scan); a scan is fused at the time of its first uplink (offsets
within ``pair_tol`` are neglected, as in the centralised methods). Only the nodes with
an uplink in the scan take part.

**Feedback ordering.** A fed-back node must start its update at ``t_k`` from the fusion
of every scan that ended before it: those with ``t_k − t_s > pair_tol`` (a scan closer
than that would have taken the measurement itself). The centre publishes a *horizon*
``W``: every downlink of a fusion at ``t_s ≤ W`` has been sent. A node processes its
pending measurement at ``t_k`` once ``t_k − W ≤ pair_tol``. Meanwhile it declares to
the centre that it is complete only up to just before ``t_k`` (its upstream
watermark), which lets the centre close every earlier scan — so the pipeline moves in
lock-step without deadlock, and the result does not depend on message timing. A node
whose downlink goes quiet is told by its process to run on alone (``alone=True``):
it then updates from its own last estimate, or initialises itself from its own
measurement; the result is then timing-dependent, and the process says so.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

from .init3d import initial_state
from .patent import KINDS_3D, LocalTracker, ScanGrouper, TrackerConfig
from .track_fusion import TrackFuser
from .types import Estimate, Measurement

MODES = ("track", "feedback", "predict")


@dataclass(frozen=True)
class Uplink:
    """One item a local node sends to the centre (module docstring)."""

    t: float
    node: str
    seq: int
    estimate: Estimate | None = None
    measurement: Measurement | None = None

    @property
    def sensor(self) -> str:  # the scan grouper's notion of "source"
        return self.node

    @property
    def order_key(self) -> tuple:
        return (self.t, self.node, self.seq)

    @property
    def init_request(self) -> bool:
        return self.estimate is None and self.measurement is not None


@dataclass(frozen=True)
class Downlink:
    """A prior sent down to one node; ``estimate.extra`` may carry the centre's own
    update with that node's measurement (``sensor_x``, ``sensor_P``; DDHNV)."""

    node: str
    estimate: Estimate
    init: bool


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

    def _uplink(self, t: float, estimate=None, measurement=None) -> Uplink:
        self._seq += 1
        return Uplink(float(t), self.node, self._seq, estimate, measurement)

    def _blocked(self, m: Measurement) -> str | None:
        return None

    def _process(self, m: Measurement, alone: bool) -> list[Uplink]:
        raise NotImplementedError


class TrackNode(LocalNode):
    """The local tracker of HNV (``mode="track"``), PHHNV (``"feedback"``) and DDHNV
    (``"predict"``) around a :class:`~fusion.patent.LocalTracker`."""

    kinds = KINDS_3D

    def __init__(self, sensor: str, config: TrackerConfig, method: str, mode: str, track: str = "T1"):
        if mode not in MODES:
            raise ValueError(f"mode must be one of {MODES}, got {mode!r}")
        super().__init__(sensor, config.pair_tol)
        self.config = config
        self.mode = mode
        self.tracker = LocalTracker(sensor, config.motion_model(), method, track)
        self._requested = False

    def receive(self, d: Downlink) -> None:
        e = d.estimate
        if d.init or self.mode != "track":
            if self.tracker.initialised and e.t < self.tracker.ekf.t:
                return  # older than where this node already is (it ran alone meanwhile)
            self.tracker.initialise(e.x, e.P, e.t)
            self._requested = False

    def _blocked(self, m):
        if not self.tracker.initialised:
            return "init" if self._requested else None
        if self.mode != "track" and m.t - self.horizon > self.pair_tol:
            return "feedback"
        return None

    def _process(self, m, alone):
        if not self.tracker.initialised:
            if alone:  # no centre: start from this sensor's own measurement
                x, P = initial_state([m], self.tracker.motion.n_x, self.config.priors())
                self.tracker.initialise(x, P, m.t)
                return []
            self._requested = True
            return [self._uplink(m.t, measurement=m)]
        if self.mode == "predict":
            return [self._uplink(m.t, self.tracker.predict(m.t), m)]
        return [self._uplink(m.t, self.tracker.update(m))]


class StationNode(LocalNode):
    """A DF station of KF+TR / MKF+TR: smooths its bearings, sends each smoothed
    bearing (a ``bearing`` measurement with the smoothed std) up."""

    kinds = frozenset({"bearing"})

    def __init__(self, sensor: str, config: dict | None, cross_fed: bool):
        from .df.methods import DFConfig, make_station_smoother

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

    feedback = False

    def __init__(self):
        self._down: list[Downlink] = []

    def take_downlinks(self) -> list[Downlink]:
        out, self._down = self._down, []
        return out

    @property
    def horizon(self) -> float:
        return -math.inf


class TrackCentre(Centre):
    """The centre of HNV / PHHNV / DDHNV: scans of uplinks, a
    :class:`~fusion.track_fusion.TrackFuser`, and the downlinks."""

    def __init__(self, name: str, config: TrackerConfig, mode: str, track: str = "T1"):
        super().__init__()
        self.name = name
        self.config = config
        self.mode = mode
        self.feedback = mode != "track"
        self.track = track
        self.motion = config.motion_model()
        self.fuser = TrackFuser(config.fusion_rule, self.motion, config.ci_criterion, name, track)
        self.nodes: set[str] = set()
        self._grouper = ScanGrouper(config.pair_tol)
        self._watermark = -math.inf

    # -- streaming ------------------------------------------------------------------------
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

    # -- scans ----------------------------------------------------------------------------
    def _run(self, scans) -> list[Estimate]:
        out: list[Estimate] = []
        for scan in scans:
            out += self._scan(scan)
        return out

    def _send(self, node: str, e: Estimate, init: bool) -> None:
        self._down.append(Downlink(node, e, init))

    def _scan(self, scan: list[Uplink]) -> list[Estimate]:
        t = scan[0].t
        requests = [u for u in scan if u.init_request]
        reports = [u for u in scan if not u.init_request]
        if not self.fuser.initialised:
            if reports:
                raise ValueError(f"{self.name}: local estimates before the shared initial state: "
                                 f"{[u.node for u in reports]}")
            x, P = initial_state([u.measurement for u in requests], self.motion.n_x, self.config.priors())
            self.fuser.initialise(x, P, t)
            e = Estimate(t, x, P, self.name, "centre", self.track)
            for u in requests:
                self._join(u.node, e)
            return [e]
        out: list[Estimate] = []
        if reports:
            out.append(self._fuse(t, reports))
        if requests:  # late joiners start from the latest fused state
            e = Estimate(self.fuser.t, self.fuser.x, self.fuser.P, self.name, "centre", self.track)
            for u in requests:
                self._join(u.node, e)
        return out

    def _join(self, node: str, e: Estimate) -> None:
        self.nodes.add(node)
        self.fuser.add_node(node)
        self._send(node, e, init=True)

    def _fuse(self, t: float, reports: list[Uplink]) -> Estimate:
        local = [_at(u.estimate, t) for u in reports]
        per_node: dict[str, Estimate] = {}
        if self.mode == "predict":
            stage1 = self.fuser.fuse(t, local)
            updates = []
            for u in reports:  # the centre's updates of the fused prediction
                c = LocalTracker(u.measurement.sensor, self.motion, self.name, self.track)
                c.accept_prior(stage1.x, stage1.P, t)
                per_node[u.node] = c.update(u.measurement, t)
                updates.append(per_node[u.node])
            fused = self.fuser.fuse(t, updates)
            nis_from = updates
        else:
            fused = self.fuser.fuse(t, local)
            nis_from = [e for e in local if e.nis is not None]
        nis = sum(e.nis for e in nis_from) if nis_from else None
        dof = sum(e.nis_dof for e in nis_from) if nis_from else None
        extra = {"omega": fused.extra["omega"]} if "omega" in fused.extra else {}  # CI weights
        centre = Estimate(t, fused.x, fused.P, self.name, "centre", self.track, nis, dof, extra)
        if self.feedback:
            for node in sorted(self.nodes):
                extra = {}
                if node in per_node:
                    extra = {"sensor_x": per_node[node].x, "sensor_P": per_node[node].P}
                self._send(node, Estimate(t, fused.x, fused.P, self.name, "centre", self.track, extra=extra), False)
        return centre


def _at(e: Estimate, t: float) -> Estimate:
    """A local estimate re-stamped to the scan time (offsets within pair_tol neglected)."""
    return e if e.t == t else Estimate(t, e.x, e.P, e.method, e.node, e.track, e.nis, e.nis_dof, e.extra)


class StationCentre(Centre):
    """The centre of KF+TR / MKF+TR: Torrieri on the latest smoothed bearings
    (:class:`fusion.df.methods.SmootherTorrieriMethod` with the smoothing done upstream)."""

    def __init__(self, name: str, config: dict | None):
        from .df.methods import SmootherTorrieriMethod

        super().__init__()
        self.name = name
        self.method = SmootherTorrieriMethod(name == "MKF+TR", config, smoothed_upstream=True)

    def process(self, u: Uplink) -> list[Estimate]:
        return self.method.process(u.measurement)

    def advance(self, t: float) -> list[Estimate]:
        return self.method.advance(t)

    def finish(self) -> list[Estimate]:
        return self.method.finish()


# The split of a method into nodes and a centre ---------------------------------------
@dataclass(frozen=True)
class Split:
    """How a distributed method is split: its topology, a node factory and a centre."""

    topology: str
    node: object  # (sensor, config) -> LocalNode
    centre: object  # (config) -> Centre


def _track_split(name: str, mode: str, topology: str) -> Split:
    return Split(
        topology,
        lambda sensor, config: TrackNode(sensor, TrackerConfig.from_dict(config), name, mode),
        lambda config: TrackCentre(name, TrackerConfig.from_dict(config), mode),
    )


SPLITS: dict[str, Split] = {
    "HNV": _track_split("HNV", "track", "distributed"),
    "PHHNV": _track_split("PHHNV", "feedback", "feedback"),
    "DDHNV": _track_split("DDHNV", "predict", "two-stage"),
    "KF+TR": Split("distributed", lambda s, c: StationNode(s, c, False), lambda c: StationCentre("KF+TR", c)),
    "MKF+TR": Split("distributed", lambda s, c: StationNode(s, c, True), lambda c: StationCentre("MKF+TR", c)),
}


def split(name: str) -> Split:
    try:
        return SPLITS[name]
    except KeyError:
        raise ValueError(f"{name} is not a distributed method (distributed methods: {', '.join(SPLITS)})") from None


# In-process composition -----------------------------------------------------------------
class NetworkMethod:
    """A split method run in one process: the nodes and the centre wired back to back,
    with exactly the message semantics of the distributed run.

    Implements the streaming method interface; emits every local report (``node`` =
    sensor) as it goes up, and the centre's estimates (``node = "centre"``).
    """

    def __init__(self, name: str, config: dict | None):
        self.name = name
        self._split = split(name)
        self._config = dict(config or {})
        self.centre = self._split.centre(self._config)
        self.nodes: dict[str, LocalNode] = {}
        self._out: list[Estimate] = []

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
                    if u.estimate is not None:
                        self._out.append(u.estimate)
                    self._out += self.centre.process(u)
            if not downs and not sent:
                return moved
            moved = True

    def _settle(self, t: float) -> list[Estimate]:
        """Every node is complete up to ``t`` (except what it holds, as its watermark
        would say): advance the centre and pump until nothing moves."""
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
                if u.estimate is not None:
                    out.append(u.estimate)
                out += self.centre.process(u)
        return out + self.centre.finish()
