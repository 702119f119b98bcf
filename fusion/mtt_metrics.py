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
* **false tracks**: tracks on no target at any step of their life;
* **duplicates**: per step, the targets on which more than one track sits — a track
  left out of the assignment whose nearest target, closer than ``c``, is held by
  another track — summed over the steps;
* **id changes**: the steps at which a target is held by another track than the one that
  held it last (unlike a break, a step held by none does not count, nor does the first
  track to hold it);
* **held after initiation**: truth-steps with an assigned track over the truth-steps of
  *settled* targets only, those a step marks as past their initiation (the scorer of a
  scenario marks a target settled from its third scan by any sensor on: a tracker needs
  a few scans to start and confirm a track, which ``held`` counts against it);
* **assigned position RMSE** (``rmse_pos_assigned``): ``√(Σ‖x − y‖² / n)`` over the n
  truth-track pairs of that assignment, every step: how well the held targets are
  localised, apart from GOSPA's penalties for the missed and the false.

GOSPA and OSPA are :func:`fusion.metrics.gospa` and :func:`fusion.metrics.ospa`. For a
large step (more than :data:`DENSE_MAX` truth-track pairs) all three come from one
sparse matching instead: only pairs closer than ``c`` can be in the optimum (a pair at
``d ≥ c`` costs ``cᵖ``, a miss plus a false track), so the pairs within ``c`` (a k-d
tree) split into independent clusters, each solved alone (most hold one truth and one
track); the optimum, the assignment and both distances are the dense ones.
:class:`TrackScorer` folds the steps in one at a time and keeps only what the metrics
need next (per live target and track, counters, a binned series), so a live run of days
is scored in bounded memory; :func:`score_tracks`, a finished run, is that fold.
"""

from __future__ import annotations

import dataclasses
from collections import Counter
from dataclasses import dataclass, field
from typing import Iterable, Mapping, Sequence

import numpy as np
from scipy.optimize import linear_sum_assignment
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from .binning import BinnedSeries
from .metrics import GOSPA, gospa, ospa

DENSE_MAX = 40_000  # truth-track pairs up to which a step is matched densely


@dataclass(frozen=True)
class Step:
    """One output time: ``truths`` and ``tracks`` map ids to positions (d,); ``settled``:
    the truths past their initiation (module docstring), None if the step does not say."""

    t: float
    truths: Mapping[str, np.ndarray]
    tracks: Mapping[str, np.ndarray]
    settled: frozenset[str] | None = None


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


def match(truths: Mapping[str, np.ndarray], tracks: Mapping[str, np.ndarray], c: float,
          p: float = 2.0) -> tuple[dict[str, str], GOSPA, float]:
    """:func:`assign`, :func:`fusion.metrics.gospa` and :func:`fusion.metrics.ospa` of one
    step: densely, or from one sparse matching for a large step (module docstring)."""
    X = [np.asarray(truths[i], dtype=float) for i in truths]
    Y = [np.asarray(tracks[k], dtype=float) for k in tracks]
    if len(X) * len(Y) <= DENSE_MAX:
        return assign(truths, tracks, c, p), gospa(Y, X, c, p), ospa(Y, X, c, p)
    tid, kid = list(truths), list(tracks)
    n, m = len(tid), len(kid)
    D = cKDTree(np.array(X)).sparse_distance_matrix(cKDTree(np.array(Y)), c, output_type="coo_matrix")
    near = D.data < c
    rows, cols, cost = D.row[near], D.col[near], D.data[near] ** p
    graph = coo_matrix((np.ones(len(rows)), (rows, n + cols)), shape=(n + m, n + m))
    _, label = connected_components(graph, directed=False)
    pairs: list[tuple[int, int, float]] = []
    order = np.argsort(label[rows], kind="stable")
    rows, cols, cost = rows[order], cols[order], cost[order]
    bounds = np.flatnonzero(np.diff(label[rows])) + 1
    for r, k, d in zip(np.split(rows, bounds), np.split(cols, bounds), np.split(cost, bounds)):
        if len(r) == 1:
            pairs.append((int(r[0]), int(k[0]), float(d[0])))
            continue
        ur, ri = np.unique(r, return_inverse=True)
        uk, ki = np.unique(k, return_inverse=True)
        block = np.full((len(ur), len(uk)), c**p)
        block[ri, ki] = d
        a, b = linear_sum_assignment(block)
        pairs += [(int(ur[i]), int(uk[j]), float(block[i, j])) for i, j in zip(a, b) if block[i, j] < c**p]
    loc = float(sum(d for _, _, d in pairs))
    half, kept = c**p / 2.0, len(pairs)
    g = GOSPA(float((loc + half * (n + m - 2 * kept)) ** (1.0 / p)), loc, half * (n - kept), half * (m - kept),
              n - kept, m - kept)
    o = float(((loc + c**p * (min(n, m) - kept) + c**p * abs(n - m)) / max(n, m)) ** (1.0 / p))
    return {tid[r]: kid[k] for r, k, _ in pairs}, g, o


@dataclass
class TrackScore:
    """One run's many-target score: per step GOSPA, OSPA, missed and false counts, and
    the run's totals (truth-steps held, breaks and their chances, track purity, false
    tracks, hold fractions, longest ghost, found at the end).

    The series have a point per step, unless the score is a :class:`TrackScorer`'s with
    ``series_max``: then ``bin`` consecutive steps a point, stamped with its last time,
    with the mean GOSPA and OSPA and the missed and false counts of its steps, and no
    ``assignments``. ``steps``, ``gospa_sum``, ``ospa_sum`` and ``missed_steps`` count
    every step either way."""

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
    steps: int = 0
    missed_steps: int = 0
    gospa_sum: float = 0.0
    ospa_sum: float = 0.0
    settled_steps: int = 0
    settled_held: int = 0
    assigned_sq: float = 0.0  # Σ‖truth − track‖² over the assigned pairs (held_steps of them)
    duplicates: int = 0
    id_changes: int = 0
    bin: int = 1
    assignments: list[dict[str, str]] = field(default_factory=list)
    hold_fractions: list[float] = field(default_factory=list)
    longest_ghost: list[int] = field(default_factory=list)
    found_at_end: list[float] = field(default_factory=list)

    COUNTS = ("truth_steps", "held_steps", "breaks", "break_chances", "track_steps", "dominant_steps",
              "false_tracks", "false_track_steps", "n_tracks", "steps", "missed_steps", "gospa_sum", "ospa_sum",
              "settled_steps", "settled_held", "assigned_sq", "duplicates", "id_changes")

    @classmethod
    def merged(cls, scores: Sequence["TrackScore"]) -> "TrackScore":
        """Several runs as one score: counts summed, per-step series concatenated, so the
        rates (held, break rate, purity, mean GOSPA) are over all of their steps."""
        out = cls(**{k: sum(getattr(s, k) for s in scores) for k in cls.COUNTS},
                  bin=max((s.bin for s in scores), default=1))
        for s in scores:
            for series in ("t", "gospa", "ospa", "n_missed", "n_false", "assignments", "hold_fractions",
                           "longest_ghost", "found_at_end"):
                getattr(out, series).extend(getattr(s, series))
        return out

    @property
    def held(self) -> float:
        return self.held_steps / self.truth_steps if self.truth_steps else float("nan")

    @property
    def held_after_init(self) -> float:
        """Held truth-steps of settled targets over their truth-steps (NaN: no step said
        which targets are settled, or none was)."""
        return self.settled_held / self.settled_steps if self.settled_steps else float("nan")

    @property
    def rmse_pos_assigned(self) -> float:
        """The position RMSE over the assigned truth-track pairs (NaN: none)."""
        return float(np.sqrt(self.assigned_sq / self.held_steps)) if self.held_steps else float("nan")

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

    def _mean(self, series: list[float], total: float) -> float:
        """Over every step: NumPy's mean of the series when it has a point per step, else
        the running sum over the count (equal to rounding)."""
        if not self.steps:
            return float("nan")
        return float(np.mean(series)) if self.bin == 1 and len(series) == self.steps else total / self.steps

    @property
    def mean_gospa(self) -> float:
        return self._mean(self.gospa, self.gospa_sum)

    @property
    def mean_ospa(self) -> float:
        return self._mean(self.ospa, self.ospa_sum)

    def summary(self) -> dict:
        return {"mean_gospa": self.mean_gospa, "mean_ospa": self.mean_ospa if self.steps else None,
                "held": self.held, "held_after_init": self.held_after_init, "breaks": self.breaks,
                "rmse_pos_assigned": self.rmse_pos_assigned,
                "break_rate": self.break_rate,
                "purity": self.purity, "worst_hold": self.worst_hold, "tracks": self.n_tracks,
                "longest_ghost": self.max_ghost, "all_found_runs": self.all_found_runs, "false_tracks": self.false_tracks,
                "false_track_steps": self.false_track_steps,
                "missed_steps": self.missed_steps, "steps": self.steps, "duplicates": self.duplicates,
                "id_changes": self.id_changes}


class TrackScorer:
    """A run's :class:`TrackScore`, folded in step by step (steps in time order).

    It keeps, per live target, the track it was on at its last step and its held and
    since-first-held steps; per live track, the steps it spent on each target (and on
    none) and its current ghost run; the run's counters; and the series. A target or track
    absent from ``forget_after`` consecutive steps is closed — its hold fraction, purity
    and false-track counts go into the totals — and forgotten, so with ``forget_after``
    and ``series_max`` memory is bounded by the live targets and tracks and
    ``series_max`` points, not by the run's length. Closing is exact for ids never used
    again (track ids are never reused, traffic aircraft neither); of the forgotten
    targets' hold fractions only the least is kept (``worst_hold``). Without
    ``forget_after`` nothing is forgotten (a finished run: :func:`score_tracks`).

    ``series_max``: at most that many series points; two neighbouring points are merged
    whenever there would be more, so ``bin`` is a power of two. Without it, one point per
    step and each step's ``assignments``.
    """

    def __init__(self, c: float, p: float = 2.0, forget_after: int | None = None, series_max: int | None = None):
        self.c, self.p = c, p
        self.forget_after, self.series_max = forget_after, series_max
        self.out = TrackScore()  # counters, the closed targets' and tracks' totals, the series
        self.last_on: dict[str, str | None] = {}  # truth -> track at its previous step (None: not held)
        self.last_id: dict[str, str] = {}  # truth -> the last track that held it
        self.found: dict[str, list[int]] = {}  # truth -> [steps held, steps since first held]
        self.on_counts: dict[str, Counter] = {}  # track -> Counter of the truths it was on (None: nothing)
        self.ghost: dict[str, int] = {}  # track -> consecutive steps on no target, up to now
        self.seen: dict[tuple[bool, str], int] = {}  # (is a track, id) -> index of its last step
        self.longest = 0
        self.closed = TrackScore()  # the forgotten tracks' and targets' totals
        self.worst_forgotten: float | None = None  # the least hold fraction of the forgotten targets
        self.found_last: float | None = None  # fraction of the last step's targets held there
        self.binned = None if series_max is None else BinnedSeries(series_max, lambda: [0.0, 0.0, 0, 0], _add)
        # (per point: Σgospa, Σospa, missed, false)

    def add(self, s: Step) -> dict[str, str]:
        """Score one step; returns its assignment (truth id -> track id)."""
        out, c, p = self.out, self.c, self.p
        pairs, g, o = match(s.truths, s.tracks, c, p)
        self._series(float(s.t), g.distance, o, g.n_missed, g.n_false, pairs)
        out.steps += 1
        out.missed_steps += g.n_missed
        out.gospa_sum += g.distance
        out.ospa_sum += o
        out.truth_steps += len(s.truths)
        out.held_steps += len(pairs)
        out.assigned_sq += sum(float(np.sum((np.asarray(s.truths[a], dtype=float) - np.asarray(s.tracks[k], dtype=float))
                                            ** 2)) for a, k in pairs.items())
        if s.settled is not None:
            settled = s.settled & s.truths.keys()
            out.settled_steps += len(settled)
            out.settled_held += len(settled & pairs.keys())
        for truth in s.truths:
            before = self.last_on.get(truth)
            if before is not None:
                out.break_chances += 1
                out.breaks += int(pairs.get(truth) != before)
            self.last_on[truth] = pairs.get(truth)
            f = self.found.setdefault(truth, [0, 0])
            if truth in pairs or f[1]:
                f[0] += int(truth in pairs)
                f[1] += 1
        for truth, k in pairs.items():
            out.id_changes += int(self.last_id.get(truth, k) != k)
            self.last_id[truth] = k
        by_track = {k: tr for tr, k in pairs.items()}
        out.duplicates += duplicates(s, pairs, by_track, c)
        self.ghost = {k: self.ghost.get(k, 0) + 1 for k in s.tracks if k not in by_track}
        self.longest = max(self.longest, *self.ghost.values(), 0)
        for k in s.tracks:
            self.on_counts.setdefault(k, Counter())[by_track.get(k)] += 1
        self.found_last = len(pairs) / len(s.truths) if s.truths else 1.0
        if self.forget_after is not None:
            self._forget(s)
        return pairs

    def _series(self, t: float, g: float, o: float, missed: int, false: int, pairs: dict) -> None:
        out = self.out
        if self.binned is None:
            out.t.append(t)
            out.gospa.append(g)
            out.ospa.append(o)
            out.n_missed.append(missed)
            out.n_false.append(false)
            out.assignments.append(pairs)
            return
        point = self.binned.sample(t)
        for i, v in enumerate((g, o, missed, false)):
            point[i] += v

    def _forget(self, s: Step) -> None:
        n = self.out.steps
        for truth in s.truths:
            self.seen[(False, truth)] = n
        for k in s.tracks:
            self.seen[(True, k)] = n
        gone = [key for key, last in self.seen.items() if n - last >= self.forget_after]
        for is_track, name in gone:
            del self.seen[(is_track, name)]
            if is_track:
                _close_track(self.closed, self.on_counts.pop(name))
            else:
                self.last_on.pop(name)
                self.last_id.pop(name, None)
                held, since = self.found.pop(name)
                frac = held / since if since else 0.0
                self.worst_forgotten = frac if self.worst_forgotten is None else min(self.worst_forgotten, frac)

    def score(self) -> TrackScore:
        """The run's score so far (the scorer goes on)."""
        out = dataclasses.replace(self.out, **{k: getattr(self.out, k) + getattr(self.closed, k)
                                              for k in ("track_steps", "dominant_steps", "false_tracks",
                                                        "false_track_steps", "n_tracks")})
        for counts in self.on_counts.values():
            _close_track(out, counts)
        if self.binned is not None:
            out.bin, pts = self.binned.bin, self.binned.points
            out.t = [t for t, _, _ in pts]
            out.gospa = [v[0] / n for _, n, v in pts]
            out.ospa = [v[1] / n for _, n, v in pts]
            out.n_missed = [v[2] for _, _, v in pts]
            out.n_false = [v[3] for _, _, v in pts]
        else:
            out.t, out.gospa, out.ospa = list(out.t), list(out.gospa), list(out.ospa)
            out.n_missed, out.n_false, out.assignments = list(out.n_missed), list(out.n_false), list(out.assignments)
        out.hold_fractions = ([] if self.worst_forgotten is None else [self.worst_forgotten]) + [
            held / since if since else 0.0 for held, since in self.found.values()]
        out.longest_ghost = [self.longest]
        out.found_at_end = [] if self.found_last is None else [self.found_last]
        return out


