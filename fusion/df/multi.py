r"""Many emitters in a network of DF stations: bearing association, ghost rejection and
localisation of each emitter with a thesis method.

Switched on, as for the 3D methods, by ``association = "gnn"`` in the scenario's
``[tracker]`` table: :func:`fusion.methods.make_method` then wraps the named DF method
(``EKF``, ``IMM``, ``TORRIERI``, ...) in :class:`MultiEmitterMethod`, and every emitter
track is one instance of that method, fed only the bearings assigned to it. The
estimates keep the method's name and carry the track ids ``E1, E2, …``.

The problem
-----------
A station hears every emitter and reports one bearing per emitter, with nothing that
says which. Two bearings from two stations always meet, so ``n`` emitters seen by two
stations give ``n²`` intersections of which ``n(n − 1)`` are *ghosts* — points where
no emitter is. A third station decides between them: a real emitter lies on one of its
bearings too, a ghost (the crossing of two bearings of two different emitters) in
general does not.

Epochs
------
Bearings are grouped into epochs as the 3D trackers group plots into frames
(:class:`fusion.mtt.FrameGrouper`: times within ``pair_tol`` of the epoch's first
bearing; closed by a later bearing, a watermark past it, or ``finish``), so the output
depends on the bearings alone. One epoch, with ``K`` the number of stations that
reported in it and ``need = min(3, K)``:

1. **Confirmed tracks take their bearings**, station by station. A track with estimate
   ``(x̂, P)`` and a bearing ``β`` of a station at ``s`` with std ``σ``::

       r = wrap(β − h(x̂)),  h(x) = atan2(y − s_y, x − s_x),   J = ∂h/∂x(x̂) = [−Δy, Δx]/ρ²
       d² = r² / (σ² + J P Jᵀ)                                  ~ χ²(1) if the pair is right

   and the gate is ``d² ≤ G = χ²⁻¹(P_G; 1)``. Within one station each track takes at
   most one bearing and each bearing goes to at most one track: global nearest
   neighbour on the ``d²`` (:func:`fusion.association.gnn`). The ``(x̂, P)`` that gates
   station ``s`` *leaves s out*: one Torrieri step from the track's estimate on the
   bearings it took from the other stations in its last ``init_epochs`` epochs (its
   estimate itself if those come from fewer than two stations). With its own estimate,
   two tracks whose emitters one station sees 4σ apart could hold each other's bearing
   of that station for good: each estimate, pulled ~1 km towards the wrong bearing,
   then prefers it.
2. **The other bearings are grouped afresh** (:func:`initiate`): every pair of them from
   two stations that meets in a well-conditioned point (:func:`fusion.df.init.usable_pairs`,
   the ``ipu`` test with ``ipu_max_rel``) is a candidate ``x_ab`` with covariance
   ``P_ab = F diag(σ_a², σ_b²) Fᵀ``. Each other station supports it with its free
   bearing of least ``d²`` against ``(x_ab, P_ab)``, if inside the gate. The candidate
   is refined by one Torrieri step on its group (``x̂, P̂``) and given a *persistence
   cost*: over this epoch and the ``init_epochs − 1`` before it, every (epoch, station)
   cell adds the least ``min(d², G)`` of its bearings against ``(x̂, P̂)``. The candidate
   with the most supporting stations (``n_st``; ties: least persistence cost) becomes a
   group if ``n_st ≥ need``, its bearings leave the pool, and the pool is searched again.
   Ghost rejection is in three parts: a real emitter has the support of every station
   that heard it, a ghost only of the two that made it plus chance passers-by; once the
   real emitters have taken their bearings, a ghost has lost the bearings it was made
   of; and a static ghost's misfit is a fixed bias, so its persistence cost grows with
   every epoch while a real emitter's stays at the noise (≈ 1 per cell).
3. **Localise**: a group continues the tentative track whose gate holds all its
   bearings (GNN on the mean ``d²``), else starts a tentative track; each track's
   bearings (in stream order) are one epoch of its own DF method (:mod:`fusion.df.methods`:
   ``ipu`` start and EKF/IMM/MEKF updates, or Torrieri's least squares on all its
   bearings so far); a track without bearings keeps its estimate.
4. **Manage** (:class:`fusion.association.TrackLogic`): a tentative track scores a hit
   when it continues with bearings of ``need`` stations, a confirmed one when it took
   bearings of two stations (a fix); M-of-N confirmation (``confirm_m``, ``confirm_n``),
   deletion after ``delete_misses`` missed epochs, when ``√trace P`` exceeds
   ``max_pos_std``, or when the ``d²`` of a confirmed track's bearings over its last
   ``init_epochs`` epochs sum beyond ``χ²⁻¹(1 − 10⁻⁵; n)`` (``n`` bearings;
   :data:`CONSISTENCY_FALSE_ALARM`): a track that holds
   one station's bearing of a neighbouring emitter fits each bearing within the gate
   but not all of them together, over time.
5. **Report** one estimate per confirmed track, in id order, stamped with the epoch's
   time; ids ``E1, E2, …`` in order of confirmation, never reused
   (:class:`fusion.association.TrackIds`).

What it does not do: it does not resolve two emitters that every station sees within
its bearing noise of each other (they form one track), and it does not always reject
a *swap ghost pair*: when two emitters lie near the line through two stations (in
``df-multi``, E1 and E5 near the df1–df3 diagonal), two ghosts — each taking those two
stations' bearings of one emitter and the other stations' bearings of the other —
explain every bearing of the pair within ~2σ. If they are started before the real
emitters' tracks, they hold those bearings until the consistency test (step 4) sees
their residuals; in 50 runs of ``df-multi`` that took 23 and 32 epochs in two runs
(``docs/results/df-multi.md``). A global multi-epoch assignment (S-D assignment over
the stations) would weigh both hypotheses at once; this tracker is greedy.

Configuration: the keys of :class:`fusion.mtt.AssociationConfig` (``association``,
``gate_prob``, ``confirm_m``, ``confirm_n``, ``delete_misses``, ``max_pos_std``) and
those of the wrapped DF method (:class:`fusion.df.methods.DFConfig`; ``sigma`` is also
the σ of the gates, ``pair_tol`` the epoch, ``ipu_max_rel`` the candidates' test).
"""

