"""Scoring against truth, in one place for every job that has truth: ``zfusion run``
(estimates received over Zenoh), the recorder (its error panels: :class:`LiveScore`, which
it only draws) and ``zfusion eval`` (in-process Monte Carlo runs), so all three give the
same numbers. An estimate of ``n`` states is compared with the components
:data:`TRUTH_INDEX` of the truth ``[px py pz vx vy vz ax ay az]``; NEES ``eᵀP⁻¹e`` and NIS
are plotted against the 95 % interval of one χ² sample (:func:`chi2_interval`).

One target per track (a scenario with one target, or tracks named after targets):
:func:`score_run` turns one run's estimates into per-estimate error records against
:func:`truth_function` — position, velocity and acceleration error, NEES ``eᵀP⁻¹e``,
NIS — which :mod:`services.summary` aggregates.

Many targets (an air picture, scored with set metrics): :func:`track_steps` cuts the run
into the scenario's scan groups (the methods' ``pair_tol``), each with every target's
true position and every track's estimate, and :func:`score_tracks_of` scores them with
GOSPA (cut-off :data:`GOSPA_CUTOFF`, order 2), track breaks, purity and false tracks
(:mod:`fusion.mtt_metrics`). Emitter fixes are horizontal and scored so. With rotating
radars no two sensors share a scan time: the steps are then the picture every
:data:`PICTURE_STEP_S` (:class:`PictureSteps`). Each step marks the targets settled
from their third look by any sensor on (:class:`Looks`), for the held fraction after
initiation.
"""

from __future__ import annotations

import heapq
import math
from collections import OrderedDict
from dataclasses import dataclass
from functools import lru_cache
from typing import Callable, Iterator, Sequence

import numpy as np

from fusion import linalg
from fusion.metrics import chi2_bounds, gospa
from fusion.mtt_metrics import Step, score_tracks
from fusion.patent import TrackerConfig
from fusion.regions import Crossings
from fusion.types import Estimate
from sensors_sim import sensor_events, truth_trajectory
from sensors_sim.trajectories import iter_times
from sensors_sim.traffic import Traffic, population

# Truth is [px py pz vx vy vz ax ay az]; an estimate of n states is compared with these
# components of it. Sizes not listed are drawn when possible but not scored.
TRUTH_INDEX: dict[int, tuple[int, ...]] = {
    2: (0, 1),  # emitter fix [px py]
    3: (0, 1, 2),  # position only
    4: (0, 1, 3, 4),  # planar CV [px py vx vy]
    6: tuple(range(6)),  # CV
    9: tuple(range(9)),  # CA
}


def truth_part(x_truth: np.ndarray, n: int) -> np.ndarray | None:
    """The components of a truth state an n-state estimate is compared with (or None)."""
    idx = TRUTH_INDEX.get(n)
    x_truth = np.asarray(x_truth, dtype=float)
    if idx is None or max(idx) >= x_truth.size:
        return None
    return x_truth[list(idx)]


def position_dims(n: int) -> int:
    """How many leading components of an n-state estimate (after :func:`truth_part`) are
    position: 2 for a map-plane state (an emitter fix, planar CV), else 3."""
    return 2 if n in (2, 4) else 3


@lru_cache(maxsize=256)
def chi2_interval(dof: int) -> tuple[float, float]:
    """The two-sided 95 % interval of a single χ²(dof) sample (one NEES or NIS)."""
    return chi2_bounds(dof, 1)


TRUTH_STATES_KEPT = 100_000  # true states a truth function keeps for its callers (0.8 kB each)

TruthFn = Callable[[int, str, float], np.ndarray]  # (run, track, t) -> true state


def truth_function(scenario) -> TruthFn:
    """Truth of the scenario's targets, evaluated from the scenario itself (the scorer may
    see truth; trackers and fusers never do)."""

    cache: dict[tuple[int, str], object] = {}
    # Every method of an evaluation is scored at the same times of a run: each true state
    # is computed once (read-only), for the latest run asked (a bounded memory).
    states: dict[tuple[int, str, float], np.ndarray] = {}
    targets = list(scenario.targets)

    def truth(run: int, track: str, t: float) -> np.ndarray:
        target = track if track in scenario.targets else (targets[0] if len(targets) == 1 else None)
        if target is None:
            raise KeyError(f"track {track!r} matches no target of {scenario.name}")
        key = (run, target, t)
        x = states.get(key)
        if x is not None:
            return x
        traj = cache.get((run, target))
        if traj is None:
            traj = cache[(run, target)] = truth_trajectory(scenario, target, run=run)
        if len(states) >= TRUTH_STATES_KEPT or (states and next(iter(states))[0] != run):
            states.clear()
        x = states[key] = np.asarray(traj.state(t), dtype=float)
        x.setflags(write=False)
        return x

    return truth


