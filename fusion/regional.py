r"""The regional topology as pure state machines: regional fusers under one system fuser.

A *regional fuser* (:class:`RegionalFuser`) is an ordinary centralised many-target
method (:class:`fusion.mtt.MultiTargetMethod`, the method's own ``[tracker]``) over the
plots of its region's sensors that it can place over its region and margin (a radar
plot's ground point within :data:`PLOT_SLACK_M` of them; a ray is always taken). After
each frame it drops the tracks that have left its region and margin
(:meth:`fusion.regions.Region.holds`) and publishes its confirmed tracks, ids
namespaced by region (``north.T3``), with the ids it stopped publishing: one
:class:`RegionalFrame`.

The *system fuser* (:class:`SystemFuser`) takes the regional frames as a distributed
centre takes local tracks, and keeps the system tracks ``T<n>``:

1. a regional track keeps its system track while it stays within the track-to-track
   χ² gate of the system track's other members, ``d² = Δᵀ(P₁ + P₂)⁺Δ`` on position and
   velocity, both predicted to the later time (:func:`fusion.tracking.hypotheses.track_distance2`);
2. a regional track that has none is assigned by GNN (:func:`fusion.tracking.associators.gnn`)
   to the system tracks that hold no track of its region, against their latest fused
   estimate; one left over starts a new system track if it is over its region's polygon
   (or over none) and in the gate of no system track holding another region's track,
   and otherwise waits unpublished, tried again each frame: a margin is for handing
   over (a young track there, its velocity still poor, would start a duplicate of the
   neighbour's), and a second track of one region on an aircraft two regions hold is a
   duplicate;
3. each system track is the covariance intersection of its members, predicted to the
   latest of their times: ``P⁻¹ = ωP₁⁻¹ + (1−ω)P₂⁻¹``, ``P⁻¹x = ωP₁⁻¹x₁ + (1−ω)P₂⁻¹x₂``,
   ω minimising ``tr P`` (:func:`fusion.track_fusion.fuse_ci`), folded pairwise over
   three or four members (where regions meet), most certain first. Two regions fed by
   one sensor, with the same process noise, have errors correlated in a way neither
   knows; CI is consistent for every such correlation, the naive product is not
   (docs/regional.md);
4. two system tracks, one of them held by two regions or more, that stay in each other's
   gate for ``merge_frames`` consecutive looks (the trackers' own duplicate rule,
   :class:`fusion.tracking.table.DuplicateWatch`, on the system estimates) are one
   aircraft: the younger is merged into the older, its members joining it where the older
   holds no track of their region, and otherwise left waiting (a region's duplicate: it
   may join a system track later, never start one). Each region's tracker has reviewed its
   own tracks; a fused track no tracker has.

So an aircraft's system id survives a handover: the next region's track joins the system
track while both regions hold the aircraft in the overlap, and the first region's track
leaves it when it is dropped. :class:`RegionalMethod` wires the fusers back to back for
the in-process evaluation; with one region the system picture is its fuser's picture.
"""

from __future__ import annotations

import dataclasses
import heapq
import math
from dataclasses import dataclass, field
from typing import Callable, Mapping, Sequence

import numpy as np
from scipy.spatial import cKDTree

from .measurement.kinds import KINDS
from .patent import TrackerConfig, uses
from .regions import Region
from .track_fusion import fuse_ci, fuse_naive
from .tracking.associators import gnn
from .tracking.config import AssociationConfig
from .tracking.hypotheses import gate_threshold, track_distance2
from .tracking.table import DELETED, TrackIds
from .types import Estimate, Measurement

__all__ = ["RegionalFrame", "RegionalFuser", "RegionalMethod", "RegionalStage", "SYSTEM_RULES", "SystemFuser",
           "SystemStage", "SystemTrack"]

SYSTEM_RULES = ("ci", "naive")  # the system fuser's rules: CI; naive only to show why not (tests, docs)
_COMPARED = np.arange(6)  # position, velocity: what track-to-track association compares
PLOT_SLACK_M = 15_000.0  # m: how far beyond its region and margin a plot's ground point may be, and still be used
SCREEN_SLACK_M = 2000.0  # m: the screen's allowance for the spread's growth over an extrapolation


