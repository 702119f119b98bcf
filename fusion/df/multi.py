r"""Many emitters in a network of DF stations: bearing association, ghost rejection and
localisation of each emitter by a DF method of :mod:`fusion.df.methods`.

A station reports one bearing per emitter it hears, with nothing that says which. Two
stations' bearings always cross, so ``n`` emitters give ``n²`` crossings of which
``n(n − 1)`` are ghosts; a third station tells them apart. Bearings are grouped into
epochs (:class:`fusion.grouping.TimeGrouper`), and per epoch, with ``need = min(3, K)`` of
the ``K`` stations that reported:

1. confirmed tracks take their bearings, station by station, by a χ²(1) gate and GNN on
   ``d² = wrap(β − h(x̂))² / (σ² + J P Jᵀ)``, ``J = [−Δy, Δx]/ρ²``, where the ``(x̂, P)``
   that gates a station leaves that station's bearings out;
2. the other bearings are grouped afresh (:func:`initiate`): each well-conditioned pair
   is a candidate, supported by the best gated bearing of every other station and
   scored by a persistence cost over the last ``init_epochs`` epochs; the groups are
   chosen at once by set packing (:func:`_packing`, ``scipy.optimize.milp``): most
   groups of the most stations, then least total cost;
3. a group continues the tentative track whose gate holds it, else starts one; each
   track is one instance of the wrapped DF method, fed only its own bearings;
4. tracks are managed by :class:`fusion.tracking.table.TrackLogic` (M-of-N, misses,
   ``max_pos_std``), a χ² consistency test over each confirmed track's window, and an
   exchange test that undoes a swap ghost pair;
5. one estimate per confirmed track is reported, ids ``E1, E2, …`` in confirmation order.

Switched on by ``association = "gnn"``; the keys are those of
:class:`fusion.tracking.config.AssociationConfig` and of the wrapped method's
:class:`fusion.df.methods.DFConfig`. docs/algorithms.md ("Many emitters") gives the
reasoning, docs/notes.md what the tests on ``df-multi`` showed.
"""

from __future__ import annotations

import dataclasses
import itertools
from collections import deque
from typing import Callable, NamedTuple, Sequence

import numpy as np
from scipy.optimize import Bounds, LinearConstraint, milp

from ..angles import wrap_pi
from ..tracking.associators import gnn
from ..tracking.config import AssociationConfig
from ..tracking.hypotheses import Hypotheses, gate_threshold
from ..tracking.manager import Frame, MultiTargetTracker, Taken
from ..tracking.table import CONFIRMED, DELETED, Track, TrackLogic
from ..grouping import TimeGrouper
from ..types import Estimate, Measurement
from .init import usable_pairs
from .methods import EMITTER_PREFIX, DFMethod
from .models import bearing, bearing_of
from .triangulation import GeometryError, intersection_jacobian, torrieri

#: false-alarm probability of the consistency test of a confirmed track (step 4). It is
#: run every epoch on every track, so it must be far below the gate's; a track holding a
#: neighbour's bearing 4σ off adds ~16 per epoch and still fails it within its window.
CONSISTENCY_FALSE_ALARM = 1e-5

#: how much lower (χ²) the two tracks' window costs must be with some stations' bearings
#: exchanged for the exchange to be made (step 4): a swap ghost pair's bearings sit ~2σ
#: off each, i.e. tens over a window, a real pair's at the noise
SWAP_MARGIN = 2 * gate_threshold(1, 0.999)
#: a track whose window cost is above this point of its χ² is tried for an exchange
SUSPECT_PROB = 0.99

#: stations whose bearings a new emitter needs (fewer if fewer stations report):
#: with two stations every crossing is a candidate and nothing can tell a ghost.
SUPPORT = 3


