r"""Many targets with the patent's centralised methods: association and track management
around the per-track filters.

:class:`MultiTargetMethod` wraps a centralised method of :mod:`fusion.patent` (``SS``,
``LCDD``, ``HNDD``, ``RADAR2D``, ``ANGLE``, ``RADAR3D``): every track is one instance of
that method, which keeps doing what it does for one target (initialise, predict, update
with its scan's pieces); the wrapper decides which plots form each track's scan. It is
switched on by ``association = "gnn"`` in ``[tracker]``, so the method keeps its patent
name; for HNV, PHHNV and DDHNV the same key switches the network's nodes and centre to
many targets (:mod:`fusion.network`) and this wrapper only hands them the stream.

A *frame* is the group of plots within ``pair_tol`` of its first one
(:class:`fusion.grouping.TimeGrouper`). Per frame: predict every track; associate sensor
by sensor, each gated against the tracks' states updated with the plots they took from
the sensors before it (χ² gate ``d² ≤ χ²⁻¹(P_G; n_z)``, GNN; confirmed tracks first);
update each track through its method; initiate tentative tracks from the plots left
(:class:`Initiator`: angle-ray/range-sphere pairs at either crossing, those the most
sensors agree with first); manage them (M-of-N, K misses, ``max_pos_std``, duplicates)
and report the confirmed ones. The steps, the initiation rules and the keys
(:class:`AssociationConfig`): docs/algorithms.md, "Many targets".
"""

from __future__ import annotations

import dataclasses
import heapq
import math
from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np

from .angles import wrap_pi
from .association import (CONFIRMED, DELETED, DuplicateWatch, ManagementRule, TrackIds, TrackLogic, gate_threshold,
                          gating_update, gnn, mahalanobis2)
from .config import config_values
from .init3d import FAR, NEAR, initial_state, spherical_to_position
from .grouping import TimeGrouper
from .patent import CentralisedMethod, GroupedMethod
from .measurement.kinds import KINDS, RAY, SPHERE, model_of, partners
from .measurement.models import SphericalModel
from .types import Estimate, Measurement

ASSOCIATIONS = ("gnn",)
_PAIR_PREFILTER = 10.0  # × the gate's σ: azimuth misfit beyond which a pair is not evaluated


@dataclass(frozen=True)
class AssociationConfig:
    """The association and track-management keys of ``[tracker]`` (module docstring)."""

    association: str = "gnn"
    gate_prob: float = 0.999
    confirm_m: int = 3
    confirm_n: int = 4
    delete_misses: int = 3
    max_pos_std: float = math.inf
    local_max_pos_std: float | None = None
    merge_frames: int = 3

    KEYS = ("association", "gate_prob", "confirm_m", "confirm_n", "delete_misses", "max_pos_std",
            "local_max_pos_std", "merge_frames")

    @classmethod
    def split(cls, config: dict | None) -> tuple["AssociationConfig | None", dict]:
        """``(association config or None, the rest of the table)``: None when the table
        has no ``association`` key (one target: the method as it is)."""
        config = dict(config or {})
        mine = {k: config.pop(k) for k in cls.KEYS if k in config}
        if "association" not in mine:
            if mine:
                raise ValueError(f"tracker config keys {sorted(mine)} need 'association' (one of {ASSOCIATIONS})")
            return None, config
        values = config_values(cls, mine, "tracker config")
        for key in ("confirm_m", "confirm_n", "delete_misses", "merge_frames"):
            if key in values and (not float(values[key]).is_integer()):
                raise ValueError(f"tracker config {key!r} must be an integer, got {values[key]!r}")
            if key in values:
                values[key] = int(values[key])
        cfg = cls(**values)
        if cfg.association not in ASSOCIATIONS:
            raise ValueError(f"tracker config 'association' must be one of {ASSOCIATIONS}, got {cfg.association!r}")
        if not 0.0 < cfg.gate_prob < 1.0:
            raise ValueError(f"tracker config 'gate_prob' must lie in (0, 1), got {cfg.gate_prob}")
        if not cfg.max_pos_std > 0.0:
            raise ValueError(f"tracker config 'max_pos_std' must be > 0, got {cfg.max_pos_std}")
        if cfg.local_max_pos_std is not None and not cfg.local_max_pos_std > 0.0:
            raise ValueError(f"tracker config 'local_max_pos_std' must be > 0, got {cfg.local_max_pos_std}")
        cfg.rule()  # M <= N, K >= 1
        cfg.duplicate_watch()  # F >= 0
        return cfg, config

    @property
    def local_pos_std_limit(self) -> float:
        """The ``max_pos_std`` of an HNV node's local tracks."""
        return self.max_pos_std if self.local_max_pos_std is None else self.local_max_pos_std

    def rule(self) -> ManagementRule:
        return ManagementRule(self.confirm_m, self.confirm_n, self.delete_misses, self.max_pos_std)

    def duplicate_watch(self) -> DuplicateWatch:
        return DuplicateWatch(self.merge_frames, self.gate_prob)