def _screen(a: Sequence[Estimate], b: Sequence[Estimate], gate: float) -> tuple[np.ndarray, np.ndarray]:
    """The pairs ``(i, j)`` of ``a`` and ``b`` that may be in the gate, in row-major order:
    those whose horizontal positions, each extrapolated to the later of the two times,
    lie within ``√(gate·(sᵢ + sⱼ)) + SCREEN_SLACK_M`` (``s`` the horizontal variance).
    A k-d tree over ``b``'s positions gives each ``a`` the candidates within that radius
    at its largest plus the distance the two can have moved over the span of all times
    (a superset), and the test is made on those pairs alone: the same pairs as the test
    over every pair, at the cost of the near ones."""
    def parts(es):
        return (np.array([e.t for e in es]), np.array([e.x[:2] for e in es]), np.array([e.x[3:5] for e in es]),
                np.array([e.P[0, 0] + e.P[1, 1] for e in es]))
    none = np.zeros(0, dtype=int)
    if not a or not b:
        return none, none
    (ta, pa, va, sa), (tb, pb, vb, sb) = parts(a), parts(b)
    span = max(ta.max(), tb.max()) - min(ta.min(), tb.min())
    speed_a, speed_b = np.hypot(va[:, 0], va[:, 1]), np.hypot(vb[:, 0], vb[:, 1])
    reach = np.sqrt(gate * (sa + sb.max())) + SCREEN_SLACK_M + (speed_a + speed_b.max()) * span
    near = cKDTree(pb).query_ball_point(pa, reach * (1 + 1e-9) + 1e-6)
    i = np.repeat(np.arange(len(a)), [len(n) for n in near])
    j = np.array([k for n in near for k in sorted(n)], dtype=int)
    if not len(i):
        return none, none
    t = np.maximum(ta[i], tb[j])
    gap = (pa[i] + va[i] * (t - ta[i])[:, None]) - (pb[j] + vb[j] * (t - tb[j])[:, None])
    radius = np.sqrt(gate * (sa[i] + sb[j])) + SCREEN_SLACK_M
    keep = np.sum(gap * gap, axis=-1) <= radius * radius
    return i[keep], j[keep]


@dataclass(frozen=True)
class RegionalFrame:
    """What one regional fuser publishes after a frame: its confirmed tracks held by the
    region (ids ``<region>.<id>``, ``node`` the region), and the ids it published before
    and no longer does (deleted, or dropped on leaving the region)."""

    region: str
    t: float
    tracks: tuple[Estimate, ...]
    dropped: tuple[str, ...] = ()


def _ground(m: Measurement) -> tuple[float, float]:
    """Where a plot puts its target over the ground, ``(e, n)``: a position report's
    position; a radar plot's site plus its horizontal range (the slant range where the
    elevation is not measured: at most 12 km off, a 12 km altitude seen from above) along
    its azimuth; ``(nan, nan)`` for a plot with no range (an angle sensor's ray)."""
    names = [c.name for c in KINDS[m.kind].components]
    if "east" in names:
        return float(m.z[names.index("east")]), float(m.z[names.index("north")])
    if "range" not in names or m.site is None:
        return math.nan, math.nan
    az, r = m.z[names.index("az")], m.z[names.index("range")]
    h = r * math.cos(m.z[names.index("el")]) if "el" in names else r
    return float(m.site[0] + h * math.sin(az)), float(m.site[1] + h * math.cos(az))


