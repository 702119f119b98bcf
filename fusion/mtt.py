r"""Many targets with the patent's centralised methods: association and track management
around the per-track filters.

:class:`MultiTargetMethod` wraps a centralised method of :mod:`fusion.patent` (``SS``,
``LCDD``, ``HNDD``, ``RADAR2D``, ``ANGLE``, ``RADAR3D``): every track is one instance of
that method, which keeps doing what it does for one target — initialise from its first
scan (:func:`fusion.init3d.initial_state`), predict, and update with its scan's pieces
(SS stacking, LCDD selection, ...). The wrapper decides which plots form each track's
scan. It is switched on by ``association = "gnn"`` in the scenario's ``[tracker]``
table, so the method keeps its patent name. For HNV, PHHNV and DDHNV the same key
switches the network's nodes and centre to many targets (:mod:`fusion.network`, "Many
targets"); :class:`MultiTargetMethod` then only hands them the stream.

A *frame* is the group of plots within ``pair_tol`` of its first one, any number per
sensor (:class:`fusion.grouping.TimeGrouper`). Per frame, at the time of its first plot:
predict every track; associate sensor by sensor against the same predictions (χ² gate,
GNN; confirmed tracks first, then tentative ones over the plots left); update each track
with its plots through its method; initiate tentative tracks from the plots left, from
pairs across sensors (an angle ray meets a 2D radar's range sphere and the radar's
azimuth agrees) or from a lone plot that nothing in its frame could pair with; manage
(M-of-N, K misses, ``max_pos_std``, duplicates); report the confirmed tracks in id order.
The steps and the initiation rules in full: docs/algorithms.md, "Many targets".

Configuration (keys of ``[tracker]`` read here; the rest goes to the wrapped method):

================  ========  ===============================================================
key               default   meaning
================  ========  ===============================================================
association       —         ``"gnn"``: many targets (absent: the one-target method)
gate_prob         0.999     χ² gate probability P_G (per sensor plot, and pair consistency)
confirm_m         3         M hits ...
confirm_n         4         ... within the first N frames (birth included) confirm a track
delete_misses     3         K consecutive missed frames delete a confirmed track
max_pos_std       inf       m; a track whose √trace(P_pos) exceeds it is deleted
local_max_pos_std max_pos_… the same for the local tracks of HNV nodes, which get no
                            feedback (:mod:`fusion.network`): one deleted rejoins from the
                            fused track
merge_frames      3         F frames in which two tracks agree make the later one a
                            duplicate, deleted (:class:`fusion.association.DuplicateWatch`;
                            0: never)
================  ========  ===============================================================
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np

from .angles import wrap_pi
from .association import CONFIRMED, DELETED, DuplicateWatch, ManagementRule, TrackIds, TrackLogic, gate_threshold, gnn, mahalanobis2
from .config import config_values
from .init3d import initial_state, spherical_to_position
from .grouping import TimeGrouper
from .patent import CentralisedMethod, GroupedMethod
from .sensors3d import SphericalModel
from .types import KIND_COMPONENTS, Estimate, Measurement

ASSOCIATIONS = ("gnn",)
_PARTNER = {"range_az": "azel", "azel": "range_az"}  # kinds that start a track as a pair
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
        predicted = [tr.method.filter.predicted(t) for tr in self.tracks]
        taken: dict[int, list[Measurement]] = {}  # track index -> its plots
        left: list[Measurement] = []
        for plots in _by_sensor(frame):
            free = list(range(len(plots)))
            model = SphericalModel.from_measurement(plots[0], self.n_x)
            gate = self._gate(model.n_z)
            Z = np.array([p.z for p in plots])
            for confirmed in (True, False):
                rows = [i for i, tr in enumerate(self.tracks) if (tr.logic.status == CONFIRMED) == confirmed]
                if not rows or not free:
                    continue
                d2 = np.array([mahalanobis2(model, *predicted[i], Z[free]) for i in rows])
                pairs = gnn(d2, gate)
                for r, c in pairs:
                    taken.setdefault(rows[r], []).append(plots[free[c]])
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
        for first, more in self._initiator.groups(sorted(left, key=lambda m: m.order_key)):
            self._start(first, more)

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

    def _start(self, first: list[Measurement], more: list[Measurement] = ()) -> _Track:
        """A tentative track from the plots ``first`` (the wrapped method's own
        initialisation from a first scan), updated at once with ``more`` (same frame)."""
        method = self._make_track()
        method.track = None  # no id until confirmed
        last = method.process_scan(first)[-1]
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
    return confirmed and any("range" in KIND_COMPONENTS[k] for k in kinds)


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

    def groups(self, left: list[Measurement]) -> list[tuple[list[Measurement], list[Measurement]]]:
        """``(first, more)`` per new track from the unclaimed plots: the plots it starts
        from and those it gathers in the same frame (module docstring, "Initiation")."""
        candidates = []
        for a in left:
            if "el" not in KIND_COMPONENTS[a.kind] or "range" in KIND_COMPONENTS[a.kind]:
                continue  # the ray: an angle sensor's az/el
            for r in left:
                if r.kind != "range_az" or r.sensor == a.sensor:
                    continue
                d2 = self.pair_consistency(a, r)
                if d2 is not None:
                    candidates.append((d2, a.order_key, r.order_key, a, r))
        candidates.sort(key=lambda c: c[:3])
        used: set[tuple] = set()
        groups = []
        for _, ka, kr, a, r in candidates:
            if ka in used or kr in used:
                continue
            first, more = sorted([a, r], key=lambda m: m.order_key), []
            used |= {ka, kr}
            x, P = initial_state(first, self.n_x, self._priors)
            for plots in _by_sensor([m for m in left if m.order_key not in used and m.sensor not in (a.sensor, r.sensor)]):
                model = SphericalModel.from_measurement(plots[0], self.n_x)
                d2 = mahalanobis2(model, x, P, np.array([p.z for p in plots]))
                j = int(np.argmin(d2))
                if d2[j] <= self._gate(model.n_z):
                    more.append(plots[j])
                    used.add(plots[j].order_key)
            groups.append((first, sorted(more, key=lambda m: m.order_key)))
        # A plot starts a track alone only if nothing in the frame could pair with it
        # (lone 2D radar and angle plots attract clutter through their broad priors).
        kinds = {m.kind for m in left}
        alone = [m for m in left if m.order_key not in used and not (_PARTNER.get(m.kind) in kinds)]
        alone.sort(key=lambda m: ("range" not in KIND_COMPONENTS[m.kind], m.order_key))  # radars first
        return groups + [([m], []) for m in alone]

    def pair_consistency(self, a: Measurement, r: Measurement) -> float | None:
        """``d²`` of the radar's azimuth against the state from the angle ray and the
        radar range, or None if the ray misses the range sphere."""
        az, el = float(a.z[0]), float(a.z[1])
        point = spherical_to_position(a.site, az, el, float(r.z[1]), r.site)
        if point is None:
            return None
        d = point[0] - np.asarray(r.site, dtype=float)
        misfit = abs(wrap_pi(r.z[0] - np.arctan2(d[0], d[1])))
        if misfit > _PAIR_PREFILTER * math.sqrt(self._gate(1)) * float(r.std[0]):
            return None  # far outside the gate: skip the full computation
        x, P = initial_state(sorted([a, r], key=lambda m: m.order_key), self.n_x, self._priors)
        model = SphericalModel(("az",), r.site, [r.std[0]], self.n_x)
        d2 = float(mahalanobis2(model, x, P, np.array([[r.z[0]]]))[0])
        return d2 if d2 <= self._gate(1) else None



def _by_sensor(plots: list[Measurement]) -> list[list[Measurement]]:
    """The plots grouped by sensor, sensors in order of first appearance."""
    out: dict[str, list[Measurement]] = {}
    for m in plots:
        out.setdefault(m.sensor, []).append(m)
    return list(out.values())