from __future__ import annotations

import dataclasses
import math
from collections import deque
from typing import Callable, Sequence

import numpy as np

from ..angles import wrap_pi
from ..association import CONFIRMED, DELETED, TrackIds, TrackLogic, gate_threshold, gnn
from ..mtt import AssociationConfig, FrameGrouper
from ..types import Estimate, Measurement
from .init import usable_pairs
from .methods import DFMethod
from .models import bearing, bearing_of, stated_sigma
from .triangulation import intersection_jacobian

#: false-alarm probability of the consistency test of a confirmed track (step 4). It is
#: run every epoch on every track: at the gate's 1e-3 true tracks were deleted about
#: once per thousand epochs (df-multi, EKF, runs 0–49: 55 breaks, one emitter of run 40
#: lost two epochs before the end; at 1e-5: 1 break). A track holding a neighbour's
#: bearing 4σ off adds ~16 per epoch and still fails it within its window.
CONSISTENCY_FALSE_ALARM = 1e-5

#: stations whose bearings a new emitter needs (fewer if fewer stations report):
#: with two stations every crossing is a candidate and nothing can tell a ghost.
SUPPORT = 3


def bearing_d2(x, P, sites, betas, sigmas) -> np.ndarray:
    """``d² = wrap(β − h(x))² / (σ² + J P Jᵀ)`` of each bearing against the estimate
    ``(x, P)`` (module docstring); ``(n,)``, ``inf`` where ``x`` is on the site.

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
    """Groups of bearing indices, one per new emitter, chosen greedily (module docstring,
    step 3). Every bearing is in at most one group; each group holds at most one bearing
    per station and bearings of at least ``need`` stations.

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
        idx = np.flatnonzero(free)
        i, j, x = usable_pairs(sites[idx], betas[idx], sigmas[idx], max_rel)
        keep = station[idx[i]] != station[idx[j]]  # two stations at one site stay two stations
        i, j, x = idx[i[keep]], idx[j[keep]], x[keep]
        if len(i) == 0:
            return groups
        m = np.arange(len(i))
        F = intersection_jacobian(sites[i], betas[i], sites[j], betas[j])
        P = np.einsum("mak,mk,mbk->mab", F, np.stack([sigmas[i] ** 2, sigmas[j] ** 2], axis=1), F)
        d2 = bearing_d2(x, P, sites, betas, sigmas)                          # (pairs, bearings)
        d2[:, ~free] = np.inf
        d2[(station[None, :] == station[i][:, None]) | (station[None, :] == station[j][:, None])] = np.inf
        member = np.zeros(d2.shape, dtype=bool)
        member[m, i] = member[m, j] = True
        for s in np.unique(station):
            cols = np.flatnonzero(station == s)
            best = cols[np.argmin(d2[:, cols], axis=1)]
            member[m, best] |= d2[m, best] <= gate
        n_st = member.sum(axis=1)
        # Persistence: the refined candidate against every epoch of the window, each
        # (epoch, station) cell scoring its best bearing's d², capped at the gate.
        xr, Pr = _refine(x, sites, betas, sigmas, member)
        cost = np.zeros(len(i))
        for cs, cb, cg, cst in cells:
            e2 = np.minimum(bearing_d2(xr, Pr, cs, cb, cg), gate)
            for s in np.unique(cst):
                cost += e2[:, cst == s].min(axis=1)
        k = int(np.lexsort((cost, -n_st))[0])
        if n_st[k] < need:
            return groups
        group = [int(b) for b in np.flatnonzero(member[k])]
        free[group] = False
        groups.append(group)