class RegionalFuser:
    """One region's fuser (module docstring) around a centralised many-target method
    (a :class:`~fusion.patent.GroupedMethod` with a ``tracker``), fed every measurement:
    it takes those of its region's sensors."""

    def __init__(self, region: Region, method):
        if not hasattr(method, "tracker") or not hasattr(method, "_grouper"):
            raise ValueError(f"region {region.name!r}: a regional fuser runs a centralised many-target method "
                             f"('association' in [tracker]), not {method!r}")
        self.region = region
        self.method = method
        self.sensors = frozenset(region.sensors)
        self._published: set[str] = set()

    def process(self, m: Measurement) -> list[RegionalFrame]:
        if m.sensor not in self.sensors or not uses(self.method.name, self.method.kinds, m):
            return []
        return [self._frame(g) for g in self.method._grouper.push(m)]

    def advance(self, t: float) -> list[RegionalFrame]:
        return [self._frame(g) for g in self.method._grouper.advance(t)]

    def finish(self) -> list[RegionalFrame]:
        return [self._frame(g) for g in self.method._grouper.finish()]

    def open_since(self) -> float:
        """The time of the frame it holds open (its next frame's time), ``inf`` if none:
        no frame of this fuser's will be before ``min(open_since(), next input time)``."""
        t = self.method._grouper.held_since()
        return math.inf if t is None else t

    def _frame(self, group: list[Measurement]) -> RegionalFrame:
        ground = np.array([_ground(m) for m in group])
        placed = ~np.isnan(ground[:, 0])
        keep = ~placed
        keep[placed] = self.region.holds(ground[placed], PLOT_SLACK_M)
        mine = [m for m, k in zip(group, keep) if k]
        estimates = self.method._group(mine) if mine else []
        table = self.method.tracker.table
        if table.tracks:
            held = self.region.holds(np.array([tr.last.x[:2] for tr in table.tracks]))
            for tr in (tr for tr, h in zip(table.tracks, held) if not h):
                tr.logic.status = DELETED
            table.tracks = [tr for tr, h in zip(table.tracks, held) if h]
        name = self.region.name
        live = {tr.id for tr in table.tracks if tr.id is not None}
        tracks = tuple(dataclasses.replace(e, node=name, track=f"{name}.{e.track}") for e in estimates
                       if e.track in live)
        ids = {f"{name}.{i}" for i in live}
        dropped = tuple(sorted(self._published - ids))
        self._published = ids
        return RegionalFrame(name, group[0].t, tracks, dropped)


@dataclass
class SystemTrack:
    """One system track: its id, its members (region -> regional id) and its latest estimate."""

    id: str
    members: dict[str, str] = field(default_factory=dict)
    last: Estimate | None = None

    def regional(self) -> bool:
        """Held by two regions or more: a fused track, which no region's tracker reviews."""
        return len(self.members) > 1


