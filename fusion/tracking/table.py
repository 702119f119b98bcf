r"""The track table of a many-target tracker: each track's life, its published id, and
the order the tracker serves the tracks in.

*Life* (:class:`TrackLogic` under a :class:`ManagementRule`): a track is born
tentative; it is confirmed once it has ``M`` hits (birth included) within its first
``N`` frames, deleted if it can no longer get there, and a confirmed track is deleted
after ``K`` consecutive missed frames; any track is deleted once its position σ
(``√trace P_pos``) exceeds ``max_pos_std``. (With JIPDA the life follows the track's
existence probability instead: :class:`fusion.tracking.jipda.ExistenceLogic`.)

*Ids* (:class:`TrackIds`): ``T1, T2, …`` (``E1, …`` for emitters) issued at
confirmation, in the table's order, never reused.

*Priority order* (:class:`TrackTable`): confirmed tracks in id order, then tentative
ones in birth order. Association serves the tracks in this order (confirmed ones first:
a young track's broad gate cannot take a plot from an established track), and the
confirmed ones are reported in it.

*Duplicates* (:class:`DuplicateWatch`): two tracks whose states agree within the
track-to-track χ² gate for ``F`` consecutive frames follow one target; the later in
priority order is deleted.

*The guards* (:mod:`fusion.guards`): a track whose state is more than ``max_gap_s``
older than a frame is deleted before the frame (:meth:`TrackTable.expire`), and one
whose position covariance is not positive definite after a frame is deleted with it
(:meth:`TrackLogic.record`): either way the frame's plots start new tracks, exactly as
they would in an empty table. An updater that cannot update a track (a fusion whose
inverses fail) deletes it itself.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable, Sequence

import numpy as np

from ..guards import MAX_GAP_S, gap_too_long, positive_definite
from ..measurement.kinds import KINDS
from ..types import Estimate, Identity
from .hypotheses import gate_threshold, track_distance2

TENTATIVE, CONFIRMED, DELETED = "tentative", "confirmed", "deleted"


@dataclass(frozen=True)
class ManagementRule:
    """M-of-N confirmation and K-miss deletion: a track is confirmed once it has
    ``confirm_m`` hits (birth included) within its first ``confirm_n`` frames, and a
    confirmed track is deleted after ``delete_misses`` consecutive missed frames; any
    track is deleted once its position σ (√trace P_pos) exceeds ``max_pos_std``."""

    confirm_m: int = 3
    confirm_n: int = 4
    delete_misses: int = 3
    max_pos_std: float = math.inf

    def __post_init__(self):
        if not 1 <= self.confirm_m <= self.confirm_n:
            raise ValueError(f"need 1 <= confirm_m <= confirm_n, got M={self.confirm_m}, N={self.confirm_n}")
        if self.delete_misses < 1:
            raise ValueError(f"delete_misses must be >= 1, got {self.delete_misses}")


@dataclass
class TrackLogic:
    """One track's status; :meth:`record` is called once per frame after its birth.

    Attributes:
        status: ``tentative``, ``confirmed`` or ``deleted``.
        hits: hits over the frames seen so far (birth counts as one).
        frames: frames seen so far, birth included.
        misses: consecutive missed frames (reset by a hit).
    """

    rule: ManagementRule
    status: str = TENTATIVE
    hits: int = 1
    frames: int = 1
    misses: int = 0

    #: M-of-N holds no existence probability (:class:`fusion.tracking.jipda.ExistenceLogic` does)
    existence = None

    def __post_init__(self):
        self._settle()

    def survive(self, t: float) -> None:
        """The start of a frame at ``t``: nothing of M-of-N changes between frames."""

    def record(self, hit: bool, P_pos: np.ndarray | None = None) -> str:
        """One more frame, with the track's position covariance ``P_pos`` after it (for
        ``max_pos_std``, and deleted if not positive definite); returns the new status."""
        if self.status == DELETED:
            raise ValueError("a deleted track records no more frames")
        self.frames += 1
        self.hits += int(hit)
        self.misses = 0 if hit else self.misses + 1
        self._settle()
        if P_pos is not None and self.status != DELETED and (
                not positive_definite(P_pos) or math.sqrt(float(np.trace(P_pos))) > self.rule.max_pos_std):
            self.status = DELETED
        return self.status

    def _settle(self) -> None:
        r = self.rule
        if self.status == TENTATIVE:
            if self.hits >= r.confirm_m:
                self.status = CONFIRMED
            elif self.hits + (r.confirm_n - self.frames) < r.confirm_m:
                self.status = DELETED  # M cannot be reached within N frames any more
        elif self.status == CONFIRMED and self.misses >= r.delete_misses:
            self.status = DELETED


def scores_hit(kinds: Sequence[str], confirmed: bool, evidence: int) -> bool:
    """Whether a 3D track scores a hit in a frame, in every topology: ``kinds`` are the
    measurement kinds of the sensors whose plots (or local tracks) it took, one per
    sensor; ``evidence`` is two, or one if the frame holds one sensor.

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