def bearing_d2(x, P, sites, betas, sigmas) -> np.ndarray:
    """``d² = wrap(β − h(x))² / (σ² + J P Jᵀ)``, ``J = ∂h/∂x``, of each bearing against the
    estimate ``(x, P)``; χ²(1) when the pair is right. ``(n,)``, ``inf`` where ``x`` is on
    the site.

    ``x`` may also be a stack ``(m, 2)`` with ``P`` ``(m, 2, 2)``: the result is ``(m, n)``.
    """
    x = np.asarray(x, dtype=float)
    sites = np.atleast_2d(np.asarray(sites, dtype=float))[:, :2]
    d = x[..., None, :] - sites                                           # (..., n, 2)
    rho2 = np.sum(d * d, axis=-1)
    with np.errstate(divide="ignore", invalid="ignore"):
        J = np.stack([-d[..., 1], d[..., 0]], axis=-1) / rho2[..., None]
    r = wrap_pi(np.asarray(betas, dtype=float) - bearing(x[..., None, :], sites))
    S = np.asarray(sigmas, dtype=float) ** 2 + np.einsum("...ni,...ij,...nj->...n", J, np.asarray(P, dtype=float), J)
    return np.where(rho2 > 0.0, r * r / S, np.inf)


def _refine(x, sites, betas, sigmas, member) -> tuple[np.ndarray, np.ndarray]:
    """One Torrieri step (:mod:`fusion.df.triangulation`) about each candidate ``x (m, 2)``
    on its member bearings (``member (m, n)`` mask): ``(x̂ (m, 2), P̂ (m, 2, 2))``."""
    d = x[:, None, :] - sites[None, :, :]
    rho2 = np.sum(d * d, axis=-1)
    G = np.stack([-d[..., 1], d[..., 0]], axis=-1) / rho2[..., None]            # ∂h/∂x, (m, n, 2)
    r = wrap_pi(betas[None, :] - bearing(x[:, None, :], sites[None, :, :]))
    w = member / sigmas[None, :] ** 2
    A = np.einsum("mni,mn,mnj->mij", G, w, G)
    P = np.linalg.inv(A)
    return x + np.einsum("mij,mj->mi", P, np.einsum("mni,mn->mi", G, w * r)), P


def initiate(sites, betas, sigmas, stations: Sequence[str], gate: float, need: int, max_rel: float = 1.0,
             window: Sequence[tuple] = ()) -> list[list[int]]:
    """Groups of bearing indices, one per new emitter. Candidates are made from every
    usable pair (:func:`_candidates`), the groups chosen among them by set packing
    (:func:`_packing`); their bearings leave the pool and the pool is searched again
    until no group is left. Every bearing is in at most one group; each group holds at
    most one bearing per station and bearings of at least ``need`` stations.

    Args:
        sites: ``(n, 2)`` station positions; betas: ``(n,)`` math bearings; sigmas:
            ``(n,)`` their std; stations: ``(n,)`` station ids (one bearing per station per
            group); gate: the χ²(1) gate ``G``; need: stations a group needs (≥ 2);
            max_rel: the ``ipu`` conditioning bound of :func:`fusion.df.init.usable_pairs`;
            window: earlier epochs, each ``(sites, betas, sigmas, stations)`` of *all* its
            bearings, for the persistence cost (empty: this epoch's support alone).
    """
    sites = np.atleast_2d(np.asarray(sites, dtype=float))[:, :2]
    betas = np.asarray(betas, dtype=float)
    sigmas = np.broadcast_to(np.asarray(sigmas, dtype=float), betas.shape)
    station = np.unique(np.asarray(stations, dtype=object), return_inverse=True)[1].ravel()
    cells = [(sites, betas, sigmas, np.asarray(stations, dtype=object))]
    cells += [(np.atleast_2d(np.asarray(a, dtype=float))[:, :2], np.asarray(b, dtype=float),
               np.asarray(c, dtype=float), np.asarray(d, dtype=object)) for a, b, c, d in window]
    free = np.ones(len(betas), dtype=bool)
    groups: list[list[int]] = []
    while True:
        member, n_st, cost = _candidates(sites, betas, sigmas, station, free, gate, max_rel, cells)
        chosen = _packing(member, n_st, cost, need)
        if not chosen:
            return groups
        for k in chosen:
            group = [int(b) for b in np.flatnonzero(member[k])]
            free[group] = False
            groups.append(group)