def _errors(e: Estimate, xt: np.ndarray) -> dict:
    n = e.x.size
    xt = np.asarray(xt, dtype=float)
    if n == 4:  # a moving emitter [px py vx vy]; a fix [px py] and a 3D track are the truth's leading parts
        xt = xt[list(TRUTH_INDEX[4])]
    else:
        xt = xt[:n] if xt.size >= n else np.pad(xt, (0, n - xt.size))
    err = e.x - xt
    d = 3 if n >= 6 else 2 if n == 4 else n  # position block: 3D track, moving or fixed 2D emitter
    out: dict = {"t": float(e.t), "n": n, "pos2": float(err[:d] @ err[:d]), "vel2": None, "acc2": None}
    if n == 4:
        out["vel2"] = float(err[2:4] @ err[2:4])
    if n >= 6:
        out["vel2"] = float(err[3:6] @ err[3:6])
    if n >= 9:
        out["acc2"] = float(err[6:9] @ err[6:9])
    try:
        out["nees"] = float(err @ linalg.solve(e.P, err))
    except np.linalg.LinAlgError:
        out["nees"] = math.nan
    out["nis"] = None if e.nis is None else float(e.nis)
    out["nis_dof"] = None if e.nis_dof is None else int(e.nis_dof)
    out["eh"] = (float(err[0]), float(err[1]))  # horizontal error (fix scatter, CEP)
    if n < 6:
        P = np.asarray(e.P, dtype=float)
        out["Ph"] = (float(P[0, 0]), float(P[0, 1]), float(P[1, 1]))
    return out


def score_run(estimates: Sequence[Estimate], truth: TruthFn, run: int, node: str = "centre") -> list[dict]:
    """Error records of one run's estimates from ``node`` (in emission order)."""
    return [_errors(e, truth(run, e.track, e.t)) for e in estimates if e.node == node]


def scan_groups(scenario, sensor_ids: Sequence[str], tol: float) -> list[tuple[float, float, list[str]]]:
    """Scan times of the sensors grouped as the methods group them: ``(first time, last
    time, sensors)`` per group (3D methods stamp a scan with its first time, DF methods
    an epoch with its last)."""
    return list(iter_scan_groups(scenario, sensor_ids, tol))


def iter_scan_groups(scenario, sensor_ids: Sequence[str], tol: float,
                     end: float | None = None) -> Iterator[tuple[float, float, list[str]]]:
    """:func:`scan_groups` lazily, up to ``end`` (default: the scenario's duration; may be
    infinite): a group is yielded once the next scan time is past its tolerance."""
    end = scenario.duration if end is None else end
    def scans(s: str) -> Iterator[tuple[float, str]]:
        sensor = scenario.sensor(s)
        return ((t, s) for t in iter_times(sensor.start, sensor.period, end))

    group: tuple[float, float, list[str]] | None = None
    for t, s in heapq.merge(*map(scans, sensor_ids)):
        if group and t - group[0] <= tol and s not in group[2]:
            group = (group[0], t, group[2] + [s])
        else:
            if group:
                yield group
            group = (t, t, [s])
    if group:
        yield group


def pair_tol_of(scenario, default: float) -> float:
    """The common ``[tracker]`` grouping tolerance (s), else the methods' ``default``."""
    tol = scenario.tracker.get("pair_tol", default)
    return float(tol) if isinstance(tol, (int, float)) else default


# Many targets ------------------------------------------------------------------------
SETTLE_LOOKS = 3  # a target is settled from its third look on (held after initiation)
PICTURE_STEP_S = 1.0  # s between the steps of a scenario with rotating radars