class SystemFuser:
    """The system picture from the regional frames (module docstring, steps 1-3).

    Args:
        name: the method's name (the estimates carry it).
        motion: the kinematic model members are predicted with (``F(dt)``, ``Q(dt)``).
        gate_prob: the track-to-track χ² gate probability.
        rule: ``ci`` (covariance intersection) or ``naive`` (independent errors assumed).
        ci_criterion: CI's ``trace`` or ``det``.
        regions: the regions by name (None: every regional track may start a system track).
        merge_frames: the consecutive looks in each other's gate that make two system
            tracks one (step 4; 0: never).
    """

    def __init__(self, name: str, motion, gate_prob: float, rule: str = "ci", ci_criterion: str = "trace",
                 regions: Mapping[str, Region] | None = None, merge_frames: int = 0):
        if rule not in SYSTEM_RULES:
            raise ValueError(f"system fusion rule must be one of {SYSTEM_RULES}, got {rule!r}")
        if not hasattr(motion, "F"):
            raise ValueError(f"the system fuser predicts with a kinematic model, not {motion!r}")
        self.name, self.motion, self.gate_prob = name, motion, gate_prob
        self.regions = dict(regions) if regions is not None else None
        self.rule, self.ci_criterion = rule, ci_criterion
        self.ids = TrackIds("T")
        self.tracks: dict[str, SystemTrack] = {}  # system id -> track, in creation order
        self.latest: dict[str, Estimate] = {}  # regional id -> its latest estimate
        self.owner: dict[str, SystemTrack] = {}  # regional id -> its system track
        self.merge_frames = merge_frames
        self.absorbed: set[str] = set()  # regional ids merged away as their region's duplicates: they never start one
        self._streak: dict[tuple[str, str], tuple[int, float]] = {}  # (older, younger) -> (looks in the gate, last look's t)

    def frame(self, f: RegionalFrame) -> list[Estimate]:
        """One regional frame; returns the estimates of the system tracks it touched."""
        for rid in f.dropped:
            self._leave(f.region, rid)
            self.latest.pop(rid, None)
            self.absorbed.discard(rid)
        for e in f.tracks:
            self.latest[e.track] = e
        unowned = []
        for e in f.tracks:
            s = self.owner.get(e.track)
            if s is not None and not self._agrees(e, s):
                self._leave(f.region, e.track)
                s = None
            if s is None:
                unowned.append(e)
        self._associate(f.region, unowned)
        touched: dict[str, SystemTrack] = {}
        for e in f.tracks:
            s = self.owner.get(e.track)
            if s is not None and s.id not in touched:
                touched[s.id] = s
                s.last = self._fuse(s)
        for s in self._review(list(touched.values())):
            touched[s.id] = s
        return [s.last for s in touched.values() if s.id in self.tracks]

    # -- association -----------------------------------------------------------------------
    def _at(self, e: Estimate, t: float) -> tuple[np.ndarray, np.ndarray]:
        """``e`` predicted to ``t ≥ e.t``."""
        if t == e.t:
            return e.x, e.P
        F, Q = self.motion.F(t - e.t), self.motion.Q(t - e.t)
        return F @ e.x, F @ e.P @ F.T + Q

    def _distance2(self, a: Estimate, b: Estimate) -> float:
        """The track-to-track ``d²`` of two estimates at the later time; ``inf`` outside
        the gate of its rank."""
        t = max(a.t, b.t)
        (xa, Pa), (xb, Pb) = self._at(a, t), self._at(b, t)
        d2, rank = track_distance2(xa, Pa, xb, Pb, dims=_COMPARED)
        return d2 if not rank or d2 <= gate_threshold(rank, self.gate_prob) else np.inf

    def _agrees(self, e: Estimate, s: SystemTrack) -> bool:
        """Whether ``e`` stays associated: in the gate of one of its system track's other
        members (trivially, if it has none)."""
        others = [self.latest[rid] for rid in s.members.values() if rid != e.track]
        return not others or any(np.isfinite(self._distance2(e, o)) for o in others)

    def _associate(self, region: str, unowned: list[Estimate]) -> None:
        """GNN of a region's regional tracks without a system track to the system tracks
        holding no track of that region; one left over starts a system track if its
        region is responsible for it (:meth:`_responsible`) and no system track holding
        another region's track is in its gate (else it is a duplicate of that one's
        aircraft, its region's second track there), and otherwise waits. The pairs are
        screened first: only those whose horizontal positions, extrapolated to the later
        time, lie within the gate's radius of their summed horizontal spread (plus
        :data:`SCREEN_SLACK_M` for the growth of that spread over the extrapolation) get
        the χ² of :meth:`_distance2`."""
        if not unowned:
            return
        near = [s for s in self.tracks.values() if s.last is not None and set(s.members) - {region}]
        free = [j for j, s in enumerate(near) if region not in s.members]
        gate = gate_threshold(len(_COMPARED), self.gate_prob)
        d2 = np.full((len(unowned), len(near)), np.inf)
        if near:
            for i, j in zip(*_screen(unowned, [s.last for s in near], gate)):
                d2[i, j] = self._distance2(unowned[i], near[j].last)
        taken = {i: free[j] for i, j in gnn(d2[:, free], gate)} if free else {}
        for i, e in enumerate(unowned):
            if i in taken:
                s = near[taken[i]]
            elif e.track not in self.absorbed and self._responsible(region, e) and not np.isfinite(d2[i]).any():
                s = SystemTrack(self.ids.next())
                self.tracks[s.id] = s
            else:
                continue  # it waits to join (tried again each frame)
            s.members[region] = e.track
            self.owner[e.track] = s

    def _responsible(self, region: str, e: Estimate) -> bool:
        """Whether ``region``'s track ``e`` may start a system track: it is over the
        region's polygon, or over no region's (the margins are for handing over: a track
        in a neighbour's polygon only joins that neighbour's tracks)."""
        if self.regions is None:
            return True
        p = e.x[:2][None, :]
        return bool(self.regions[region].inside(p)[0]) or not any(r.inside(p)[0] for r in self.regions.values())

    def _leave(self, region: str, rid: str) -> None:
        """Regional track ``rid`` is no member of its system track any more; a system
        track left without members is deleted."""
        s = self.owner.pop(rid, None)
        if s is None:
            return
        if s.members.get(region) == rid:
            del s.members[region]
        if not s.members:
            del self.tracks[s.id]
            self._streak = {k: n for k, n in self._streak.items() if s.id not in k} if self._streak else self._streak

    # -- review (step 4) ---------------------------------------------------------------------
    def _review(self, touched: list[SystemTrack]) -> list[SystemTrack]:
        """Each system track just re-fused against the system tracks near it (screened
        as in :meth:`_associate`): a pair, one of them held by two regions or more, in
        the gate of :meth:`_distance2` adds a look to its streak if it is at a later time
        than the streak's last (several regions' frames of one time are one look), out
        of it ends the streak; at ``merge_frames`` looks the younger is merged into the
        older (:meth:`_merge`). Returns the system tracks that took members."""
        if not self.merge_frames or not touched:
            return []
        others = [s for s in self.tracks.values() if s.last is not None]
        gate = gate_threshold(len(_COMPARED), self.gate_prob)
        looked: set[tuple[str, str]] = set()
        merged: list[SystemTrack] = []
        for i, j in zip(*_screen([s.last for s in touched], [o.last for o in others], gate)):
            a, b = touched[i], others[j]
            if a is b or not (a.regional() or b.regional()):
                continue
            key = (a.id, b.id) if self.ids.number(a.id) < self.ids.number(b.id) else (b.id, a.id)
            if key in looked or key[0] not in self.tracks or key[1] not in self.tracks:
                continue
            looked.add(key)
            if not np.isfinite(self._distance2(a.last, b.last)):
                self._streak.pop(key, None)
                continue
            n, t = self._streak.get(key, (0, -math.inf))
            now = max(a.last.t, b.last.t)
            self._streak[key] = n, t = (n + 1, now) if now > t else (n, t)
            if n >= self.merge_frames:
                merged.append(self._merge(self.tracks[key[0]], self.tracks[key[1]]))
        return merged

    def _merge(self, keep: SystemTrack, gone: SystemTrack) -> SystemTrack:
        """``gone``'s members join ``keep`` where it holds no track of their region, the
        others wait as their region's duplicates; ``gone`` is deleted."""
        for region, rid in gone.members.items():
            del self.owner[rid]
            if region in keep.members:
                self.absorbed.add(rid)
            else:
                keep.members[region] = rid
                self.owner[rid] = keep
        del self.tracks[gone.id]
        self._streak = {k: n for k, n in self._streak.items() if gone.id not in k}
        keep.last = self._fuse(keep)
        return keep

    # -- fusion ----------------------------------------------------------------------------
    def _fuse(self, s: SystemTrack) -> Estimate:
        """The members' estimates predicted to the latest of their times and fused."""
        members = [self.latest[rid] for rid in s.members.values()]
        t = max(e.t for e in members)
        states = [self._at(e, t) for e in members]
        if self.rule == "naive" and len(states) > 1:
            x, P = fuse_naive([x for x, _ in states], [P for _, P in states])
        else:  # CI folded pairwise, most certain first: each step's ω in closed form
            states.sort(key=lambda s: float(np.trace(s[1][:3, :3])))
            x, P = states[0]
            for xi, Pi in states[1:]:
                x, P, _ = fuse_ci([x, xi], [P, Pi], self.ci_criterion)
        return Estimate(t, x, P, self.name, "centre", s.id)