class _Track:
    """One track: its filter (an instance of the wrapped method) and its life."""

    __slots__ = ("method", "logic", "birth", "last")

    def __init__(self, method: CentralisedMethod, logic: TrackLogic, birth: int, last: Estimate):
        self.method, self.logic, self.birth = method, logic, birth
        self.last = last  # its estimate of the latest frame (updated, or predicted when missed)


class MultiTargetMethod(GroupedMethod):
    """Association and track management around a centralised patent method.

    Args:
        name: the wrapped method's name (the estimates carry it).
        make_track: builds a fresh instance of the wrapped method (one per track).
        config: the association keys.
    """

    def __init__(self, name: str, make_track: Callable[[], CentralisedMethod], config: AssociationConfig):
        self.name = name
        self._make_track = make_track
        proto = make_track()
        if not isinstance(proto, CentralisedMethod):  # HNV, PHHNV, DDHNV associate themselves (fusion.methods)
            raise ValueError(f"association is available for the centralised methods (LCDD, HNDD, SS, RADAR2D, "
                             f"ANGLE, RADAR3D) and HNV, PHHNV, DDHNV, not {name}")
        self.kinds = proto.kinds
        self.n_x = proto.n_x
        self.config = config
        self.rule = config.rule()
        self._initiator = Initiator(self.n_x, proto.priors, config.gate_prob)
        self._grouper = TimeGrouper(proto.config.pair_tol)
        self._ids = TrackIds()
        self._births = 0
        self._duplicates = config.duplicate_watch()
        self.tracks: list[_Track] = []  # confirmed in id order, then tentative in birth order

    def __repr__(self) -> str:
        return f"MultiTargetMethod({self.name!r})"

    # One frame -----------------------------------------------------------------------
    def _gate(self, dof: int) -> float:
        return gate_threshold(dof, self.config.gate_prob)

    def _group(self, frame: list[Measurement]) -> list[Estimate]:
        t = frame[0].t
        state = [tr.method.filter.predicted(t) for tr in self.tracks]  # gating states
        taken: dict[int, list[Measurement]] = {}  # track index -> its plots
        left: list[Measurement] = []
        sensors = _by_sensor(frame)
        for k, plots in enumerate(sensors):
            free = list(range(len(plots)))
            model = model_of(plots[0], self.n_x)
            gate = self._gate(model.n_z)
            Z = np.array([p.z for p in plots])
            for confirmed in (True, False):
                rows = [i for i, tr in enumerate(self.tracks) if (tr.logic.status == CONFIRMED) == confirmed]
                if not rows or not free:
                    continue
                d2 = np.array([mahalanobis2(model, *state[i], Z[free]) for i in rows])
                pairs = gnn(d2, gate)
                for r, c in pairs:
                    taken.setdefault(rows[r], []).append(plots[free[c]])
                    if k + 1 < len(sensors):  # the next sensor is gated against the updated state
                        state[rows[r]] = gating_update(model, *state[rows[r]], Z[free[c]])
                used = {free[c] for _, c in pairs}
                free = [j for j in free if j not in used]
            left += [plots[j] for j in free]

        evidence = min(2, len({m.sensor for m in frame}))  # sensors a hit needs (scores_hit)
        for i, tr in enumerate(self.tracks):
            if i in taken:
                tr.last = tr.method.process_scan(sorted(taken[i], key=lambda m: m.order_key))[-1]
            else:
                tr.last = tr.method.coast(t)
            sensors = {m.sensor: m.kind for m in taken.get(i, ())}
            tr.logic.record(scores_hit(list(sensors.values()), tr.logic.status == CONFIRMED, evidence),
                            tr.method.filter.P[:3, :3])
        live = {tr.birth: tr for tr in self.tracks if tr.logic.status != DELETED}  # in priority order
        for birth in self._duplicates.duplicates([(b, tr.last.x, tr.last.P) for b, tr in live.items()]):
            live[birth].logic.status = DELETED
        for first, more, x, P in self._initiator.groups(sorted(left, key=lambda m: m.order_key)):
            self._start(first, more, x, P)

        for tr in self.tracks:
            if tr.logic.status == CONFIRMED and tr.method.track is None:
                tr.method.track = self._ids.next()
        self.tracks = [tr for tr in self.tracks if tr.logic.status != DELETED]
        confirmed = sorted((tr for tr in self.tracks if tr.logic.status == CONFIRMED), key=lambda tr: self._id_key(tr))
        self.tracks = confirmed + sorted((tr for tr in self.tracks if tr.logic.status != CONFIRMED),
                                         key=lambda tr: tr.birth)
        return [dataclasses.replace(tr.last, track=tr.method.track) for tr in confirmed]

    @staticmethod
    def _id_key(tr: _Track) -> int:
        return int(tr.method.track[1:])

    def _start(self, first: list[Measurement], more: list[Measurement], x: np.ndarray, P: np.ndarray) -> _Track:
        """A tentative track started at ``(x, P)``, the initial state of the plots
        ``first`` (:meth:`Initiator.groups`), updated at once with ``more`` (same frame)."""
        method = self._make_track()
        method.track = None  # no id until confirmed
        last = method.start(x, P, first[0].t)
        if more:
            last = method.process_scan(list(more))[-1]
        self._births += 1
        tr = _Track(method, TrackLogic(self.rule), self._births, last)
        self.tracks.append(tr)  # confirmed at birth if M = 1: given its id with the others
        return tr