def _candidates(sites, betas, sigmas, station, free, gate, max_rel, cells):
    """Every candidate group of the ``free`` bearings, one per usable pair from two
    stations: the pair's ``ipu`` fix and covariance, the gated bearing of least ``d²`` of
    every other station, one Torrieri step on the group, and its persistence cost (each
    (epoch, station) cell of ``cells`` adds its best ``min(d², gate)``). Returns
    ``(member (m, n) mask, n_st (m,) stations, cost (m,) persistence)``."""
    idx = np.flatnonzero(free)
    i, j, x = usable_pairs(sites[idx], betas[idx], sigmas[idx], max_rel)
    keep = station[idx[i]] != station[idx[j]]  # two stations at one site stay two stations
    i, j, x = idx[i[keep]], idx[j[keep]], x[keep]
    member = np.zeros((len(i), len(betas)), dtype=bool)
    if len(i) == 0:
        return member, np.zeros(0, dtype=int), np.zeros(0)
    m = np.arange(len(i))
    F = intersection_jacobian(sites[i], betas[i], sites[j], betas[j])
    P = np.einsum("mak,mk,mbk->mab", F, np.stack([sigmas[i] ** 2, sigmas[j] ** 2], axis=1), F)
    d2 = bearing_d2(x, P, sites, betas, sigmas)                          # (pairs, bearings)
    d2[:, ~free] = np.inf
    d2[(station[None, :] == station[i][:, None]) | (station[None, :] == station[j][:, None])] = np.inf
    member[m, i] = member[m, j] = True
    for s in np.unique(station):
        cols = np.flatnonzero(station == s)
        best = cols[np.argmin(d2[:, cols], axis=1)]
        member[m, best] |= d2[m, best] <= gate
    # Persistence: the refined candidate against every epoch of the window, each
    # (epoch, station) cell scoring its best bearing's d², capped at the gate.
    xr, Pr = _refine(x, sites, betas, sigmas, member)
    cost = np.zeros(len(i))
    for cs, cb, cg, cst in cells:
        e2 = np.minimum(bearing_d2(xr, Pr, cs, cb, cg), gate)
        for s in np.unique(cst):
            cost += e2[:, cst == s].min(axis=1)
    return member, member.sum(axis=1), cost


def _packing(member, n_st, cost, need) -> list[int]:
    """The candidates (rows of ``member``) to make groups of, in the order most stations,
    least cost: disjoint, each with at least ``need`` stations; as many groups of the
    most stations as can be, then of one station fewer, ...; among such sets, the one of
    least total persistence cost. Chosen for the whole pool at once, as an integer
    program: a 4-station ghost picked first could take the bearings of two emitters."""
    ok = np.flatnonzero(n_st >= need)
    if len(ok) == 0:
        return []
    # One candidate per distinct group (pairs of one group's bearings give it again).
    order = ok[np.lexsort((cost[ok],))]
    _, first = np.unique(member[order], axis=0, return_index=True)
    cand = order[np.sort(first)]
    A = member[cand].T.astype(float)                 # (bearings, candidates): each bearing once
    if np.all(A.sum(axis=1) <= 1):                   # no two candidates share a bearing
        chosen = cand
    else:
        constraints = [LinearConstraint(A, -np.inf, 1.0)]
        n = n_st[cand]
        for level in range(int(n.max()), need - 1, -1):
            at = (n == level).astype(float)
            if not at.any():
                continue
            most = _solve(-at, constraints)
            constraints.append(LinearConstraint(at[None, :], -most.fun - 0.5, np.inf))
        chosen = cand[_solve(cost[cand], constraints).x > 0.5]
    return [int(k) for k in chosen[np.lexsort((cost[chosen], -n_st[chosen]))]]


def _solve(c, constraints):
    """``min c·z`` over binary ``z`` under ``constraints`` (HiGHS, solved exactly)."""
    res = milp(c, integrality=np.ones(len(c)), bounds=Bounds(0, 1), constraints=constraints,
               options={"mip_rel_gap": 0.0})
    if res.x is None:
        raise RuntimeError(f"bearing grouping: {res.message}")
    return res


class Bearings(NamedTuple):
    """Bearings of one epoch, or a track's share of one, decoded once: row ``i`` of each
    array is bearing ``i``."""

    sites: np.ndarray            # (n, 2) station positions
    betas: np.ndarray            # (n,) math bearings
    sigmas: np.ndarray           # (n,) their std
    stations: list[str]          # (n,) station ids
    measurements: list[Measurement]
    t0: float                    # the epoch's start

    def subset(self, idx) -> "Bearings":
        """The bearings ``idx`` (indices, in order)."""
        idx = list(idx)
        return Bearings(self.sites[idx], self.betas[idx], self.sigmas[idx], [self.stations[i] for i in idx],
                        [self.measurements[i] for i in idx], self.t0)