class _Emitter:
    """One emitter track: its DF method instance, its life, its latest estimate, and the
    bearings it took in its last ``window`` epochs."""

    __slots__ = ("method", "logic", "birth", "last", "id", "nis", "taken")

    def __init__(self, method: DFMethod, logic: TrackLogic, birth: int, last: Estimate, window: int):
        self.method, self.logic, self.birth, self.last = method, logic, birth, last
        self.id: str | None = None  # issued at confirmation
        self.nis: deque = deque(maxlen=window)  # (Σ d², number of bearings) of its last epochs as confirmed
        self.taken: deque = deque(maxlen=window)  # per epoch: (sites, betas, sigmas, stations) it took

    def without(self, station: str) -> tuple[np.ndarray, np.ndarray]:
        """``(x, P)`` to gate ``station``'s bearings with: one Torrieri step from the
        estimate on the track's bearings of its last epochs from the *other* stations
        (module docstring, step 1), or the estimate itself if they are fewer than two
        stations."""
        rows = [(site, b, sg, st) for sites, betas, sigmas, stations in self.taken
                for site, b, sg, st in zip(sites, betas, sigmas, stations) if st != station]
        if len({r[3] for r in rows}) < 2:
            return self.last.x, self.last.P
        sites = np.array([r[0] for r in rows])
        x, P = _refine(np.asarray(self.last.x, dtype=float)[None, :2], sites, np.array([r[1] for r in rows]),
                       np.array([r[2] for r in rows]), np.ones((1, len(rows)), dtype=bool))
        return x[0], P[0]