def scores_hit(kinds: Sequence[str], confirmed: bool, evidence: int) -> bool:
    """Whether a track scores a hit in a frame (module docstring, step 5), in every
    topology: ``kinds`` are the measurement kinds of the sensors whose plots (or local
    tracks) it took, one per sensor; ``evidence`` is two, or one if the frame holds one
    sensor.

    A tentative track needs ``evidence`` sensors: one angle or radar plot fixes only a
    line or a circle, which false alarms and neighbouring targets satisfy. A confirmed
    one needs them too, or one sensor that measures range: fed by an angle sensor
    alone, a track's range drifts away from the target's radar plots while the
    target's rays keep it alive — a ghost along the ray. (air-picture, SS, run 0: a
    track fed by angle2 alone in 25 of 30 frames, 1.5–2 km off every aircraft, lived
    34 frames with a hit from one sensor of any kind.)"""
    if len(kinds) >= evidence:
        return True
    return confirmed and any(KINDS[k].fixes_range for k in kinds)


class Initiator:
    """New tracks from the plots of one frame that no track took (module docstring,
    "Initiation"); shared by :class:`MultiTargetMethod` and the distributed centre
    (:class:`fusion.network.MultiTrackCentre`)."""

    def __init__(self, n_x: int, priors, gate_prob: float):
        self.n_x = n_x
        self._priors = priors
        self.gate_prob = gate_prob

    def _gate(self, dof: int) -> float:
        return gate_threshold(dof, self.gate_prob)

    def groups(self, left: list[Measurement]) -> list[tuple[list[Measurement], list[Measurement], np.ndarray, np.ndarray]]:
        """``(first, more, x, P)`` per new track from the unclaimed plots: the plots it
        starts from, those it gathers in the same frame (module docstring, "Initiation")
        and the initial state ``(x, P)`` it starts from (``first``'s).

        Every consistent pair gathers first; pairs are then taken best first by their
        *support* — most sensors in the group, then least total ``d²`` (pair and gathered
        plots) — so a pair of one aircraft's ray with a neighbour's range sphere, which
        only its own sensors agree with, loses to the pairs of either aircraft, which the
        other sensors confirm. A pair whose gathered plots a better group took gathers
        again from what is left and waits its turn with its new support. When the angle
        sensor is outside the radar's range sphere its ray crosses it twice ahead of it:
        each crossing in the gate is a candidate of its own (:meth:`pair_consistency`),
        and the support decides between them as between any two pairs."""
        candidates = []
        radars = [r for r in left if KINDS[r.kind].start == SPHERE]
        for a in left:
            if KINDS[a.kind].start != RAY:
                continue  # the ray: an angle sensor's az/el
            for r, roots in _near_spheres(a, [r for r in radars if r.sensor != a.sensor],
                                          _PAIR_PREFILTER * math.sqrt(self._gate(1))):
                candidates += [(a, r, *pair) for pair in self.pair_consistency(a, r, roots)]
        used: set[tuple] = set()
        queue = []
        for a, r, root, d2, x, P in candidates:
            more, d2_more = self._gather(a, r, x, P, left, used)
            queue.append((-len(more), d2 + d2_more, a.order_key, r.order_key, root, d2, a, r, x, P, more))
        heapq.heapify(queue)  # (ka, kr, root) is unique: the comparison never reaches the plots
        groups = []
        while queue:
            _, _, ka, kr, root, d2, a, r, x, P, more = heapq.heappop(queue)
            if ka in used or kr in used:
                continue
            if any(m.order_key in used for m in more):  # a better group took some: gather again
                more, d2_more = self._gather(a, r, x, P, left, used)
                heapq.heappush(queue, (-len(more), d2 + d2_more, ka, kr, root, d2, a, r, x, P, more))
                continue
            used |= {ka, kr, *(m.order_key for m in more)}
            groups.append((sorted([a, r], key=lambda m: m.order_key), sorted(more, key=lambda m: m.order_key), x, P))
        # A plot starts a track alone only if nothing in the frame could pair with it
        # (lone 2D radar and angle plots attract clutter through their broad priors).
        kinds = {m.kind for m in left}
        alone = [m for m in left if m.order_key not in used and not (partners(m.kind) & kinds)]
        alone.sort(key=lambda m: (not KINDS[m.kind].fixes_range, m.order_key))  # radars first
        return groups + [([m], [], *initial_state([m], self.n_x, self._priors)) for m in alone]

    def _gather(self, a: Measurement, r: Measurement, x: np.ndarray, P: np.ndarray, left: list[Measurement],
                used: set):
        """The nearest plot in the χ² gate of the pair's initial state ``(x, P)`` from
        every other sensor, among the plots not ``used``; and the sum of their ``d²``."""
        more, total = [], 0.0
        for plots in _by_sensor([m for m in left if m.order_key not in used and m.sensor not in (a.sensor, r.sensor)]):
            model = model_of(plots[0], self.n_x)
            d2 = mahalanobis2(model, x, P, np.array([p.z for p in plots]))
            j = int(np.argmin(d2))
            if d2[j] <= self._gate(model.n_z):
                more.append(plots[j])
                total += float(d2[j])
        return more, total

    def pair_consistency(self, a: Measurement, r: Measurement,
                         roots: Sequence[int] = (FAR, NEAR)) -> list[tuple[int, float, np.ndarray, np.ndarray]]:
        """``(root, d², x, P)`` per crossing (among ``roots``) of the angle plot's ray with
        the radar plot's range sphere that is ahead of the angle sensor (``root``:
        :data:`fusion.init3d.FAR` or ``NEAR``, module docstring of :mod:`fusion.init3d`)
        and consistent with the radar's azimuth: ``(x, P)`` the pair's initial state at
        that crossing, ``d²`` of the radar's azimuth against it inside the χ²(1) gate.
        Empty if the ray misses or touches the sphere or no crossing is in the gate."""
        pair = sorted([a, r], key=lambda m: m.order_key)
        model = SphericalModel(("az",), r.site, [r.std[0]], self.n_x)
        out = []
        for root in roots:
            if spherical_to_position(a.site, float(a.z[0]), float(a.z[1]), float(r.z[1]), r.site, root) is None:
                continue
            x, P = initial_state(pair, self.n_x, self._priors, root)
            d2 = float(mahalanobis2(model, x, P, np.array([[r.z[0]]]))[0])
            if d2 <= self._gate(1) and not any(np.array_equal(x, o[2]) for o in out):  # one state: one candidate
                out.append((root, d2, x, P))
        return out