class _Emitter(Track):
    """One emitter track: its DF method instance (``filter``), its life, its latest
    estimate, and the bearings it took in its last ``window`` epochs."""

    __slots__ = ("nis", "taken")

    def __init__(self, method: DFMethod, last: Estimate, window: int, logic: TrackLogic | None = None):
        super().__init__(method, last, logic)
        self.nis: deque = deque(maxlen=window)  # (Σ d², number of bearings) of its last epochs as confirmed
        self.taken: deque[Bearings] = deque(maxlen=window)  # its bearings of each epoch

    @property
    def method(self) -> DFMethod:
        return self.filter

    @method.setter
    def method(self, method: DFMethod) -> None:
        self.filter = method

    def without(self, station: str) -> tuple[np.ndarray, np.ndarray]:
        """``(x, P)`` to gate ``station``'s bearings with: one Torrieri step from the
        estimate on the track's bearings of its last epochs from the *other* stations, or
        the estimate itself if they come from fewer than two stations. Gating a station
        with an estimate its own bearings pulled would let a track keep a neighbour's
        bearing of that station for good."""
        sites, betas, sigmas, stations = _stacked(self.taken)
        keep = stations != station
        if len(set(stations[keep])) < 2:
            return self.last.x, self.last.P
        x, P = _refine(np.asarray(self.last.x, dtype=float)[None, :2], sites[keep], betas[keep], sigmas[keep],
                       np.ones((1, int(keep.sum())), dtype=bool))
        return x[0], P[0]