@dataclass
class TrackIds:
    """Issues ``T1, T2, …`` (``prefix`` + counter), one per confirmed track, never reused."""

    prefix: str = "T"
    issued: int = field(default=0)

    def next(self) -> str:
        self.issued += 1
        return f"{self.prefix}{self.issued}"

    def number(self, track_id: str) -> int:
        """The counter value of an id this issued."""
        return int(track_id[len(self.prefix):])


class Track:
    """One track of a table: its estimator, its life, its latest estimate.

    Attributes:
        filter: what estimates the track — a filter, a track fuser, a DF method: the
            table does not look inside.
        last: its estimate of the latest frame (updated, or predicted when missed).
        logic: its :class:`TrackLogic` (or any object with ``status``, ``existence``,
            ``survive`` and ``record``: :class:`fusion.tracking.jipda.ExistenceLogic`;
            given by :meth:`TrackTable.add` if None).
        birth: its place in the order of births (set by :meth:`TrackTable.add`).
        id: its published id, issued at confirmation (None before).
        identity: the identity its target claims: that of the latest plot assigned to it
            that carries one (a position report's), else None. Only an assignment sets
            it: an identity never decides one (the gate does), so two aircraft sending
            one address keep two tracks with the same identity.
        identity_changes: how often a plot's identity replaced a different one.
    """

    __slots__ = ("filter", "last", "logic", "birth", "id", "identity", "identity_changes")

    def __init__(self, filter, last: Estimate, logic=None):
        self.filter, self.last, self.logic = filter, last, logic
        self.birth = 0
        self.id: str | None = None
        self.identity: Identity | None = None
        self.identity_changes = 0

    def claim(self, plots) -> None:
        """Take the identity of the last of ``plots`` (assigned to it, in stream order)
        that carries one, counting a change."""
        for m in reversed(plots):
            identity = getattr(m, "identity", None)
            if identity is not None:
                if self.identity is not None and identity != self.identity:
                    self.identity_changes += 1
                self.identity = identity
                return

    @property
    def confirmed(self) -> bool:
        return self.logic.status == CONFIRMED

    @property
    def deleted(self) -> bool:
        return self.logic.status == DELETED

    @property
    def existence(self) -> float | None:
        """The probability that the track's target exists, if its logic holds one (JIPDA)."""
        return self.logic.existence


