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
   (docs/regional.md). The system track says what its members say of the target: the
   identity (address, callsign) of the most certain member that has one, and the
   largest existence among them (a JIPDA region's);
4. two system tracks, one of them held by two regions or more or the two held by
   different regions, that stay in each other's gate for ``merge_frames`` consecutive
   looks (the trackers' own duplicate rule, :class:`fusion.tracking.table.DuplicateWatch`,
   on the system estimates) are one aircraft: the younger is merged into the older, its
   members joining it where the older holds no track of their region, and otherwise left
   waiting (a region's duplicate: it may join a system track later, never start one).
   Each region's tracker has reviewed its own tracks; a fused track, or two regions'
   tracks, no tracker has.

So an aircraft's system id survives a handover: the next region's track joins the system
track while both regions hold the aircraft in the overlap, and the first region's track
leaves it when it is dropped. :class:`RegionalMethod` wires the fusers back to back for
the in-process evaluation; with one region the system picture is its fuser's picture.
"""

from __future__ import annotations

import dataclasses
import heapq
import itertools
import math
from dataclasses import dataclass, field
from typing import Callable, Iterable, Mapping, Sequence

import numpy as np
from scipy.spatial import cKDTree

from .measurement.kinds import KINDS
from .motion import KinematicModel
from .patent import TrackerConfig, uses
from .regions import Region
from .track_fusion import CI_CRITERIA, fuse_naive
from .tracking.associators import gnn
from .tracking.config import AssociationConfig
from .tracking.hypotheses import _PINV_RTOL, gate_threshold
from .tracking.table import DELETED, TrackIds
from .types import Estimate, Measurement

__all__ = ["RegionalFrame", "RegionalFuser", "RegionalMethod", "RegionalStage", "SYSTEM_RULES", "SystemFuser",
           "SystemStage", "SystemTrack"]

SYSTEM_RULES = ("ci", "naive")  # the system fuser's rules: CI; naive only to show why not (tests, docs)
_COMPARED = np.arange(6)  # position, velocity: what track-to-track association compares
PLOT_SLACK_M = 15_000.0  # m: how far beyond its region and margin a plot's ground point may be, and still be used
SCREEN_SLACK_M = 2000.0  # m: the screen's allowance for the spread's growth over an extrapolation


def _transitions(motion, dt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``F(dt)`` and ``Q(dt)`` of ``motion`` for each of the ``dt`` (stacked ``(k, n, n)``):
    the per-axis blocks of :class:`~fusion.motion.KinematicModel`'s polynomial models
    (``F₁[i, j] = dt^(j−i)/(j−i)!``; ``Q₁`` continuous or discrete) evaluated at every
    ``dt`` at once and expanded as :meth:`~fusion.motion.KinematicModel.F` does (``⊗ I₃``,
    ``Q₁ ⊗ diag(axis_scale)``); any other model through its ``F`` and ``Q``, once per
    distinct ``dt``."""
    base = type(motion)
    polynomial = isinstance(motion, KinematicModel) and all(
        getattr(base, f) is getattr(KinematicModel, f) for f in ("F_axis", "Q_axis", "noise_gain_axis",
                                                                  "continuous_Q_axis"))
    if not polynomial:
        uniq, back = np.unique(dt, return_inverse=True)
        return (np.stack([motion.F(d) for d in uniq])[back], np.stack([motion.Q(d) for d in uniq])[back])
    m, k = motion.order, len(dt)
    lag = np.arange(m)[None, :] - np.arange(m)[:, None]  # j − i
    fact = np.array([math.factorial(max(n, 0)) for n in range(m)], dtype=float)
    power = dt[:, None, None] ** np.maximum(lag, 0)[None]
    F1 = np.where(lag[None] >= 0, power / fact[np.maximum(lag, 0)][None], 0.0)
    if motion.noise == "discrete":
        G = np.stack([0.5 * dt * dt, dt, np.ones(k)][:m], axis=-1)  # Γ
        Q1 = motion.q * G[:, :, None] * G[:, None, :]
    else:
        p = (m - 1) - np.arange(m)
        pf = np.array([1.0, 1.0, 2.0])[p]
        s = p[:, None] + p[None, :] + 1
        Q1 = motion.q * dt[:, None, None] ** s[None] / (s * pf[:, None] * pf[None, :])[None]
    scale = np.ones(3) if motion.axis_scale is None else motion.axis_scale

    def expand(A, d):  # A ⊗ diag(d), per k
        return (A[:, :, None, :, None] * np.diag(d)[None, None, :, None, :]).reshape(k, 3 * m, 3 * m)
    return expand(F1, np.ones(3)), expand(Q1, scale)


def _ci_pairs(x1: np.ndarray, P1: np.ndarray, x2: np.ndarray, P2: np.ndarray,
              criterion: str) -> tuple[np.ndarray, np.ndarray]:
    """:func:`fusion.track_fusion.fuse_ci` of each pair ``(x1[k], P1[k])``, ``(x2[k],
    P2[k])``, all at once, through the pencil of ``Yᵢ = Pᵢ⁻¹`` with no inverse taken:
    with ``P₂ = LLᵀ`` (Cholesky of the equilibrated ``P₂``) and ``L⁻¹P₁L⁻ᵀ = Z diag(μ)
    Zᵀ``, ``V = LZ`` has ``VᵀY₂V = I`` and ``VᵀY₁V = diag(λ)``, ``λ = 1/μ``, so
    ``P = (ωY₁ + (1−ω)Y₂)⁻¹ = V diag(1/(1 + ωa)) Vᵀ`` (``a = λ − 1``) and
    ``x = x₁ + (1−ω)PY₂(x₂ − x₁) = x₁ + (1−ω)V diag(1/(1 + ωa)) ZᵀL⁻¹(x₂ − x₁)``. ω is
    the root in ``[0, 1]`` of the criterion's derivative, ``−Σ cₐa/(1 + ωa)²`` for the
    trace (``c = |v|²``, the columns of ``V``) or ``−Σ a/(1 + ωa)`` for the determinant
    — increasing in ω, found by Newton steps kept inside a shrinking bracket. Equal
    covariances: the mean, ``P₁``."""
    d = np.diagonal(P2, axis1=-2, axis2=-1)
    if not d.min() > 0.0:  # also catches NaN
        raise ValueError("covariance is not positive definite")
    s = 1.0 / np.sqrt(d)
    try:
        C = np.linalg.cholesky(P2 * (s[:, :, None] * s[:, None, :]))
    except np.linalg.LinAlgError:
        raise ValueError("covariance is not positive definite") from None
    W = np.linalg.inv(C) * s[:, None, :]  # L⁻¹, L = diag(1/s) C
    mu, Z = np.linalg.eigh(W @ P1 @ np.swapaxes(W, -1, -2))
    if not mu.min() > 0.0:
        raise ValueError("covariance is not positive definite")
    V = (C @ Z) / s[:, :, None]
    a, c = 1.0 / mu - 1.0, np.sum(V * V, axis=-2)
    k = len(x1)
    trace = criterion == "trace"

    def slope(w, a, c):  # the derivative and its own derivative, per pair
        r = 1.0 / (1.0 + w[:, None] * a)
        if trace:
            return -np.sum(c * a * r * r, axis=-1), np.sum(2.0 * c * a * a * r ** 3, axis=-1)
        return -np.sum(a * r, axis=-1), np.sum(a * a * r * r, axis=-1)
    g0, g1 = slope(np.zeros(k), a, c)[0], slope(np.ones(k), a, c)[0]
    w = np.where(g0 >= 0.0, 0.0, 1.0)
    inner = np.flatnonzero((g0 < 0.0) & (g1 > 0.0))
    # Newton steps for the pairs not yet converged (each pair's own): a step that leaves
    # the bracket halves it instead; a pair is done once its step is below 1e-15, or its
    # bracket below 1e-14 (where the derivative's rounding makes steps cycle).
    lo, hi, wi = np.zeros(len(inner)), np.ones(len(inner)), np.full(len(inner), 0.5)
    active = np.arange(len(inner))
    for _ in range(100):
        if not len(active):
            break
        u = wi[active]
        g, gp = slope(u, a[inner[active]], c[inner[active]])
        below = g < 0.0
        lo[active], hi[active] = np.where(below, u, lo[active]), np.where(below, hi[active], u)
        step = u - g / gp
        step = np.where((step >= lo[active]) & (step <= hi[active]), step, 0.5 * (lo[active] + hi[active]))
        wi[active] = step
        active = active[(np.abs(step - u) > 1e-15) & (hi[active] - lo[active] > 1e-14)]
    w[inner] = wi
    D = 1.0 / (1.0 + w[:, None] * a)
    P = (V * D[:, None, :]) @ np.swapaxes(V, -1, -2)
    z = np.einsum("kji,kj->ki", Z, np.einsum("kij,kj->ki", W, x2 - x1))
    x = x1 + (1.0 - w)[:, None] * np.einsum("kij,kj->ki", V, D * z)
    equal = np.all(P1 == P2, axis=(-2, -1))
    if equal.any():
        x[equal], P[equal] = (x1[equal] + x2[equal]) / 2, P1[equal]
    return x, P


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

    def resume(self, published: Iterable[str]) -> None:
        """Started again where an earlier run of this region's fuser was: its method's
        table seeded with those tracks (by the caller), ``published`` their ids as its
        frames carried them (``<region>.<id>``), so its next frame says which of them it
        no longer publishes."""
        self._published = set(published)

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


class _Rows:
    """The system tracks' latest fused estimates as arrays for the screen, kept as the
    tracks change rather than built from every track per frame: per row (rows in the
    order the tracks were created, never reused until compacted) the time, horizontal
    position, velocity and variance, and which regions hold the track (a bit each). A
    k-d tree over the positions as they were when it was built; the rows written since
    are tested directly, and the tree is built again once they are many."""

    def __init__(self, regions: Sequence[str]):
        self.bit = {r: 1 << i for i, r in enumerate(regions)}
        self.row: dict[str, int] = {}  # system id -> row
        self.tracks: list[SystemTrack | None] = []
        self.t, self.s = np.zeros(0), np.zeros(0)
        self.p, self.v = np.zeros((0, 2)), np.zeros((0, 2))
        self.held = np.zeros(0, dtype=np.int64)  # the regions' bits; 0: no row (deleted)
        self._tree: cKDTree | None = None
        self._tree_t0 = 0.0
        self._tree_rows = np.zeros(0, dtype=int)
        self._fresh: set[int] = set()  # rows written since the tree was built

    def mask(self, regions) -> int:
        m = 0
        for r in regions:
            b = self.bit.get(r)
            m |= b if b is not None else self.bit.setdefault(r, 1 << len(self.bit))
        return m

    def put(self, s: SystemTrack) -> None:
        """``s`` took a new estimate or other members."""
        if s.last is None:
            return
        i = self.row.get(s.id)
        if i is None:
            i = self.row[s.id] = len(self.tracks)
            self.tracks.append(s)
            if i >= len(self.t):
                grow = max(64, len(self.t))
                self.t, self.s, self.held = (np.concatenate([a, np.zeros(grow, a.dtype)])
                                             for a in (self.t, self.s, self.held))
                self.p, self.v = (np.concatenate([a, np.zeros((grow, 2))]) for a in (self.p, self.v))
        e = s.last
        self.t[i], self.p[i], self.v[i], self.s[i] = e.t, e.x[:2], e.x[3:5], e.P[0, 0] + e.P[1, 1]
        self.held[i] = self.mask(s.members)
        self._fresh.add(i)

    def remove(self, s: SystemTrack) -> None:
        i = self.row.pop(s.id, None)
        if i is not None:
            self.tracks[i] = None
            self.held[i] = 0
            self._fresh.discard(i)

    def near(self, es: Sequence[Estimate], gate: float, eligible: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The pairs ``(i, row)`` of ``es`` and the rows where ``eligible`` (a boolean per
        row) that may be in the gate, in row-major order: those whose horizontal
        positions, each extrapolated to the later of the two times, lie within
        ``√(gate·(sᵢ + sⱼ)) + SCREEN_SLACK_M`` (``s`` the horizontal variance). The
        candidates come from two k-d trees, over the rows unchanged since the big one
        was built and over the rows written since, each over the positions extrapolated
        to its latest time ``T₀``: a row within the radius at the later time ``t`` is
        within ``√(gate·(sᵢ + max s)) + SCREEN_SLACK_M + |vᵢ|·max(0, T₀ − tᵢ) + max|v|·|tᵢ −
        T₀|`` of ``es[i]``'s own position there (a superset); the test is made on those
        pairs alone."""
        none = np.zeros(0, dtype=int)
        if not es:
            return none, none
        if len(self._fresh) > max(256, len(self.row) // 4):
            kept = self._build()
            eligible = eligible[kept]
        n = len(self.tracks)
        wanted = eligible[:n] & (self.held[:n] != 0)
        if not wanted.any():
            return none, none
        ta, pa = np.array([e.t for e in es]), np.array([e.x[:2] for e in es])
        va, sa = np.array([e.x[3:5] for e in es]), np.array([e.P[0, 0] + e.P[1, 1] for e in es])
        speed_a = np.hypot(va[:, 0], va[:, 1])
        fresh = np.array(sorted(self._fresh), dtype=int)
        fresh = fresh[wanted[fresh]]
        stale = wanted.copy()
        stale[fresh] = False
        parts_i, parts_j = [none], [none]
        for tree, t0, rows, mine in ((self._tree, self._tree_t0, self._tree_rows, stale),
                                     (*self._tree_of(fresh), fresh, wanted)):
            among = np.flatnonzero(mine)
            if tree is None or not len(among):
                continue
            reach = (np.sqrt(gate * (sa + self.s[among].max())) + SCREEN_SLACK_M + speed_a * np.maximum(0.0, t0 - ta)
                     + np.hypot(self.v[among, 0], self.v[among, 1]).max() * np.abs(ta - t0))
            found = tree.query_ball_point(pa, reach * (1 + 1e-9) + 1e-6, return_sorted=False)
            counts = np.fromiter((len(f) for f in found), int, len(found))
            cand = rows[np.fromiter(itertools.chain.from_iterable(found), int, int(counts.sum()))]
            ci = np.repeat(np.arange(len(es)), counts)
            use = mine[cand]
            parts_i.append(ci[use])
            parts_j.append(cand[use])
        i, j = np.concatenate(parts_i), np.concatenate(parts_j)
        order = np.lexsort((j, i))
        i, j = i[order], j[order]
        t = np.maximum(ta[i], self.t[j])
        gap = (pa[i] + va[i] * (t - ta[i])[:, None]) - (self.p[j] + self.v[j] * (t - self.t[j])[:, None])
        radius = np.sqrt(gate * (sa[i] + self.s[j])) + SCREEN_SLACK_M
        keep = np.sum(gap * gap, axis=-1) <= radius * radius
        return i[keep], j[keep]

    def _tree_of(self, rows: np.ndarray) -> tuple[cKDTree | None, float]:
        """A k-d tree over ``rows``' positions extrapolated to their latest time, and that time."""
        if not len(rows):
            return None, 0.0
        t0 = float(self.t[rows].max())
        return cKDTree(self.p[rows] + self.v[rows] * (t0 - self.t[rows])[:, None]), t0

    def _build(self) -> np.ndarray:
        """Compacts the rows (dropping the deleted, keeping the order) and builds the
        tree; returns the old rows kept, in their new order."""
        live = np.flatnonzero(self.held[:len(self.tracks)] != 0)
        self.tracks = [self.tracks[i] for i in live]
        self.row = {s.id: k for k, s in enumerate(self.tracks)}
        arrays = (self.t, self.s, self.held, self.p, self.v)
        self.t, self.s, self.held, self.p, self.v = (a[live].copy() for a in arrays)
        self._tree_rows = np.arange(len(live))
        self._tree, self._tree_t0 = self._tree_of(self._tree_rows)
        self._fresh = set()
        return live


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
        if ci_criterion not in CI_CRITERIA:
            raise ValueError(f"ci criterion must be one of {CI_CRITERIA}, got {ci_criterion!r}")
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
        self._rows = _Rows(list(self.regions or ()))  # the system tracks' estimates as arrays, for the screen

    def frame(self, f: RegionalFrame) -> list[Estimate]:
        """One regional frame; returns the estimates of the system tracks it touched."""
        for rid in f.dropped:
            self._leave(f.region, rid)
            self.latest.pop(rid, None)
            self.absorbed.discard(rid)
        for e in f.tracks:
            self.latest[e.track] = e
        # keeping (step 1): every owned track against its system track's other members, at once
        mine, others, whose = [], [], []
        for k, e in enumerate(f.tracks):
            s = self.owner.get(e.track)
            if s is not None:
                for rid in s.members.values():
                    if rid != e.track:
                        mine.append(e), others.append(self.latest[rid]), whose.append(k)
        agrees = np.ones(len(f.tracks), dtype=bool)
        if whose:
            agrees[whose] = False
            agrees[np.asarray(whose)[np.isfinite(self._distances2(mine, others))]] = True
        unowned = []
        for e, ok in zip(f.tracks, agrees):
            s = self.owner.get(e.track)
            if s is not None and not ok:
                self._leave(f.region, e.track)
                s = None
            if s is None:
                unowned.append(e)
        self._associate(f.region, unowned)
        touched = list({s.id: s for s in (self.owner.get(e.track) for e in f.tracks) if s is not None}.values())
        self._fuse(touched)
        merged = {s.id: s for s in self._review(touched)}
        out = {s.id: s for s in touched}
        out.update(merged)
        return [s.last for s in out.values() if s.id in self.tracks]

    # -- association -----------------------------------------------------------------------
    def _predict(self, es: Sequence[Estimate], t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Each ``es[k]`` predicted to ``t[k] ≥ es[k].t`` (itself where the times are equal),
        stacked."""
        x, P = np.array([e.x for e in es]), np.array([e.P for e in es])
        dt = t - np.array([e.t for e in es])
        move = np.flatnonzero(dt != 0)
        if len(move):
            F, Q = _transitions(self.motion, dt[move])
            x[move] = np.einsum("kij,kj->ki", F, x[move])
            P[move] = F @ P[move] @ np.swapaxes(F, -1, -2) + Q
        return x, P

    def _distances2(self, a: Sequence[Estimate], b: Sequence[Estimate]) -> np.ndarray:
        """The track-to-track ``d²`` of each pair ``(a[k], b[k])`` at the later of their
        times (:func:`~fusion.tracking.hypotheses.track_distance2` on position and
        velocity, for all pairs at once); ``inf`` outside the gate of its rank."""
        if not len(a):
            return np.zeros(0)
        t = np.maximum([e.t for e in a], [e.t for e in b])
        (xa, Pa), (xb, Pb) = self._predict(a, t), self._predict(b, t)
        d = (xa - xb)[:, _COMPARED]
        T = (Pa + Pb)[:, _COMPARED[:, None], _COMPARED[None, :]]
        sd = np.sqrt(np.clip(np.diagonal(T, axis1=-2, axis2=-1), 0.0, None))
        sd = np.where(sd > 1e-300, sd, 1.0)
        w, V = np.linalg.eigh(0.5 * (T + np.swapaxes(T, -1, -2)) / sd[:, :, None] / sd[:, None, :])
        keep = w > _PINV_RTOL * np.maximum(np.max(w, axis=-1, initial=0.0), 1e-300)[:, None]
        y = np.einsum("kji,kj->ki", V, d / sd)
        d2 = np.sum(np.where(keep, y * y / np.where(keep, w, 1.0), 0.0), axis=-1)
        rank = keep.sum(axis=-1)
        limit = np.array([gate_threshold(int(r), self.gate_prob) if r else np.inf for r in range(len(_COMPARED) + 1)])
        return np.where((rank == 0) | (d2 <= limit[rank]), d2, np.inf)

    def _associate(self, region: str, unowned: list[Estimate]) -> None:
        """GNN of a region's regional tracks without a system track to the system tracks
        holding no track of that region; one left over starts a system track if its
        region is responsible for it (:meth:`_responsible`) and no system track holding
        another region's track is in its gate (else it is a duplicate of that one's
        aircraft, its region's second track there), and otherwise waits. The pairs are
        screened first (:meth:`_Rows.near`): only those whose horizontal positions,
        extrapolated to the later time, lie within the gate's radius of their summed
        horizontal spread (plus :data:`SCREEN_SLACK_M` for the growth of that spread over
        the extrapolation) get the χ² of :meth:`_distances2`."""
        if not unowned:
            return
        rows, bit = self._rows, self._rows.mask([region])
        gate = gate_threshold(len(_COMPARED), self.gate_prob)
        i, j = rows.near(unowned, gate, (rows.held & ~bit) != 0)
        cols, j = np.unique(j, return_inverse=True)
        d2 = np.full((len(unowned), len(cols)), np.inf)
        d2[i, j] = self._distances2([unowned[k] for k in i], [rows.tracks[r].last for r in cols[j]])
        free = np.flatnonzero((rows.held[cols] & bit) == 0)
        taken = {i: int(cols[free[j]]) for i, j in gnn(d2[:, free], gate)} if len(free) else {}
        for i, e in enumerate(unowned):
            if i in taken:
                s = rows.tracks[taken[i]]
            elif e.track not in self.absorbed and self._responsible(region, e) and not np.isfinite(d2[i]).any():
                s = SystemTrack(self.ids.next())
                self.tracks[s.id] = s
            else:
                continue  # it waits to join (tried again each frame)
            s.members[region] = e.track
            self.owner[e.track] = s
            rows.put(s)

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
            self._rows.remove(s)
            self._streak = {k: n for k, n in self._streak.items() if s.id not in k} if self._streak else self._streak
        else:
            self._rows.put(s)

    # -- review (step 4) ---------------------------------------------------------------------
    def _review(self, touched: list[SystemTrack]) -> list[SystemTrack]:
        """Each system track just re-fused against the system tracks near it (screened
        as in :meth:`_associate`; the χ² only where one of the two is held by two regions
        or more, for all such pairs at once): a pair in the gate of :meth:`_distances2`
        adds a look to its streak if it is at a later time than the streak's last
        (several regions' frames of one time are one look), out of it ends the streak; at
        ``merge_frames`` looks the younger is merged into the older (:meth:`_merge`).
        Returns the system tracks that took members."""
        if not self.merge_frames or not touched:
            return []
        rows = self._rows
        gate = gate_threshold(len(_COMPARED), self.gate_prob)
        i, j = rows.near([s.last for s in touched], gate, rows.held != 0)
        pairs = [(touched[a], rows.tracks[b]) for a, b in zip(i, j)]
        scored = [k for k, (a, b) in enumerate(pairs) if a is not b and self._reviewed(a, b)]
        d2 = np.full(len(pairs), np.nan)
        d2[scored] = self._distances2([pairs[k][0].last for k in scored], [pairs[k][1].last for k in scored])
        looked: set[tuple[str, str]] = set()
        merged: list[SystemTrack] = []
        changed: set[str] = set()  # merged into in this review: a new estimate, new members
        for (a, b), d in zip(pairs, d2):
            if a is b or not self._reviewed(a, b):
                continue
            key = (a.id, b.id) if self.ids.number(a.id) < self.ids.number(b.id) else (b.id, a.id)
            if key in looked or key[0] not in self.tracks or key[1] not in self.tracks:
                continue
            looked.add(key)
            if np.isnan(d) or a.id in changed or b.id in changed:
                d = self._distances2([a.last], [b.last])[0]
            if not np.isfinite(d):
                self._streak.pop(key, None)
                continue
            n, t = self._streak.get(key, (0, -math.inf))
            now = max(a.last.t, b.last.t)
            self._streak[key] = n, t = (n + 1, now) if now > t else (n, t)
            if n >= self.merge_frames:
                merged.append(self._merge(self.tracks[key[0]], self.tracks[key[1]]))
                changed.add(key[0])
        return merged

    @staticmethod
    def _reviewed(a: SystemTrack, b: SystemTrack) -> bool:
        """Whether step 6 reviews a pair: one of them held by two regions or more, or the
        two held by different regions (two regions' tracks of one aircraft that the join
        missed — one born out of the other's gate — which no region's tracker sees
        together). Two system tracks of one region alone are its tracker's to review."""
        return a.regional() or b.regional() or not a.members.keys() & b.members.keys()

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
        self._rows.remove(gone)
        self._streak = {k: n for k, n in self._streak.items() if gone.id not in k}
        self._fuse([keep])
        return keep

    # -- fusion ----------------------------------------------------------------------------
    def _fuse(self, tracks: Sequence[SystemTrack]) -> None:
        """Each track's members' estimates predicted to the latest of their times and
        fused (its ``last``): CI folded pairwise, most certain first (each step's ω in
        closed form, :func:`_ci_pairs`), the ``k``-th step of every track with more than
        ``k`` members together. A track with one member is that member's estimate. Each
        carries its members' identity and existence (module docstring, step 3)."""
        several = []
        for s in tracks:
            if len(s.members) == 1:
                e = self.latest[next(iter(s.members.values()))]
                s.last = Estimate(e.t, e.x, e.P, self.name, "centre", s.id, existence=e.existence, identity=e.identity)
                self._rows.put(s)
            else:
                several.append(s)
        if not several:
            return
        members = [[self.latest[rid] for rid in s.members.values()] for s in several]
        n = np.array([len(m) for m in members])
        t = np.array([max(e.t for e in m) for m in members])
        flat = [e for m in members for e in m]
        xs, Ps = self._predict(flat, np.repeat(t, n))
        ends = np.cumsum(n)
        # most certain first (by the trace of the position block; ties in order)
        size = np.trace(Ps[:, :3, :3], axis1=-2, axis2=-1)
        order = [e - k + np.argsort(size[e - k:e], kind="stable") for k, e in zip(n, ends)]
        if self.rule == "naive":
            fused = [fuse_naive(list(xs[e - k:e]), list(Ps[e - k:e])) for k, e in zip(n, ends)]
            x, P = np.array([f[0] for f in fused]), np.array([f[1] for f in fused])
        else:  # CI folded pairwise, most certain first
            x, P = xs[[o[0] for o in order]], Ps[[o[0] for o in order]]
            for k in range(1, int(n.max())):
                fold = np.flatnonzero(n > k)
                nxt = [order[i][k] for i in fold]
                x[fold], P[fold] = _ci_pairs(x[fold], P[fold], xs[nxt], Ps[nxt], self.ci_criterion)
        for s, o, tk, xk, Pk in zip(several, order, t, x, P):
            said = [flat[i] for i in o]
            identity = next((e.identity for e in said if e.identity is not None), None)
            existence = max((e.existence for e in said if e.existence is not None), default=None)
            s.last = Estimate(float(tk), xk.copy(), Pk.copy(), self.name, "centre", s.id, existence=existence,
                              identity=identity)
            self._rows.put(s)


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