class Looks:
    """When each target was looked at: its scans by any sensor while in coverage,
    detected or not (a rotating radar's beam crossings), the ``n`` first kept. A target
    is *settled* from its ``n``-th look on. Fed with events (:meth:`see`, as the
    evaluation generates the streams), or following the scenario's own streams lazily
    (:meth:`following`)."""

    def __init__(self, n: int = SETTLE_LOOKS):
        self.n = n
        self._times: dict[str, list[float]] = {}  # target -> its first looks, at most n
        self._feeds: list[list] = []  # [event iterator, next event]

    @classmethod
    def following(cls, scenario, run: int = 0, n: int = SETTLE_LOOKS) -> "Looks":
        looks = cls(n)
        for sid in scenario.sensors:
            events = sensor_events(scenario, sid, run)
            looks._feeds.append([events, next(events, None)])
        return looks

    def see(self, ev) -> None:
        """Take one sensor event (:class:`sensors_sim.SensorEvent`)."""
        if ev.in_coverage and not ev.clutter and ev.target:
            times = self._times.setdefault(ev.target, [])
            if len(times) < self.n:
                times.append(ev.t)
                times.sort()
            elif ev.t < times[-1]:
                times[-1] = ev.t
                times.sort()

    def settled(self, truths, t: float) -> frozenset[str]:
        """Of ``truths`` (ids of the targets alive at ``t``), those settled by ``t``.
        Following the streams, it forgets the targets looked at by ``t`` that are no
        longer alive (ids are never reused), so a live run holds only the alive ones."""
        for feed in self._feeds:
            while feed[1] is not None and feed[1].t <= t:
                self.see(feed[1])
                feed[1] = next(feed[0], None)
        if self._feeds:
            for k in [k for k, times in self._times.items() if times[0] <= t and k not in truths]:
                del self._times[k]
        return frozenset(k for k in truths if len(self._times.get(k, ())) == self.n and self._times[k][-1] <= t)


def track_steps(scenario, estimates: Sequence[Estimate], run: int = 0, node: str = "centre",
                looks: Looks | None = None) -> list[Step]:
    """The run as :class:`fusion.mtt_metrics.Step` s: one per scan group of the scenario's
    sensors (as the methods group them, ``pair_tol`` of ``[tracker]``), with every
    target's (and alive ``[traffic]`` aircraft's) true position and every track's estimate
    of that group (a track's last, in ``estimates``' order), or, with rotating radars, the
    picture every second (:class:`PictureSteps`). Emitter fixes are horizontal
    (``[px, py]``): they are scored against the truth's horizontal position. ``looks``:
    the scenario's looks if the caller has them (else they are followed)."""
    steps = step_maker(scenario, run, node, looks=looks)
    if isinstance(steps, PictureSteps):
        out = [step for e in sorted(estimates, key=lambda e: e.t) for step in steps.add(e)]
        return out + steps.close(scenario.duration)
    groups: dict[int, list[Estimate]] = {}
    for e in estimates:
        k = steps.group_of(e)
        if k is not None:
            groups.setdefault(k, []).append(e)
    return steps.close(scenario.duration, groups)


def step_maker(scenario, run: int = 0, node: str = "centre", end: float | None = None,
               looks: Looks | None = None) -> "TrackSteps | PictureSteps":
    """The steps of the scenario's runs, as a stream: :class:`PictureSteps` with rotating
    radars, else :class:`TrackSteps`."""
    rotating = any(getattr(s, "sectors", 0) for s in scenario.sensors.values())
    return (PictureSteps if rotating else TrackSteps)(scenario, run, node, end, looks)