class TrackTable:
    """The tracks in priority order (module docstring) and their ids.

    Args:
        new_logic: a new track's logic (default: :class:`TrackLogic` under the default rule).
        prefix: of the published ids.
        max_gap_s: a track whose state is older than this before a frame is deleted
            (:meth:`expire`).
    """

    def __init__(self, new_logic: Callable[[], TrackLogic] | None = None, prefix: str = "T",
                 max_gap_s: float = MAX_GAP_S):
        self.new_logic = new_logic or (lambda: TrackLogic(ManagementRule()))
        self.max_gap_s = max_gap_s
        self.ids = TrackIds(prefix)
        self.births = 0
        self.tracks: list[Track] = []  # confirmed in id order, then tentative in birth order

    def __len__(self) -> int:
        return len(self.tracks)

    def add(self, track: Track) -> Track:
        """A new track, last in the order until the frame closes (confirmed at birth if
        ``M = 1``: then given its id with the others); its logic a new one if it has none."""
        if track.logic is None:
            track.logic = self.new_logic()
        self.births += 1
        track.birth = self.births
        self.tracks.append(track)
        return track

    def expire(self, t: float) -> list[Track]:
        """Before a frame at ``t``: the tracks whose latest estimate is more than
        ``max_gap_s`` before it (:func:`fusion.guards.gap_too_long`) are deleted and
        leave the table; returns them (their configuration may have to tell others)."""
        gone = [tr for tr in self.tracks if gap_too_long(t - tr.last.t, self.max_gap_s)]
        for tr in gone:
            tr.logic.status = DELETED
        if gone:
            self.tracks = [tr for tr in self.tracks if tr.logic.status != DELETED]
        return gone

    def close_frame(self) -> list[Track]:
        """The end of a frame: ids for the tracks confirmed in it (in table order), the
        deleted ones gone, the priority order restored. Returns the confirmed tracks,
        in id order."""
        for tr in self.tracks:
            if tr.logic.status == CONFIRMED and tr.id is None:
                tr.id = self.ids.next()
        live = [tr for tr in self.tracks if tr.logic.status != DELETED]
        confirmed = sorted((tr for tr in live if tr.id is not None), key=lambda tr: self.ids.number(tr.id))
        self.tracks = confirmed + sorted((tr for tr in live if tr.id is None), key=lambda tr: tr.birth)
        return confirmed


class DuplicateWatch:
    """Finds tracks that follow a target another track already holds (module docstring).

    Args:
        frames: consecutive frames a pair must agree before the later track goes
            (0: never).
        gate_prob: χ² gate probability of the agreement test.
        dims: the compared state components (position and velocity).
    """

    def __init__(self, frames: int, gate_prob: float, dims=(0, 1, 2, 3, 4, 5)):
        if frames < 0:
            raise ValueError(f"merge_frames must be >= 0, got {frames}")
        self.frames = frames
        self.gate_prob = gate_prob
        self.dims = np.asarray(dims)
        self._streak: dict[tuple, int] = {}

    def review(self, tracks: Sequence[Track]) -> None:
        """One frame of a table's ``tracks`` (in priority order, at the frame's time):
        the duplicates among the live ones are marked deleted."""
        live = {tr.birth: tr for tr in tracks if tr.logic.status != DELETED}
        for birth in self.duplicates([(b, tr.last.x, tr.last.P) for b, tr in live.items()]):
            live[birth].logic.status = DELETED

    def duplicates(self, tracks) -> list:
        """One frame: ``tracks`` are ``(key, x, P)`` at the frame's time, the track that
        keeps priority first (confirmed in id order, then tentative in birth order).
        Returns the keys of the tracks to delete."""
        if not self.frames or len(tracks) < 2:
            self._streak = {}
            return []
        keys = [k for k, _, _ in tracks]
        X = np.array([np.asarray(x, float)[self.dims] for _, x, _ in tracks])
        T = np.array([np.trace(np.asarray(P, float)[np.ix_(self.dims[:3], self.dims[:3])]) for _, _, P in tracks])
        # d² ≥ |Δpos|² / tr(T_pos): pairs farther apart than that bound allows cannot agree.
        D2 = np.sum((X[:, None, :3] - X[None, :, :3]) ** 2, axis=-1)
        bound = gate_threshold(len(self.dims), self.gate_prob) * (T[:, None] + T[None, :])
        streak: dict[tuple, int] = {}
        gone: set[int] = set()
        for i, j in zip(*np.nonzero(np.triu(D2 <= bound, 1))):
            (ki, xi, Pi), (kj, xj, Pj) = tracks[i], tracks[j]
            d2, rank = track_distance2(xi, Pi, xj, Pj, dims=self.dims)
            if rank and d2 > gate_threshold(rank, self.gate_prob):
                continue
            n = streak[(ki, kj)] = self._streak.get((ki, kj), 0) + 1
            if n >= self.frames and i not in gone:
                gone.add(j)
        self._streak = {k: n for k, n in streak.items() if not ({k[0], k[1]} & {keys[g] for g in gone})}
        return [keys[g] for g in sorted(gone)]