class MultiEmitterMethod:
    """A streaming method (``process``/``advance``/``finish``) that tracks many emitters
    (module docstring): a :class:`~fusion.tracking.manager.MultiTargetTracker` whose
    plots are the epoch's bearings (by their index in it), each track localised by its
    own instance of the wrapped DF method.

    The tracker's parts are this object's methods: :meth:`predict`, :meth:`scans`,
    :meth:`hypothesise`, :meth:`condition`, :meth:`unclaimed` (steps 1 and 2's
    hypotheses: confirmed tracks, station by station), :meth:`initiate` (2, 3),
    :meth:`update`, :meth:`position_cov`, :meth:`start` and :meth:`review` (4).

    Args:
        name: the wrapped DF method's name (the estimates carry it).
        make_emitter: builds a fresh instance of that method (one per emitter track).
        config: the association keys.
    """

    def __init__(self, name: str, make_emitter: Callable[[], DFMethod], config: AssociationConfig):
        proto = make_emitter()
        if config.local_max_pos_std is not None or config.merge_frames != AssociationConfig.merge_frames:
            raise ValueError(f"{name}: 'merge_frames' and 'local_max_pos_std' apply to 3D tracks, not to emitters")
        self.name = name
        self.config = config
        self.df = proto.config
        self._make_emitter = make_emitter
        self._gate = gate_threshold(1, config.gate_prob)
        self._grouper = TimeGrouper(self.df.pair_tol)
        self._window: deque = deque(maxlen=int(self.df.init_epochs) - 1)  # earlier epochs, newest first
        self.tracker = MultiTargetTracker(self, config.associator(confirmed_first=True), self, self,
                                          config.table(prefix=EMITTER_PREFIX), self)
        self._epoch = Bearings(np.zeros((0, 2)), np.zeros(0), np.zeros(0), [], [], 0.0)  # the frame's bearings

    @classmethod
    def from_table(cls, name: str, make: Callable[[dict], DFMethod], table: dict) -> "MultiEmitterMethod":
        """DF method ``name`` (``make(table)`` builds one instance) for many emitters,
        from a resolved ``[tracker]`` table with ``association``."""
        association, rest = AssociationConfig.split(table)
        if association is None:
            raise ValueError(f"{name}: many emitters need 'association' in the tracker table")
        if rest.get("motion", "static") != "static":
            raise ValueError(f"association with motion = {rest['motion']!r}: many emitters are tracked as static "
                             "ones (the bearing association gates on their latest positions)")
        return cls(name, lambda: make(dict(rest)), association)

    @property
    def table(self):
        return self.tracker.table

    @property
    def tracks(self) -> list[_Emitter]:
        """The emitter tracks, in priority order."""
        return self.tracker.tracks

    def __repr__(self) -> str:
        return f"MultiEmitterMethod({self.name!r})"

    # Streaming interface -------------------------------------------------------------
    def process(self, m: Measurement) -> list[Estimate]:
        if not np.isfinite(m.t):
            raise ValueError(f"{self.name}: measurement from {m.sensor!r} has non-finite time {m.t}")
        bearing_of(m)  # a bad message fails at its arrival
        return self._run(self._grouper.push(m))

    def advance(self, t: float) -> list[Estimate]:
        if not np.isfinite(t):
            raise ValueError(f"{self.name}: watermark must be finite, got {t}")
        return self._run(self._grouper.advance(t))

    def finish(self) -> list[Estimate]:
        return self._run(self._grouper.finish())

    def _run(self, epochs: list[list[Measurement]]) -> list[Estimate]:
        out = []
        for epoch in epochs:
            t = max(m.t for m in epoch)
            self._epoch = self._bearings(epoch, epoch[0].t)  # decoded once; tracks take subsets of it
            out += [dataclasses.replace(tr.last, t=t, track=tr.id, node="centre") for tr in self.tracker.frame(epoch)]
        return out

    def _bearings(self, ms: list[Measurement], t0: float) -> Bearings:
        """The bearing measurements ``ms`` of the epoch starting at ``t0``, decoded."""
        pairs = [bearing_of(m) for m in ms]
        return Bearings(np.array([p[0][:2] for p in pairs]).reshape(-1, 2), np.array([p[1] for p in pairs]),
                        np.array([self.df.sigma_of(m) for m in ms]), [m.sensor for m in ms], list(ms), t0)

    # Steps 1–2: hypotheses of the confirmed tracks, station by station --------------------
    @staticmethod
    def predict(tracks: list[_Emitter], frame: Frame) -> list[int]:
        """The confirmed tracks (their places): the rows of every station's hypotheses."""
        return [i for i, tr in enumerate(tracks) if tr.confirmed]

    def scans(self, frame: Frame) -> list[list[int]]:
        """The epoch's bearings (their indices) by station, stations in name order."""
        stations = self._epoch.stations
        return [[c for c, sid in enumerate(stations) if sid == s] for s in sorted(set(stations))]

    def hypothesise(self, rows: list[int], tracks: list[_Emitter], scan: list[int]) -> Hypotheses:
        """A station's bearings against the confirmed tracks, each gated with the
        estimate that leaves that station out (:meth:`_Emitter.without`)."""
        e = self._epoch
        s = e.stations[scan[0]]
        d2 = np.array([bearing_d2(*tracks[i].without(s), e.sites[scan], e.betas[scan], e.sigmas[scan])
                       for i in rows]).reshape(len(rows), len(scan))
        return Hypotheses(scan, rows, d2, np.full(len(rows), self._gate), np.ones(len(rows), dtype=bool))

    @staticmethod
    def condition(rows, hyp: Hypotheses, association) -> None:
        """No sequential gating: each station is gated on its own estimate anyway."""

    @staticmethod
    def unclaimed(hyp: Hypotheses, columns) -> list[int]:
        return [hyp.plots[c] for c in columns]

    # Steps 2–3: new groups, and the tentative tracks they continue ---------------------------
    def initiate(self, left: list[int], tracks: list[_Emitter], frame: Frame) -> tuple[dict[int, list[Taken]], list]:
        """The bearings no confirmed track took, grouped afresh (with the window's
        persistence cost); a group continues the tentative track whose gate holds all
        its bearings (GNN on their mean ``d²``), else starts one."""
        e = self._epoch
        idx = np.array(sorted(left), dtype=int)
        need = min(SUPPORT, frame.sensors)
        groups = [[int(idx[c]) for c in g] for g in initiate(
            e.sites[idx], e.betas[idx], e.sigmas[idx], [e.stations[c] for c in idx], self._gate, need,
            self.df.ipu_max_rel, self._window)]
        self._window.appendleft((e.sites, e.betas, e.sigmas, e.stations))
        tentative = [i for i, tr in enumerate(tracks) if not tr.confirmed]
        cost = np.full((len(tentative), len(groups)), np.inf)
        for r, i in enumerate(tentative):
            for c, g in enumerate(groups):
                d2 = bearing_d2(tracks[i].last.x, tracks[i].last.P, e.sites[g], e.betas[g], e.sigmas[g])
                if np.all(d2 <= self._gate):
                    cost[r, c] = float(np.mean(d2))
        continued = dict(gnn(cost, self._gate))
        return ({tentative[r]: [Taken(tuple(groups[c]), (cost[r, c],))] for r, c in continued.items()},
                [g for c, g in enumerate(groups) if c not in continued.values()])

    # Step 4: updates and management ----------------------------------------------------
    def update(self, tr: _Emitter, taken: list[Taken], frame: Frame) -> bool:
        """A confirmed track localised on the bearings it took (in epoch order), a
        tentative one on the group it continues; a hit with bearings of 2 stations
        (confirmed) or of the ``need`` a new track needs (tentative)."""
        mine = [i for tk in taken for i in tk.plots]
        if tr.confirmed:
            bearings, enough = self._epoch.subset(sorted(mine)), 2
            tr.nis.append((sum((d for tk in taken for d in tk.d2), 0.0), len(mine)))
        else:
            bearings, enough = self._epoch.subset(mine), min(SUPPORT, frame.sensors)
        self._update(tr, bearings, enough)
        return len(set(bearings.stations)) >= enough

    def _update(self, tr: _Emitter, mine: Bearings, enough: int) -> None:
        """Track ``tr`` with its bearings ``mine`` of the epoch: localise, and keep them
        in its window."""
        if mine.measurements:
            est = self._localise(tr.method, mine.measurements, mine.t0)
            if est is not None:
                tr.last = est
        tr.taken.append(mine)

    @staticmethod
    def position_cov(tr: _Emitter) -> np.ndarray:
        return tr.last.P

    def start(self, group: list[int], frame: Frame) -> _Emitter | None:
        """A tentative track from one initiation group (bearing indices), if its method
        gives a fix on it."""
        mine = self._epoch.subset(group)
        method = self._make_emitter()
        est = self._localise(method, mine.measurements, mine.t0)
        if est is None:
            return None
        tr = _Emitter(method, est, int(self.df.init_epochs))
        tr.taken.append(mine)
        return tr

    def review(self, tracks: list[_Emitter]) -> None:
        """The tracks confirmed before this epoch (they have ids): the consistency test
        of each, then the exchange test of the pairs still confirmed."""
        confirmed = [tr for tr in tracks if tr.id is not None]
        for tr in confirmed:
            self._check_consistency(tr)
        self._resolve_swaps([tr for tr in confirmed if tr.logic.status == CONFIRMED])

    def _resolve_swaps(self, tracks: list[_Emitter]) -> None:
        """Exchange some stations' bearings between two confirmed tracks when that fits
        their last ``init_epochs`` epochs of bearings better by more than
        :data:`SWAP_MARGIN`: a swap ghost pair becomes the two emitters it was made of. Each track is
        judged by the χ² cost of the static least-squares fix (Torrieri) of its window;
        only pairs with a track above the :data:`SUSPECT_PROB` point of its χ² are tried
        (one ghost of a swap pair may fit well; the other does not)."""
        full = [tr for tr in tracks if len(tr.taken) == tr.taken.maxlen]
        cost = {id(tr): _fit_cost(tr.taken, tr.last.x) for tr in full}
        suspect = {id(tr) for tr in full if cost[id(tr)] is not None and cost[id(tr)][0] > cost[id(tr)][1]}
        for a, b in itertools.combinations(full, 2):
            if not ({id(a), id(b)} & suspect) or cost[id(a)] is None or cost[id(b)] is None \
                    or [e.t0 for e in a.taken] != [e.t0 for e in b.taken]:
                continue
            shared = sorted({st for e in a.taken for st in e.stations} & {st for e in b.taken for st in e.stations})
            base = cost[id(a)][0] + cost[id(b)][0]
            best = None
            for k in range(1, len(shared)):
                for group in itertools.combinations(shared, k):
                    if shared[0] in group:  # a group and its complement are one exchange
                        continue
                    a2, b2 = _exchange(a.taken, b.taken, set(group))
                    ca, cb = _fit_cost(a2), _fit_cost(b2)
                    if ca is None or cb is None:
                        continue
                    if ca[0] + cb[0] < base - SWAP_MARGIN and (best is None or ca[0] + cb[0] < best[0]):
                        best = (ca[0] + cb[0], a2, b2)
            if best is not None:
                for tr, window in ((a, best[1]), (b, best[2])):
                    self._rebuild(tr, window)
                    cost[id(tr)] = _fit_cost(tr.taken, tr.last.x)
                suspect -= {id(a), id(b)}

    def _rebuild(self, tr: _Emitter, window: list[Bearings]) -> None:
        """Track ``tr`` (its id and life kept) restarted from the bearings ``window``."""
        tr.method = self._make_emitter()
        tr.taken.clear()
        tr.nis.clear()
        for epoch in window:
            est = self._localise(tr.method, epoch.measurements, epoch.t0) if epoch.measurements else None
            if est is not None:
                tr.last = est
            tr.taken.append(epoch)

    def _check_consistency(self, tr: _Emitter) -> None:
        """Delete a confirmed track whose bearings of the last ``init_epochs`` epochs are,
        together, beyond the χ² point at :data:`CONSISTENCY_FALSE_ALARM`."""
        if tr.logic.status == DELETED:
            return
        total, n = (sum(v) for v in zip(*tr.nis))
        if n and total > gate_threshold(int(n), 1.0 - CONSISTENCY_FALSE_ALARM):
            tr.logic.status = DELETED

    def _localise(self, method: DFMethod, bearings: list[Measurement], t0: float) -> Estimate | None:
        """One epoch of the track's own DF method on its bearings (in stream order); the
        watermark at the epoch's end closes it. None while the method has no fix."""
        out = [e for m in bearings for e in method.process(m)]
        out += method.advance(t0 + self.df.pair_tol)
        return out[-1] if out else None


