r"""One many-target tracker over injected parts.

:class:`MultiTargetTracker` runs one *frame* (the plots within ``pair_tol`` of its first
one) at a time:

0. **expire** the tracks more than ``max_gap_s`` old (:mod:`fusion.guards`);
1. **associate** scan by scan (a scan: one sensor's plots): the hypothesiser gives the
   scan's gated costs against every track, the associator decides who took what, and
   the hypothesiser conditions the tracks' gating states on it before the next scan
   (sequential gating);
2. **initiate**: the initiator groups the plots no track took into new tracks (and
   may hand a group to a tentative track instead); with an associator that says how
   likely some track made each plot (JIPDA's ``claimed``), every plot claimed under
   :data:`CLAIMED_MAX`;
3. **update** each track with what it took, or coast it; record the frame's hit or
   miss in its logic (with JIPDA the logic's existence: it survives to the frame before
   step 1, and takes each scan's ``r⁺`` from the associator);
4. **review** the table (duplicates; a configuration's own checks);
5. **start** the new tracks (with an associator that keeps existence, JIPDA's ``born``:
   a new track's existence is ``existence_birth · ∏ (1 − claimedⱼ)`` over its plots,
   charged the miss of each sensor of its frame that gave its group no plot); **close**
   the frame: ids at confirmation, the deleted gone, the priority order restored
   (:class:`~fusion.tracking.table.TrackTable`).

The parts are protocols (below). The centralised many-target methods
(:class:`fusion.mtt.MultiTargetMethod`), the distributed centre
(:class:`fusion.network.MultiTrackCentre`: local tracks as plots, track-to-track costs)
and the emitter tracker (:class:`fusion.df.multi.MultiEmitterMethod`) are configurations
of it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property
from typing import Any, Protocol, Sequence

import numpy as np

from ..types import Measurement
from .associators import Associator
from .hypotheses import Hypotheses
from .table import CONFIRMED, Track, TrackTable

CLAIMED_MAX = 0.99  # a plot claimed more starts no weighed birth (its existence: under 1 % of existence_birth)


@dataclass(frozen=True)
class Frame:
    """The plots of one frame, in stream order; ``t`` is the first one's time."""

    plots: Sequence

    @property
    def t(self) -> float:
        return self.plots[0].t

    @cached_property
    def sensors(self) -> int:
        """How many sensors (or nodes) the frame holds."""
        return len({p.sensor for p in self.plots})


@dataclass(frozen=True)
class Taken:
    """What one track took from one scan: the plots, their ``d²``, their association
    weights ``β`` (1 for an assignment) and the weight ``β₀`` that the track made none
    of them (0 for an assignment)."""

    plots: tuple
    d2: tuple[float, ...]
    beta: tuple[float, ...] = (1.0,)
    miss: float = 0.0

    @property
    def weighted(self) -> bool:
        """Whether this is a weighted association's (anything but one plot for sure)."""
        return self.miss != 0.0 or self.beta != (1.0,)


class Hypothesiser(Protocol):
    def predict(self, tracks: Sequence[Track], frame: Frame) -> Any:
        """The tracks' gating states at the frame's time (opaque to the tracker)."""

    def scans(self, frame: Frame) -> Sequence[Sequence]:
        """The frame's plots as scans, in the order they are associated."""

    def hypothesise(self, states: Any, tracks: Sequence[Track], scan: Sequence) -> Hypotheses: ...

    def condition(self, states: Any, hyp: Hypotheses, association) -> None:
        """Sequential gating: condition the gating states on the scan's association."""

    def unclaimed(self, hyp: Hypotheses, columns: Sequence[int]) -> list:
        """What becomes of the plots no track took: those left for initiation."""


class Initiator(Protocol):
    def initiate(self, left: list, tracks: Sequence[Track], frame: Frame) -> tuple[dict[int, list[Taken]], list]:
        """From the plots no track took: ``(continued, births)`` — groups handed to
        existing (tentative) tracks by their place in ``tracks``, and the groups that
        start new tracks."""


class Updater(Protocol):
    def update(self, track: Track, taken: list[Taken], frame: Frame) -> bool:
        """Update (or coast) the track with what it took; returns whether it scores a hit.
        A track it cannot update it marks deleted."""

    def position_cov(self, track: Track) -> np.ndarray:
        """The covariance ``max_pos_std`` is checked on."""

    def start(self, group, frame: Frame) -> Track | None:
        """A new track from an initiation group (None: the group gives no state)."""


class Reviewer(Protocol):
    def review(self, tracks: Sequence[Track]) -> None:
        """After the updates: mark tracks deleted (duplicates, a failed consistency test).
        ``tracks`` begins with those the frame expired (deleted already)."""