class TrackSteps:
    """The steps of a run (:func:`track_steps`), also as a stream: :meth:`add` takes
    estimates in time order and returns the steps they complete (a scan group is complete
    once an estimate of a later one arrives), :meth:`close` the rest up to a time. The
    stream holds one group's estimates, the groups' start times from it up to the first
    after the newest estimate, and a cursor on the traffic."""

    def __init__(self, scenario, run: int = 0, node: str = "centre", end: float | None = None,
                 looks: Looks | None = None):
        self.node = node
        self.tol = pair_tol_of(scenario, TrackerConfig.pair_tol)
        self._groups = iter_scan_groups(scenario, list(scenario.sensors), self.tol, end)
        self._done = False
        self.starts: list[float] = []  # group start times read, from the current group's on
        self.first = 0  # the current group's index: starts[0]'s
        self.pending: list[Estimate] = []  # the current group's estimates (stream)
        self.trajs = {tid: truth_trajectory(scenario, tid, run) for tid in scenario.targets}
        self.traffic = population(scenario, run)
        self.looks = looks if looks is not None else Looks.following(scenario, run)
        self.dim: int | None = None  # the tracks' position dimension (emitter fixes: 2)
        self.late = 0  # stream: estimates of a group already complete (dropped)

    def _read_to(self, t: float) -> None:
        """Read group starts until one is after ``t`` (or there are no more)."""
        while not self._done and (not self.starts or self.starts[-1] <= t):
            g = next(self._groups, None)
            if g is None:
                self._done = True
            else:
                self.starts.append(g[0])

    def group_of(self, e: Estimate) -> int | None:
        """The index of the scan group ``e`` is an estimate of (None: of none)."""
        if e.node != self.node:
            return None
        self._read_to(e.t + 1e-12)
        k = int(np.searchsorted(self.starts, e.t + 1e-12, side="right")) - 1
        if k < 0:
            self.late += int(self.first > 0)
            return None
        return k + self.first if e.t - self.starts[k] <= self.tol else None

    def add(self, e: Estimate) -> list[Step]:
        """Take the next estimate (in time order); the steps it completes."""
        k = self.group_of(e)
        if k is None:
            return []
        out = [self._next() for _ in range(k - self.first)]
        self.pending.append(e)
        return out

    def close(self, until: float, groups: dict[int, list[Estimate]] | None = None) -> list[Step]:
        """The steps of the groups left that start by ``until``; ``groups``: their
        estimates by group index (else the stream's)."""
        self._read_to(until)
        out = []
        while self.starts and self.starts[0] <= until:
            if groups is not None:
                self.pending = groups.get(self.first, [])
            out.append(self._next())
        return out

    def _next(self) -> Step:
        """The current group's step; the next group becomes current."""
        tracks = {e.track: np.asarray(e.x[:3], dtype=float) for e in self.pending}
        self.dim = min([len(p) for p in tracks.values()] + ([self.dim] if self.dim else []), default=None)
        t, dim = self.starts.pop(0), self.dim or 3
        self.first += 1
        self.pending = []
        truths = truth_positions(self.trajs, self.traffic, t, dim)
        return Step(t, truths, tracks, self.looks.settled(truths, t))


def truth_positions(trajs: dict, traffic: Traffic | None, t: float, dim: int = 3) -> dict[str, np.ndarray]:
    """Every target's and alive aircraft's true position at ``t`` (its first ``dim``)."""
    truths = {tid: tr.position(t)[:dim] for tid, tr in trajs.items()}
    if traffic is not None:
        fleet = traffic.fleet(t)
        truths.update(zip(fleet.ids, fleet.positions(t)[:, :dim]))
    return truths


class PictureSteps:
    """The steps of a run with rotating radars, as a stream: at ``k·PICTURE_STEP_S`` up to
    the end, the picture a display would show: each track's latest estimate at or before
    the step, at most ``max_age`` old (the longest sensor period: a track no sensor has
    updated for a turn of the slowest is gone), moved to the step's time along its
    velocity. :meth:`add` takes estimates in time order and returns the steps they
    complete (a step is complete once an estimate after it arrives), :meth:`close` the
    rest up to a time. It holds one estimate per live track."""

    def __init__(self, scenario, run: int = 0, node: str = "centre", end: float | None = None,
                 looks: Looks | None = None):
        self.node = node
        self.end = scenario.duration if end is None else end
        self.max_age = max(s.period for s in scenario.sensors.values())
        self.trajs = {tid: truth_trajectory(scenario, tid, run) for tid in scenario.targets}
        self.traffic = population(scenario, run)
        self.looks = looks if looks is not None else Looks.following(scenario, run)
        self.k = 0  # the next step's index
        self.latest: dict[str, Estimate] = {}
        self.late = 0  # stream: estimates older than a step already out (scored from the next)

    def add(self, e: Estimate) -> list[Step]:
        if e.node != self.node:
            return []
        out = []
        while self.k * PICTURE_STEP_S < e.t and self.k * PICTURE_STEP_S <= self.end:
            out.append(self._next())
        if e.t < (self.k - 1) * PICTURE_STEP_S:
            self.late += 1
        self.latest[e.track] = e
        return out

    def close(self, until: float, groups=None) -> list[Step]:
        out = []
        while self.k * PICTURE_STEP_S <= min(until, self.end):
            out.append(self._next())
        return out

    def _next(self) -> Step:
        t = self.k * PICTURE_STEP_S
        self.k += 1
        self.latest = {k: e for k, e in self.latest.items() if t - e.t <= self.max_age}
        tracks = {k: np.asarray(e.x[:3], dtype=float) + np.asarray(e.x[3:6], dtype=float) * (t - e.t)
                  for k, e in self.latest.items() if e.t <= t}
        truths = truth_positions(self.trajs, self.traffic, t)
        return Step(t, truths, tracks, self.looks.settled(truths, t))