def duplicates(s: Step, pairs: Mapping[str, str], by_track: Mapping[str, str], c: float) -> int:
    """The step's targets on which a second track sits: each target held in ``pairs``
    that is the nearest target, closer than ``c``, of a track left out of them."""
    extra = [k for k in s.tracks if k not in by_track]
    if not extra or not pairs:
        return 0
    truths = list(s.truths)
    d, j = cKDTree(np.array([s.truths[t] for t in truths], dtype=float)).query(
        np.array([s.tracks[k] for k in extra], dtype=float), distance_upper_bound=c)
    return len({truths[i] for di, i in zip(np.atleast_1d(d), np.atleast_1d(j)) if di < c and truths[i] in pairs})


def _add(a: list, b: list) -> None:
    a[:] = [x + y for x, y in zip(a, b)]


def _close_track(out: TrackScore, counts: Counter) -> None:
    """Add one track's life (the steps it spent on each target, ``None``: none) to ``out``."""
    on_target = {truth: n for truth, n in counts.items() if truth is not None}
    out.track_steps += sum(counts.values())
    out.dominant_steps += max(on_target.values(), default=0)
    out.false_track_steps += counts.get(None, 0)
    out.false_tracks += int(not on_target)
    out.n_tracks += 1


def score_tracks(steps: Iterable[Step], c: float, p: float = 2.0) -> TrackScore:
    """Score a run's steps (in time order); ``c`` is the cut-off distance, ``p`` the order."""
    scorer = TrackScorer(c, p)
    for s in steps:
        scorer.add(s)
    return scorer.score()