class MultiTargetTracker:
    """Many targets over injected parts (module docstring).

    Args:
        hypothesiser, associator, initiator, updater: the parts.
        table: the track table (its logic is the track management).
        reviewer: an optional review after the updates (e.g. a
            :class:`~fusion.tracking.table.DuplicateWatch`).
    """

    def __init__(self, hypothesiser: Hypothesiser, associator: Associator, initiator: Initiator, updater: Updater,
                 table: TrackTable, reviewer: Reviewer | None = None):
        self.hypothesiser = hypothesiser
        self.associator = associator
        self.initiator = initiator
        self.updater = updater
        self.table = table
        self.reviewer = reviewer
        self._unclaimed: dict[int, float] = {}  # this frame: id of a plot left -> 1 − claimed (Weights.claimed)

    @property
    def tracks(self) -> list[Track]:
        """The tracks, in priority order (confirmed in id order, then tentative in birth order)."""
        return self.table.tracks

    def taken_over(self, track: Track) -> None:
        """``track``, just added to the table, confirmed as one taken over from another
        tracker's picture (a rebuild: its history is not known, its state is)."""
        track.logic.status, track.logic.hits = CONFIRMED, track.logic.rule.confirm_m

    def frame(self, plots: Sequence) -> list[Track]:
        """One frame (module docstring); returns its confirmed tracks, in id order."""
        frame = Frame(plots)
        expired = self.table.expire(frame.t)
        tracks = list(self.table.tracks)
        self._unclaimed = {}
        taken, left = self.associate(tracks, frame)
        continued, births = self.initiator.initiate(left, tracks, frame)
        for i, track in enumerate(tracks):
            mine = taken[i] + continued.get(i, [])
            hit = self.updater.update(track, mine, frame)
            if not track.deleted:  # (an updater deletes a track it cannot update)
                track.logic.record(hit, self.updater.position_cov(track))
            track.claim([m for tk in mine if not tk.weighted for m in tk.plots])
        if self.reviewer is not None:
            self.reviewer.review(expired + tracks)
        born = getattr(self.associator, "born", None)  # JIPDA's: the birth frame's misses
        for group in births:
            track = self.updater.start(group, frame)
            if track is not None:
                self.table.add(track).logic.survive(frame.t)
                track.claim(initial_plots(group))
                if born is not None and track.existence is not None:
                    plots = initial_plots(group)
                    seen = {m.sensor for m in plots}
                    missed = [s for s in dict.fromkeys(m.sensor for m in frame.plots) if s not in seen]
                    unclaimed = math.prod(self._unclaimed.get(id(m), 1.0) for m in plots)
                    track.logic.existence = born(track.existence, missed, unclaimed)
        return self.table.close_frame()

    def associate(self, tracks: list[Track], frame: Frame) -> tuple[list[list[Taken]], list]:
        """Scan by scan: what each track took, and the plots left for initiation. A
        track logic with existence survives to the frame first, and takes the existence
        each scan's association leaves (JIPDA's ``Weights.existence``)."""
        for track in tracks:
            track.logic.survive(frame.t)
        states = self.hypothesiser.predict(tracks, frame)
        taken: list[list[Taken]] = [[] for _ in tracks]
        left: list = []
        scans = self.hypothesiser.scans(frame)
        for k, scan in enumerate(scans):
            hyp = self.hypothesiser.hypothesise(states, tracks, scan)
            association = self.associator.associate(hyp)
            if association.existence is not None:
                for r, e in enumerate(association.existence):
                    tracks[hyp.rows[r]].logic.existence = float(e)
            for r, cols, beta, miss in association.per_row():
                taken[hyp.rows[r]].append(Taken(tuple(scan[c] for c in cols), tuple(hyp.d2[r, list(cols)]), beta, miss))
            claimed = getattr(association, "claimed", None)
            if claimed is None:
                free = [c for c in range(len(scan)) if c not in association.used]
            else:  # a birth weighed by 1 − claimed (JIPDA.born)
                free = [c for c in range(len(scan)) if claimed[c] < CLAIMED_MAX]
                self._unclaimed.update((id(scan[c]), 1.0 - float(claimed[c])) for c in free)
            left += self.hypothesiser.unclaimed(hyp, free)
            if k + 1 < len(scans):
                self.hypothesiser.condition(states, hyp, association)
        return taken, left


def initial_plots(group) -> list:
    """The plots of a measurement initiation group ``(first, more, x, P)``, in stream
    order; [] for any other group (a network centre's local tracks)."""
    if isinstance(group, tuple) and len(group) == 4:
        return sorted((m for m in (*group[0], *group[1]) if isinstance(m, Measurement)), key=lambda m: m.order_key)
    return []