GOSPA_CUTOFF = 1000.0  # m: GOSPA's c, order p = 2, for every many-target score


def many_targets(scenario) -> bool:
    """Scored as an air picture (set metrics) rather than per target."""
    return len(scenario.targets) > 1 or getattr(scenario, "traffic", None) is not None


def score_tracks_of(scenario, estimates: Sequence[Estimate], run: int = 0, c: float = GOSPA_CUTOFF,
                    p: float = 2.0, looks: Looks | None = None):
    """A run's fused tracks scored by :func:`fusion.mtt_metrics.score_tracks`."""

    return score_tracks(track_steps(scenario, estimates, run, looks=looks), c, p)


def region_crossings(scenario, run: int = 0) -> int:
    """The run's aircraft passing from one of the scenario's ``[regions]`` into another,
    at the steps a many-target run is scored at (:class:`fusion.regions.Crossings`)."""
    crossings = Crossings(scenario.regions)
    for step in track_steps(scenario, [], run, looks=Looks()):
        crossings.add(step.truths)
    return crossings.count


# The recorder's panels ---------------------------------------------------------------------

TRUTH_CACHE = 4096  # truth samples kept per target, to score estimates against
PENDING_MAX = 4096  # estimates waiting for the truth sample of their time (and open frames per method)


@dataclass(frozen=True)
class Scored:
    """One value for a panel: ``metric`` (``error_pos``, ``nees``, ``nis``, ``gospa``,
    ``missed``, ``false``) of the estimates ``prefix`` names (``(method,)`` fused,
    ``(method, node)`` a local track) at ``t``; ``dof`` and ``bounds`` for a NEES or NIS
    (the 95 % interval of one χ² sample)."""

    metric: str
    prefix: tuple[str, ...]
    t: float
    value: float
    dof: int | None = None
    bounds: tuple[float, float] | None = None