def _stacked(window: Sequence[Bearings]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The bearings of ``window`` (a track's epochs) as one set:
    ``(sites (n, 2), betas (n,), sigmas (n,), stations (n,))``, in epoch order."""
    if not window:
        return np.zeros((0, 2)), np.zeros(0), np.zeros(0), np.array([], dtype=object)
    return (np.concatenate([e.sites for e in window]), np.concatenate([e.betas for e in window]),
            np.concatenate([e.sigmas for e in window]),
            np.array([st for e in window for st in e.stations], dtype=object))


def _fit_cost(window: Sequence[Bearings], x0=None) -> tuple[float, float] | None:
    """``(χ² cost, its SUSPECT_PROB point)`` of the static least-squares fix of the
    bearings of ``window`` (a track's epochs), or None without two
    stations: three Gauss–Newton steps (Torrieri) from ``x0`` or the bearings' mean
    pairwise intersection, enough to tell a ghost's tens from the noise."""
    sites, betas, sigmas, stations = _stacked(window)
    if len(set(stations)) < 2:
        return None
    try:
        fix = torrieri(sites, betas, sigmas, x0=x0, iterations=3)
    except (GeometryError, np.linalg.LinAlgError, ValueError):
        return None
    return fix.chi2, _suspect_level(len(betas) - 2)


def _suspect_level(dof: int) -> float:
    return gate_threshold(dof, SUSPECT_PROB)


def _exchange(a: Sequence[Bearings], b: Sequence[Bearings], stations: set) -> tuple[list[Bearings], list[Bearings]]:
    """The windows of two tracks with their bearings of ``stations`` exchanged, epoch
    by epoch (the epochs of both windows are the same)."""
    out_a, out_b = [], []
    for ea, eb in zip(a, b):
        out_a.append(_merged(ea, eb, stations))
        out_b.append(_merged(eb, ea, stations))
    return out_a, out_b


def _merged(mine: Bearings, other: Bearings, stations: set) -> Bearings:
    """``mine``'s bearings of the stations not in ``stations`` and ``other``'s of those,
    in stream order."""
    rows = [(mine, i) for i, st in enumerate(mine.stations) if st not in stations]
    rows += [(other, i) for i, st in enumerate(other.stations) if st in stations]
    rows.sort(key=lambda r: r[0].measurements[r[1]].order_key)
    return Bearings(np.array([e.sites[i] for e, i in rows]).reshape(-1, 2), np.array([e.betas[i] for e, i in rows]),
                    np.array([e.sigmas[i] for e, i in rows]), [e.stations[i] for e, i in rows],
                    [e.measurements[i] for e, i in rows], mine.t0)
