r"""Multi-target track quality: GOSPA/OSPA per time step, and what the set distances do
not show — track breaks, purity, false tracks.

Input is a sequence of *steps*, one per output time: the true positions of the targets
present and the reported positions of the tracks, each keyed by id. At every step the
truths are assigned to the tracks as GOSPA assigns them (least ``Σ dᵖ``, costs capped at
``cᵖ``; a pair at distance ``≥ c`` is no pair), so a track is "on" a target exactly when
GOSPA counts it as localising that target. Over the run:

* **held**: truth-steps with an assigned track, over all truth-steps;
* **breaks**: a held target held at its next step by no track or another one, over the
  chances to break (a target not yet held cannot break);
* **purity**: track-steps on each track's most frequent target, over all track-steps;
* **hold** of a target: from the first step it is held, the fraction of steps it is;
* **ghost persistence**: the longest run of steps one track spent on no target;
* **found at the end**: the fraction of the last step's targets held there;
* **false tracks**: tracks on no target at any step of their life.

GOSPA and OSPA are :func:`fusion.metrics.gospa` and :func:`fusion.metrics.ospa`.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field
from typing import Mapping, Sequence

import numpy as np
from scipy.optimize import linear_sum_assignment

from .metrics import gospa, ospa


@dataclass(frozen=True)
class Step:
    """One output time: ``truths`` and ``tracks`` map ids to positions (d,)."""

    t: float
    truths: Mapping[str, np.ndarray]
    tracks: Mapping[str, np.ndarray]


def assign(truths: Mapping[str, np.ndarray], tracks: Mapping[str, np.ndarray], c: float,
           p: float = 2.0) -> dict[str, str]:
    """Truth id -> track id, as GOSPA pairs them: the assignment of least ``Σ dᵖ`` with
    costs capped at ``cᵖ``, keeping only pairs closer than ``c``."""
    if not truths or not tracks:
        return {}
    tid, kid = list(truths), list(tracks)
    X = np.array([truths[i] for i in tid], dtype=float)
    Y = np.array([tracks[k] for k in kid], dtype=float)
    D = np.linalg.norm(X[:, None, :] - Y[None, :, :], axis=-1) ** p
    rows, cols = linear_sum_assignment(np.minimum(D, c**p))
    return {tid[r]: kid[k] for r, k in zip(rows, cols) if D[r, k] < c**p}


@dataclass
class TrackScore:
    """One run's many-target score: per step GOSPA, OSPA, missed and false counts, and
    the run's totals (truth-steps held, breaks and their chances, track purity, false
    tracks, hold fractions, longest ghost, found at the end)."""

    t: list[float] = field(default_factory=list)
    gospa: list[float] = field(default_factory=list)
    ospa: list[float] = field(default_factory=list)
    n_missed: list[int] = field(default_factory=list)
    n_false: list[int] = field(default_factory=list)
    truth_steps: int = 0
    held_steps: int = 0
    breaks: int = 0
    break_chances: int = 0
    track_steps: int = 0
    dominant_steps: int = 0
    false_tracks: int = 0
    false_track_steps: int = 0
    n_tracks: int = 0
    assignments: list[dict[str, str]] = field(default_factory=list)
    hold_fractions: list[float] = field(default_factory=list)
    longest_ghost: list[int] = field(default_factory=list)
    found_at_end: list[float] = field(default_factory=list)

    COUNTS = ("truth_steps", "held_steps", "breaks", "break_chances", "track_steps", "dominant_steps",
              "false_tracks", "false_track_steps", "n_tracks")

    @classmethod
    def merged(cls, scores: Sequence["TrackScore"]) -> "TrackScore":
        """Several runs as one score: counts summed, per-step series concatenated, so the
        rates (held, break rate, purity, mean GOSPA) are over all of their steps."""
        out = cls(**{k: sum(getattr(s, k) for s in scores) for k in cls.COUNTS})
        for s in scores:
            for series in ("t", "gospa", "ospa", "n_missed", "n_false", "assignments", "hold_fractions",
                           "longest_ghost", "found_at_end"):
                getattr(out, series).extend(getattr(s, series))
        return out

    @property
    def held(self) -> float:
        return self.held_steps / self.truth_steps if self.truth_steps else float("nan")

    @property
    def break_rate(self) -> float:
        return self.breaks / self.break_chances if self.break_chances else 0.0

    @property
    def purity(self) -> float:
        return self.dominant_steps / self.track_steps if self.track_steps else float("nan")

    @property
    def max_ghost(self) -> int:
        """The longest ghost of all runs (``longest_ghost`` is one per run)."""
        return max(self.longest_ghost, default=0)

    @property
    def all_found_runs(self) -> int:
        """Runs whose last step held every target."""
        return sum(f == 1.0 for f in self.found_at_end)

    @property
    def worst_hold(self) -> float:
        return min(self.hold_fractions) if self.hold_fractions else float("nan")

    @property
    def mean_gospa(self) -> float:
        return float(np.mean(self.gospa)) if self.gospa else float("nan")

    def summary(self) -> dict:
        return {"mean_gospa": self.mean_gospa, "mean_ospa": float(np.mean(self.ospa)) if self.ospa else None,
                "held": self.held, "breaks": self.breaks, "break_rate": self.break_rate,
                "purity": self.purity, "worst_hold": self.worst_hold, "tracks": self.n_tracks,
                "longest_ghost": self.max_ghost, "all_found_runs": self.all_found_runs, "false_tracks": self.false_tracks,
                "false_track_steps": self.false_track_steps,
                "missed_steps": int(sum(self.n_missed)), "steps": len(self.t)}


def score_tracks(steps: Sequence[Step], c: float, p: float = 2.0) -> TrackScore:
    """Score a run's steps (in time order); ``c`` is the cut-off distance, ``p`` the order."""
    out = TrackScore()
    last_on: dict[str, str | None] = {}  # truth -> track at its previous step (None: not held)
    on_counts: dict[str, Counter] = {}  # track -> Counter of the truths it was on (None: nothing)
    found: dict[str, list[int]] = {}  # truth -> [steps held, steps since first held]
    ghost: dict[str, int] = {}  # track -> consecutive steps on no target, up to now
    longest = 0
    for s in steps:
        pairs = assign(s.truths, s.tracks, c, p)
        X = [np.asarray(s.truths[i], dtype=float) for i in s.truths]
        Y = [np.asarray(s.tracks[k], dtype=float) for k in s.tracks]
        g = gospa(Y, X, c, p)
        out.t.append(float(s.t))
        out.gospa.append(g.distance)
        out.ospa.append(ospa(Y, X, c, p))
        out.n_missed.append(g.n_missed)
        out.n_false.append(g.n_false)
        out.assignments.append(pairs)
        out.truth_steps += len(s.truths)
        out.held_steps += len(pairs)
        for truth in s.truths:
            before = last_on.get(truth)
            if before is not None:
                out.break_chances += 1
                out.breaks += int(pairs.get(truth) != before)
            last_on[truth] = pairs.get(truth)
            f = found.setdefault(truth, [0, 0])
            if truth in pairs or f[1]:
                f[0] += int(truth in pairs)
                f[1] += 1
        by_track = {k: tr for tr, k in pairs.items()}
        ghost = {k: ghost.get(k, 0) + 1 for k in s.tracks if k not in by_track}
        longest = max(longest, *ghost.values(), 0)
        for k in s.tracks:
            on_counts.setdefault(k, Counter())[by_track.get(k)] += 1
    for counts in on_counts.values():
        life = sum(counts.values())
        on_target = {truth: n for truth, n in counts.items() if truth is not None}
        out.track_steps += life
        out.dominant_steps += max(on_target.values(), default=0)
        out.false_track_steps += counts.get(None, 0)
        out.false_tracks += int(not on_target)
    out.n_tracks = len(on_counts)
    out.hold_fractions = [held / since if since else 0.0 for held, since in found.values()]
    out.longest_ghost = [longest]
    if steps:
        last = steps[-1]
        out.found_at_end = [len(assign(last.truths, last.tracks, c, p)) / len(last.truths) if last.truths else 1.0]
    return out