class LiveScore:
    """Estimates scored against the truth as both arrive, in any order (the recorder's
    panels; it draws what this hands back).

    One target per track: each estimate's position error and NEES, once the truth sample
    of its time is in (an estimate waits for it, at most ``PENDING_MAX`` of them; one
    older than the ``TRUTH_CACHE`` samples kept of its target is ``unscored``). Many
    targets (``many``; None: judged from the truth, more than one target seen): the fused
    tracks of each time are a frame, scored with GOSPA (cut-off :data:`GOSPA_CUTOFF`,
    order 2) against every target present at that time, once a later truth frame shows
    the truth of its time is complete. Every NIS is handed back as it comes.
    """

    def __init__(self, many: bool | None = None):
        self.many = many
        self.unscored = 0  # estimates older than the truth kept of their target: drawn, never scored
        self._truth: dict[str, OrderedDict[float, np.ndarray]] = {}
        self._truth_t = -math.inf  # the latest truth frame's time
        self._pending: OrderedDict[float, list[tuple[Estimate, tuple[str, ...]]]] = OrderedDict()
        self._n_pending = 0
        # many targets: per method, its frames not scored yet (time -> fused positions) and its state size
        self._frames: dict[str, OrderedDict[float, list[np.ndarray]]] = {}
        self._size: dict[str, int] = {}

    def truth(self, target: str, t: float, x: np.ndarray) -> list[Scored]:
        """A truth sample: what it lets be scored."""
        self._truth_t = max(self._truth_t, t)
        cache = self._truth.setdefault(target, OrderedDict())
        cache[t] = x
        while len(cache) > TRUTH_CACHE:
            cache.popitem(last=False)
        out: list[Scored] = []
        waiting = self._pending.get(t)
        if waiting:
            keep = []
            for e, prefix in waiting:
                if e.track == target or (e.track not in self._truth and len(self._truth) == 1):
                    out += self._score(e, prefix, x)
                    self._n_pending -= 1
                else:
                    keep.append((e, prefix))
            if keep:
                self._pending[t] = keep
            else:
                del self._pending[t]
        if self._frames:
            out += self._score_frames()
        return out

    def forget(self, target: str) -> None:
        """``target`` has left: its truth samples go."""
        self._truth.pop(target, None)

    def estimate(self, e: Estimate, fused: bool) -> list[Scored]:
        """An estimate (``fused``: of the centre): what it lets be scored now."""
        prefix = (e.method,) if fused else (e.method, e.node)
        out = []
        if e.nis is not None and e.nis_dof:
            out.append(Scored("nis", prefix, e.t, float(e.nis), int(e.nis_dof), chi2_interval(int(e.nis_dof))))
        if TRUTH_INDEX.get(e.x.size) is None:
            return out
        if self.many or (self.many is None and len(self._truth) > 1):
            if fused:
                frames = self._frames.setdefault(e.method, OrderedDict())
                self._size[e.method] = e.x.size
                frames.setdefault(e.t, []).append(e.x[:position_dims(e.x.size)].astype(float))
                while len(frames) > PENDING_MAX:  # no truth is coming
                    frames.popitem(last=False)
                out += self._score_frames()
            return out
        truth = self._truth.get(e.track)
        if truth is None and len(self._truth) == 1:
            truth = next(iter(self._truth.values()))
        if truth is not None and e.t in truth:
            return out + self._score(e, prefix, truth[e.t])
        if truth is not None and len(truth) >= TRUTH_CACHE and e.t < next(iter(truth)):
            self.unscored += 1  # its truth came and was forgotten (the truth far ahead, at --speed max)
            return out
        self._pending.setdefault(e.t, []).append((e, prefix))
        self._n_pending += 1
        while self._n_pending > PENDING_MAX:
            _, dropped = self._pending.popitem(last=False)
            self._n_pending -= len(dropped)
        return out

    def finish(self) -> list[Scored]:
        """The end: the frames still open, scored."""
        return self._score_frames(final=True)

    @staticmethod
    def _score(e: Estimate, prefix: tuple[str, ...], x_truth: np.ndarray) -> list[Scored]:
        ref = truth_part(x_truth, e.x.size)
        if ref is None:
            return []
        err = e.x - ref
        d = position_dims(e.x.size)
        out = [Scored("error_pos", prefix, e.t, float(np.linalg.norm(err[:d])))]
        try:
            nees = float(err @ np.linalg.solve(e.P, err))
        except np.linalg.LinAlgError:
            return out
        if math.isfinite(nees):
            out.append(Scored("nees", prefix, e.t, nees, e.x.size, chi2_interval(e.x.size)))
        return out

    def _truth_at(self, t: float) -> list[np.ndarray] | None:
        """The truth of every target present at ``t`` (one whose samples start after ``t`` or
        end before it is not), or None if a target whose samples span ``t`` lacks it (lost)."""
        out = []
        for cache in self._truth.values():
            x = cache.get(t)
            if x is not None:
                out.append(x)
            elif cache and next(iter(cache)) < t < next(reversed(cache)):
                return None
        return out

    def _score_frames(self, final: bool = False) -> list[Scored]:
        """Every complete frame whose truth is in, scored; one whose time the truth has
        passed without a sample dropped."""
        out = []
        for method, frames in self._frames.items():
            n = self._size[method]
            while len(frames) > (0 if final else 1) and self._truth:
                t = next(iter(frames))
                if not final and self._truth_t <= t:
                    break  # the truth of this time is still to come (a later truth frame closes it)
                truths = self._truth_at(t)
                if not truths:  # a sample lost, or no truth of that time: not scored
                    frames.popitem(last=False)
                    continue
                refs = [truth_part(x, n) for x in truths]
                d = position_dims(n)
                g = gospa(frames.popitem(last=False)[1], [r[:d] for r in refs if r is not None], GOSPA_CUTOFF, 2.0)
                out += [Scored("gospa", (method,), t, g.distance), Scored("missed", (method,), t, float(g.n_missed)),
                        Scored("false", (method,), t, float(g.n_false))]
        return out