class RegionalMethod:
    """The regional topology in one process: every regional fuser fed the measurement
    stream, their frames fed to the system fuser in ``(t, region)`` order — each frame
    once no fuser can still emit an earlier one (:func:`release`), the order a system
    fuser process merges the regional fusers' streams in by their watermarks. Implements
    the streaming method interface; emits the system fuser's estimates (``node =
    "centre"``). ``clock`` (optional, e.g. ``time.process_time``): each part's time is
    summed into :attr:`cpu` (region name, or ``"system"``)."""

    def __init__(self, name: str, fusers: Sequence[RegionalFuser], system: SystemFuser,
                 clock: Callable[[], float] | None = None):
        self.name = name
        self.fusers = list(fusers)
        self.system = system
        self.clock = clock
        self.cpu: dict[str, float] = {**{f.region.name: 0.0 for f in self.fusers}, "system": 0.0}
        self._held: list[tuple[float, str, RegionalFrame]] = []  # frames not fed yet, a heap by (t, region)

    @classmethod
    def from_config(cls, name: str, regions: Mapping[str, Region], config: dict,
                    make_method: Callable[[str, dict], object], rule: str = "ci",
                    clock: Callable[[], float] | None = None) -> "RegionalMethod":
        """Method ``name``'s regional fusers (``make_method(name, config)`` each) under a
        system fuser with the method's motion model, gate and CI criterion."""
        if not regions:
            raise ValueError("the regional topology needs [regions] in the scenario or site")
        system = cls.system_fuser(name, config, regions, rule)
        return cls(name, [RegionalFuser(r, make_method(name, config)) for r in regions.values()], system, clock)

    @staticmethod
    def system_fuser(name: str, config: dict, regions: Mapping[str, Region], rule: str = "ci") -> SystemFuser:
        """Method ``name``'s system fuser: its motion model, gate and CI criterion, and the
        regions (which region may start a system track: :meth:`SystemFuser._responsible`)."""
        association, rest = AssociationConfig.split(config)
        if association is None:
            raise ValueError(f"{name}: the regional topology needs a many-target method ('association' in [tracker])")
        cfg = TrackerConfig.from_dict(rest)
        return SystemFuser(name, cfg.motion_model(), association.gate_prob, rule, cfg.ci_criterion, regions,
                           association.merge_frames)

    def process(self, m: Measurement) -> list[Estimate]:
        # another measurement at m.t may still open a frame at m.t: only earlier ones go
        return self._run(lambda f: f.process(m), lambda t: t < m.t)

    def advance(self, t: float) -> list[Estimate]:
        # nothing at or before t is still to come
        return self._run(lambda f: f.advance(t), lambda ft: ft <= t)

    def finish(self) -> list[Estimate]:
        return self._run(lambda f: f.finish(), lambda t: True)

    def _timed(self, key: str, fn, *args):
        if self.clock is None:
            return fn(*args)
        start = self.clock()
        try:
            return fn(*args)
        finally:
            self.cpu[key] += self.clock() - start

    def _run(self, step, before: Callable[[float], bool]) -> list[Estimate]:
        """``step`` every fuser, then feed the system fuser the frames that are ``before``
        what may still come and earlier than every frame a fuser holds open."""
        for f in self.fusers:
            for fr in self._timed(f.region.name, step, f):
                heapq.heappush(self._held, (fr.t, fr.region, fr))
        open_since = min((f.open_since() for f in self.fusers), default=math.inf)
        out: list[Estimate] = []
        while self._held and self._held[0][0] < open_since and before(self._held[0][0]):
            out += self._timed("system", self.system.frame, heapq.heappop(self._held)[2])
        return out