class MultiEmitterMethod:
    """Bearing association, ghost rejection and track management around a DF method
    (module docstring).

    Args:
        name: the wrapped DF method's name (the estimates carry it).
        make_emitter: builds a fresh instance of that method (one per emitter track).
        config: the association keys.
    """

    def __init__(self, name: str, make_emitter: Callable[[], DFMethod], config: AssociationConfig):
        proto = make_emitter()
        if not isinstance(proto, DFMethod):
            raise ValueError(f"MultiEmitterMethod needs a DF method, got {name}")
        self.name = name
        self.config = config
        self.df = proto.config
        self._make_emitter = make_emitter
        self._rule = config.rule()
        self._gate = gate_threshold(1, config.gate_prob)
        self._grouper = FrameGrouper(self.df.pair_tol)
        self._ids = TrackIds(prefix="E")
        self._births = 0
        self._window: deque = deque(maxlen=int(self.df.init_epochs) - 1)  # earlier epochs, newest first
        self.tracks: list[_Emitter] = []  # confirmed in id order, then tentative in birth order

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
        return [e for epoch in epochs for e in self._epoch(epoch)]

    # One epoch -----------------------------------------------------------------------
    def _sigma(self, m: Measurement) -> float:
        return stated_sigma(m) if self.df.sigma == "sensor" else float(self.df.sigma)

    def _bearings(self, ms: list[Measurement]) -> tuple:
        """``(sites (n, 2), betas (n,), sigmas (n,), stations)`` of bearing measurements."""
        pairs = [bearing_of(m) for m in ms]
        return (np.array([p[0][:2] for p in pairs]).reshape(-1, 2), np.array([p[1] for p in pairs]),
                np.array([self._sigma(m) for m in ms]), [m.sensor for m in ms])

    def _epoch(self, epoch: list[Measurement]) -> list[Estimate]:
        t = max(m.t for m in epoch)
        sites = np.array([bearing_of(m)[0] for m in epoch])
        betas = np.array([bearing_of(m)[1] for m in epoch])
        sigmas = np.array([self._sigma(m) for m in epoch])
        stations = [m.sensor for m in epoch]
        need = min(SUPPORT, len(set(stations)))

        confirmed = [tr for tr in self.tracks if tr.logic.status == CONFIRMED]
        tentative = [tr for tr in self.tracks if tr.logic.status != CONFIRMED]

        # 1. Confirmed tracks take their bearings, station by station.
        taken: dict[int, list[int]] = {}  # confirmed track index -> its bearings
        nis = np.zeros(len(confirmed))     # and the sum of their d²
        free = np.ones(len(epoch), dtype=bool)
        for s in sorted(set(stations)) if confirmed else ():
            cols = [c for c, sid in enumerate(stations) if sid == s]
            d2 = np.array([bearing_d2(*tr.without(s), sites[cols], betas[cols], sigmas[cols]) for tr in confirmed])
            for r, c in gnn(d2, self._gate):
                taken.setdefault(r, []).append(cols[c])
                free[cols[c]] = False
                nis[r] += d2[r, c]

        # 2. The rest is grouped afresh (with the window's persistence cost); a group
        #    continues the tentative track whose gate holds all its bearings, else starts one.
        idx = np.flatnonzero(free)
        groups = [[int(idx[c]) for c in g] for g in initiate(
            sites[idx], betas[idx], sigmas[idx], [stations[c] for c in idx], self._gate, need, self.df.ipu_max_rel,
            self._window)]
        self._window.appendleft((sites, betas, sigmas, stations))
        cost = np.full((len(tentative), len(groups)), np.inf)
        for r, tr in enumerate(tentative):
            for c, g in enumerate(groups):
                d2 = bearing_d2(tr.last.x, tr.last.P, sites[g], betas[g], sigmas[g])
                if np.all(d2 <= self._gate):
                    cost[r, c] = float(np.mean(d2))
        continued = dict(gnn(cost, self._gate))

        for k, tr in enumerate(confirmed):
            self._update(tr, epoch, sorted(taken.get(k, ())), 2)
            tr.nis.append((nis[k], len(taken.get(k, ()))))
            self._check_consistency(tr)
        for r, tr in enumerate(tentative):
            self._update(tr, epoch, groups[continued[r]] if r in continued else [], need)
        for c, g in enumerate(groups):
            if c not in continued.values():
                self._start([epoch[i] for i in g], epoch[0].t)

        for tr in self.tracks:
            if tr.logic.status == CONFIRMED and tr.id is None:
                tr.id = self._ids.next()
        live = [tr for tr in self.tracks if tr.logic.status != DELETED]
        confirmed = sorted((tr for tr in live if tr.logic.status == CONFIRMED), key=lambda tr: int(tr.id[1:]))
        self.tracks = confirmed + sorted((tr for tr in live if tr.logic.status != CONFIRMED), key=lambda tr: tr.birth)
        return [dataclasses.replace(tr.last, t=t, track=tr.id, node="centre") for tr in confirmed]

    def _update(self, tr: _Emitter, epoch: list[Measurement], mine: list[int], enough: int) -> None:
        """Track ``tr`` with its bearings ``mine`` of the epoch: localise, then a hit if
        they come from ``enough`` stations (module docstring, step 4)."""
        if mine:
            est = self._localise(tr.method, [epoch[c] for c in mine], epoch[0].t)
            if est is not None:
                tr.last = est
        tr.taken.append(self._bearings([epoch[c] for c in mine]))
        tr.logic.record(len({epoch[c].sensor for c in mine}) >= enough)
        if tr.logic.status != DELETED and math.sqrt(float(np.trace(tr.last.P))) > self.config.max_pos_std:
            tr.logic.status = DELETED

    def _check_consistency(self, tr: _Emitter) -> None:
        """Delete a confirmed track whose bearings of the last ``init_epochs`` epochs are,
        together, outside the χ² gate (module docstring, step 4)."""
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

    def _start(self, bearings: list[Measurement], t0: float) -> None:
        """A tentative track from one initiation group, if its method gives a fix on it."""
        method = self._make_emitter()
        est = self._localise(method, bearings, t0)
        if est is None:
            return
        self._births += 1
        tr = _Emitter(method, TrackLogic(self._rule), self._births, est, int(self.df.init_epochs))
        tr.taken.append(self._bearings(bearings))
        self.tracks.append(tr)