def _near_spheres(a: Measurement, radars: list[Measurement], k: float) -> list[tuple[Measurement, tuple[int, ...]]]:
    """The 2D radar plots whose range sphere the angle plot's ray crosses ahead of it at a
    point within ``k`` azimuth σ of the radar's own azimuth, each with the roots that do —
    a cheap screen, all radars at once, before :meth:`Initiator.pair_consistency` (``k`` ≫
    the gate: a crossing it drops is far outside it). The ray-sphere points are
    :func:`fusion.init3d.spherical_to_position`'s."""
    if not radars:
        return []
    az, el = float(a.z[0]), float(a.z[1])
    u = np.array([math.cos(el) * math.sin(az), math.cos(el) * math.cos(az), math.sin(el)])
    sites = np.array([r.site for r in radars], dtype=float)
    Z = np.array([r.z for r in radars], dtype=float)
    std_az = np.array([r.std[0] for r in radars], dtype=float)
    w = np.asarray(a.site, dtype=float) - sites
    b = w @ u
    disc = b * b - (np.sum(w * w, axis=1) - Z[:, 1] ** 2)
    sq = np.sqrt(np.where(disc > 0.0, disc, 0.0))
    keep = {}
    for root in (FAR, NEAR):
        t = -b + root * sq
        d = w + t[:, None] * u  # the point from the radar's site
        misfit = np.abs(wrap_pi(Z[:, 0] - np.arctan2(d[:, 0], d[:, 1])))
        keep[root] = (disc > 0.0) & (t > 0.0) & (misfit <= k * std_az)
    out = [(r, tuple(root for root in (FAR, NEAR) if keep[root][i])) for i, r in enumerate(radars)]
    return [(r, roots) for r, roots in out if roots]


def _by_sensor(plots: list[Measurement]) -> list[list[Measurement]]:
    """The plots grouped by sensor, sensors in order of first appearance."""
    out: dict[str, list[Measurement]] = {}
    for m in plots:
        out.setdefault(m.sensor, []).append(m)
    return list(out.values())