class RegionalStage:
    """A regional fuser as its own process runs it (``zfusion fuser --region``): fed its
    region's measurements by time and the merged input's watermarks (``advance``), it
    emits regional frames, and :meth:`watermark` says up to when its frames are complete
    — below the frame it holds open, and not past the input's watermark — which the
    system fuser merges the regions' frames by, in the ``(t, region)`` order of
    :class:`RegionalMethod`."""

    def __init__(self, fuser: RegionalFuser):
        self.fuser = fuser
        self._through = -math.inf  # the input's watermark: no measurement at or before it is to come

    def process(self, m: Measurement) -> list[RegionalFrame]:
        return self.fuser.process(m)

    def advance(self, t: float) -> list[RegionalFrame]:
        self._through = max(self._through, t)
        return self.fuser.advance(t)

    def finish(self) -> list[RegionalFrame]:
        return self.fuser.finish()

    def watermark(self) -> float:
        """No frame at or before this time is still to come."""
        return min(math.nextafter(self.fuser.open_since(), -math.inf), self._through)


class SystemStage:
    """The system fuser as its own process runs it (``zfusion fuser --system``): fed the
    regional frames in ``(t, region)`` order, it emits the system tracks' estimates."""

    def __init__(self, system: SystemFuser):
        self.system = system

    def process(self, f: RegionalFrame) -> list[Estimate]:
        return self.system.frame(f)

    def advance(self, t: float) -> list[Estimate]:
        return []

    def finish(self) -> list[Estimate]:
        return []
