"""The ``--json`` summary (docs/design.md) from scored estimates (:mod:`services.scoring`).

Shared by ``zfusion run`` (one run, estimates received over Zenoh) and ``zfusion eval``
(many in-process Monte Carlo runs), so both report the same numbers the same way.

Scoring is two steps: :func:`services.scoring.score_run` turns one run's estimates into
per-estimate error records (so a Monte Carlo worker returns a few numbers per estimate
instead of the estimates), and :func:`aggregate` turns the records of all runs into one method's
summary; :func:`method_summary` does both. Per method, beside the contract's fields
(``rmse_pos``/``rmse_vel``/``rmse_acc``: ``√mean‖e‖²`` over every scored estimate of
every run; ``cep50``: the median horizontal miss of the final fixes; ``anees``: mean
``eᵀP⁻¹e``; ``series``):

``nees_dof``, ``anees_bounds``
    the state dimension and the 95 % χ² interval of a per-step average over ``runs``.
``median_point_distance``
    emitter fixes only: the thesis's "CEP 50 %", the distance from truth to the
    coordinate-wise median of the final fixes (a bias measure, not a radius).
``anis_per_dof``
    ``ΣNIS / Σdof`` over the updates that report an NIS (1 for a consistent filter).
``final``, ``second_half``
    the last estimate of each run; the estimates with ``t ≥ (t_first + t_last)/2``.

``series`` has at most ``SERIES_MAX`` points: a longer run's output times are binned
(:func:`_series`; the bin size is then given as ``series.bin``).

One run (``zfusion run``, ``zfusion fuser --json``) is scored by :class:`RunScorer`, in
one place: a scenario run by the batch above; a live run, open-ended, by settling its
estimates as they age into a :class:`Running` (the same sums, folded in), so the launcher
holds a window of estimates and ``SERIES_MAX`` points however long it runs. A process
lost during the run (killed: ``zfusion run``'s ``outages``) is followed through the same
steps (:class:`fusion.absence.LossWatch`): its outage in the summary says how long the
aircraft the picture held at the loss were absent from it (:meth:`RunScorer.loss`).
"""

from __future__ import annotations

import dataclasses
import math
from collections import defaultdict
from typing import Sequence

import numpy as np

from fusion.absence import LossWatch, loss_counts
from fusion.binning import BinnedSeries
from fusion.metrics import chi2_bounds, median_point_distance
from fusion.mtt_metrics import Step, TrackScorer
from fusion.types import Estimate

from .scoring import (GOSPA_CUTOFF, TruthFn, many_targets, score_run, score_tracks_of, step_maker, track_steps,
                      truth_function)


def _rms(values: Sequence[float | None]) -> float | None:
    vals = [v for v in values if v is not None]
    return float(math.sqrt(sum(vals) / len(vals))) if vals else None


def _mean(values) -> float | None:
    vals = [v for v in values if v is not None and math.isfinite(v)]
    if len(vals) < len([v for v in values if v is not None]):
        return None  # a NaN NEES (singular P) makes the average meaningless
    return float(np.mean(vals)) if vals else None


SERIES_MAX = 3600  # points of a summary series; a longer run's are binned (see _series)
FORGET_STEPS = 600  # a live many-target score forgets a target or track absent from this many steps


def _series(per_t: dict[float, list[dict]], ts: list[float]) -> dict:
    """Per output time: RMSEs, ANEES, mean NIS and dof, estimates. Beyond ``SERIES_MAX``
    times (a run of hours), consecutive times are binned ``k = ⌈len/SERIES_MAX⌉`` at a
    time, each bin stamped with its last time and scored over all its estimates, so the
    summary of a long run stays bounded; the overall figures are computed from every
    estimate regardless."""
    k = max(1, math.ceil(len(ts) / SERIES_MAX))
    bins = [(ts[min(i + k, len(ts)) - 1], [e for t in ts[i:i + k] for e in per_t[t]]) for i in range(0, len(ts), k)]
    return {
        "t": [t for t, _ in bins],
        "rmse_pos": [_rms([e["pos2"] for e in b]) for _, b in bins],
        "rmse_vel": [_rms([e["vel2"] for e in b]) for _, b in bins],
        "rmse_acc": [_rms([e["acc2"] for e in b]) for _, b in bins],
        "anees": [_mean([e["nees"] for e in b]) for _, b in bins],
        "anis": [_mean([e["nis"] for e in b if e["nis"] is not None]) for _, b in bins],
        "nis_dof": [_mean([e["nis_dof"] for e in b if e["nis_dof"]]) for _, b in bins],
        "n": [len(b) for _, b in bins],
        **({"bin": k} if k > 1 else {}),
    }


def aggregate(runs: Sequence[Sequence[dict]]) -> dict:
    """One method's summary from the :func:`score_run` records of every run."""
    per_t: dict[float, list[dict]] = defaultdict(list)
    all_err: list[dict] = []
    finals: list[dict] = []
    for records in runs:
        for er in records:
            per_t[er["t"]].append(er)
            all_err.append(er)
        if records:
            finals.append(records[-1])
    is_fix = bool(all_err) and all_err[-1]["n"] < 6
    ts = sorted(per_t)
    dof = all_err[-1]["n"] if all_err else None
    nis_pairs = [(e["nis"], e["nis_dof"]) for e in all_err if e["nis"] is not None and e["nis_dof"]]
    out = {
        "rmse_pos": _rms([e["pos2"] for e in all_err]),
        "rmse_vel": _rms([e["vel2"] for e in all_err]),
        "rmse_acc": _rms([e["acc2"] for e in all_err]),
        "cep50": None,
        "anees": _mean([e["nees"] for e in all_err]),
        "n_updates": len(all_err),
        "series": _series(per_t, ts),
        "nees_dof": dof,
        "anees_bounds": list(chi2_bounds(dof, len(runs))) if dof else None,
        "anis_per_dof": float(sum(n for n, _ in nis_pairs) / sum(d for _, d in nis_pairs)) if nis_pairs else None,
        "median_point_distance": None,
        "final": None,
    }
    if ts:
        # the second half of the run's output times: the filters' steady state, free of the
        # start-up transient (the first estimate is the initialiser's, e.g. velocity 0)
        t_half = 0.5 * (ts[0] + ts[-1])
        late = [e for e in all_err if e["t"] >= t_half]
        out["second_half"] = {"from_t": t_half, "rmse_pos": _rms([e["pos2"] for e in late]),
                              "rmse_vel": _rms([e["vel2"] for e in late]),
                              "rmse_acc": _rms([e["acc2"] for e in late]),
                              "anees": _mean([e["nees"] for e in late])}
    _finals(out, finals, is_fix)
    return out


def _finals(out: dict, finals: list[dict], is_fix: bool) -> None:
    """The fields of a method summary ``out`` read from each run's last record: ``final``,
    and for emitter fixes ``cep50`` (median horizontal miss) and the fixes' spread."""
    out["cep50"] = float(np.median([math.hypot(*f["eh"]) for f in finals])) if is_fix and finals else None
    out["final"] = {
        "t": _mean([f["t"] for f in finals]),
        "rmse_pos": _rms([f["pos2"] for f in finals]),
        "rmse_vel": _rms([f["vel2"] for f in finals]),
        "rmse_acc": _rms([f["acc2"] for f in finals]),
        "n_runs": len(finals),
    }
    if is_fix and finals:
        err = np.array([f["eh"] for f in finals])
        out["median_point_distance"] = median_point_distance(err, np.zeros(2))
        Ph = np.mean([f["Ph"] for f in finals], axis=0)
        out["final"]["err"] = err.tolist()
        out["final"]["P_mean"] = [[Ph[0], Ph[1]], [Ph[1], Ph[2]]]
        out["final"]["mse_pos"] = float(np.mean(np.sum(err**2, axis=1)))


_KEYS = ("pos2", "vel2", "acc2", "nees", "nis", "nis_dof")
_MEANS = ("nees", "nis", "nis_dof")  # averaged (a non-finite value voids the average); the rest are RMS'd


class _Sums:
    """Sum and count of each field of a set of error records, as :func:`_rms` and
    :func:`_mean` read them (``None`` skipped; for a mean, a non-finite value voids it)."""

    __slots__ = ("n", "s", "c", "bad")

    def __init__(self) -> None:
        self.n = 0
        self.s = dict.fromkeys(_KEYS, 0.0)
        self.c = dict.fromkeys(_KEYS, 0)
        self.bad = dict.fromkeys(_MEANS, 0)

    def add(self, er: dict) -> None:
        self.n += 1
        for key in _KEYS:
            v = er[key]
            if v is None or (key == "nis_dof" and not v):
                continue
            self.c[key] += 1
            if key in self.bad and not math.isfinite(v):
                self.bad[key] += 1
            else:
                self.s[key] += v

    def merge(self, other: "_Sums") -> None:
        self.n += other.n
        for key in _KEYS:
            self.s[key] += other.s[key]
            self.c[key] += other.c[key]
        for key in _MEANS:
            self.bad[key] += other.bad[key]

    def rms(self, key: str) -> float | None:
        return float(math.sqrt(self.s[key] / self.c[key])) if self.c[key] else None

    def mean(self, key: str) -> float | None:
        return None if self.bad[key] or not self.c[key] else float(self.s[key] / self.c[key])


class Running:
    """One run's :func:`aggregate`, folded in record by record (records in time order), in
    memory bounded by ``SERIES_MAX`` whatever the run's length: running sums for the
    overall figures, and per series point the sums of its output times.

    A sum is accumulated in the order the batch takes its records, so ``rmse_*``,
    ``anis_per_dof``, ``n_updates`` and ``final`` are :func:`aggregate`'s to the bit. A
    mean (``anees``) is the sequential sum over the count, where :func:`aggregate` takes
    NumPy's pairwise mean: equal up to rounding. The series: with at most ``SERIES_MAX``
    output times, one point a time as in :func:`aggregate`; beyond, two neighbouring
    points are merged whenever there would be more, so ``series.bin`` is a power of two
    (:func:`aggregate` bins ``⌈n / SERIES_MAX⌉`` times, knowing ``n``). ``second_half``
    is summed over the points stamped at or after its ``from_t``: exact with one point a
    time, to within one point otherwise.
    """

    def __init__(self) -> None:
        self.total = _Sums()
        self.series: BinnedSeries[_Sums] = BinnedSeries(SERIES_MAX, _Sums, _Sums.merge)  # a point: output times
        self.t_first: float | None = None
        self.last: dict | None = None  # the latest record: the run's final
        self._nis = 0.0  # ΣNIS and Σdof over the records that give both
        self._dof = 0

    def add(self, er: dict) -> None:
        t = er["t"]
        self.total.add(er)
        if self.t_first is None:
            self.t_first = t
        new_time = not self.series or t > self.series.last_t
        (self.series.sample(t) if new_time else self.series.last).add(er)
        if er["nis"] is not None and er["nis_dof"]:
            self._nis += er["nis"]
            self._dof += er["nis_dof"]
        self.last = er

    def summary(self) -> dict:
        """The method summary, as :func:`aggregate` gives it for this one run."""
        tot, last = self.total, self.last
        dof = last["n"] if last else None
        pts = self.series.points
        out = {
            "rmse_pos": tot.rms("pos2"), "rmse_vel": tot.rms("vel2"), "rmse_acc": tot.rms("acc2"),
            "cep50": None,
            "anees": tot.mean("nees"),
            "n_updates": tot.n,
            "series": {
                "t": [p[0] for p in pts],
                "rmse_pos": [p[2].rms("pos2") for p in pts],
                "rmse_vel": [p[2].rms("vel2") for p in pts],
                "rmse_acc": [p[2].rms("acc2") for p in pts],
                "anees": [p[2].mean("nees") for p in pts],
                "anis": [p[2].mean("nis") for p in pts],
                "nis_dof": [p[2].mean("nis_dof") for p in pts],
                "n": [p[2].n for p in pts],
                **({"bin": self.series.bin} if self.series.bin > 1 else {}),
            },
            "nees_dof": dof,
            "anees_bounds": list(chi2_bounds(dof, 1)) if dof else None,
            "anis_per_dof": float(self._nis / self._dof) if self._dof else None,
            "median_point_distance": None,
            "final": None,
        }
        if pts:
            t_half = 0.5 * (self.t_first + pts[-1][0])
            late = _Sums()
            for p in pts:
                if p[0] >= t_half:
                    late.merge(p[2])
            out["second_half"] = {"from_t": t_half, "rmse_pos": late.rms("pos2"), "rmse_vel": late.rms("vel2"),
                                  "rmse_acc": late.rms("acc2"), "anees": late.mean("nees")}
        _finals(out, [last] if last else [], last is not None and last["n"] < 6)
        return out


def method_summary(runs: Sequence[Sequence[Estimate]], truth: TruthFn, node: str = "centre") -> dict:
    """Metrics of one method over Monte Carlo runs (each a list of its fused estimates)."""
    return aggregate([score_run(estimates, truth, r, node) for r, estimates in enumerate(runs)])


def tracks_summary(scores: Sequence) -> dict:
    """Metrics of one many-target method over Monte Carlo runs, each a
    :class:`fusion.mtt_metrics.TrackScore`. The per-target fields of docs/design.md do not apply
    (null); the set metrics do: mean GOSPA (and its per-step series, averaged over runs
    when the runs share their steps), held fraction, breaks, purity, false tracks."""
    same_steps = all(s.t == scores[0].t for s in scores)
    gospa = np.mean([s.gospa for s in scores], axis=0) if same_steps else np.asarray(scores[0].gospa)
    run = type(scores[0]).merged(scores)
    finite = lambda v: float(v) if math.isfinite(v) else None  # noqa: E731  (no steps: no rate)
    return {
        "rmse_pos": None, "rmse_vel": None, "rmse_acc": None, "cep50": None, "anees": None,
        "n_updates": run.track_steps,
        "series": {"t": list(scores[0].t), "gospa": [float(g) for g in gospa],
                   **({"bin": run.bin} if run.bin > 1 else {})},
        "gospa": finite(run.mean_gospa),
        "held": finite(run.held),
        "held_after_init": finite(run.held_after_init),
        "rmse_pos_assigned": finite(run.rmse_pos_assigned),
        "breaks": run.breaks,
        "break_rate": run.break_rate,
        "purity": finite(run.purity),
        "worst_hold": finite(run.worst_hold),
        "longest_ghost": run.max_ghost,
        "longest_ghost_per_run": [int(g) for g in run.longest_ghost],
        "all_found_runs": run.all_found_runs,
        "found_at_end_per_run": [float(f) for f in run.found_at_end],
        "tracks": run.n_tracks,
        "false_tracks": run.false_tracks,
        "duplicates": run.duplicates,
        "id_changes": run.id_changes,
        "steps": run.steps,
    }


def scenario_times(estimates: Sequence[Estimate], epoch: float) -> list[Estimate]:
    """A live run's fused estimates (UTC ``t``) on scenario time (``t − epoch``), the
    latest of each ``(node, track, t)`` only: after a re-filtering the fuser re-publishes
    corrected estimates of times it has published already (docs/live.md)."""
    latest: dict[tuple, Estimate] = {}
    for e in estimates:
        latest.pop((e.node, e.track, e.t), None)
        latest[(e.node, e.track, e.t)] = e
    return sorted((dataclasses.replace(e, t=e.t - epoch) for e in latest.values()), key=lambda e: e.t)


def on_time_base(method: dict, epoch: float) -> dict:
    """A method summary scored on scenario time, with its times moved to the UTC base."""
    out = dict(method)
    series = dict(out.get("series", {}))
    series["t"] = [epoch + t for t in series.get("t", [])]
    out["series"] = series
    if out.get("final", {}).get("t") is not None:
        out["final"] = {**out["final"], "t": epoch + out["final"]["t"]}
    if "second_half" in out:
        out["second_half"] = {**out["second_half"], "from_t": epoch + out["second_half"]["from_t"]}
    return out


class RunScorer:
    """One run's fused estimates, scored against truth into its method summary as they
    arrive: what ``zfusion run`` and ``zfusion fuser --json`` report (:func:`run_summary`).

    A scenario run is finite: its estimates are kept, and scored at its end by
    :func:`method_summary` (or, many targets, :func:`tracks_summary`), in the order they came.

    A live run (``epoch``: its UTC time of scenario time 0) is open-ended. A re-filtering
    re-publishes corrected estimates of times already published (docs/live.md), so an
    estimate is *pending* — the latest of its ``(node, track, t)`` replaces it — until it
    is ``settle_s`` older than the newest one (the OOSM window plus the fuser's maximum
    delay: nothing older is re-published). Then it *settles*: the pending estimates older
    than that, in time order, are scored on scenario time and folded into a
    :class:`Running` (one target), or cut into steps (:class:`services.scoring.TrackSteps`)
    folded into a :class:`fusion.mtt_metrics.TrackScorer` (many targets; a target or
    track absent from ``FORGET_STEPS`` steps is closed and forgotten). So a live run holds
    at most ``settle_s`` of estimates, ``SERIES_MAX`` series points and, many targets, the
    recent targets and tracks, and its summary is the batch's on :func:`scenario_times` of
    the same estimates (one target: the sums to the bit, means to rounding,
    :class:`Running`; many: the same, but for the forgotten targets' hold fractions, of
    which only the least is kept).
    """

    def __init__(self, scenario, epoch: float | None = None, settle_s: float = math.inf, node: str = "centre"):
        self.scenario = scenario
        self.epoch = epoch
        self.settle_s = settle_s
        self.node = node
        self.many = many_targets(scenario)
        self.truth = truth_function(scenario)
        self.n = 0  # estimates received
        self.latest: float | None = None  # the newest estimate's t (on the wire's time base)
        self.last_t: float | None = None  # the last one's
        self.kept: list[Estimate] = []  # a scenario run's estimates
        self.pending: dict[tuple, Estimate] = {}  # live: the latest estimate of each (node, track, t), unsettled
        self.running = Running()
        self.steps = step_maker(scenario, node=node, end=math.inf) if self.many and epoch is not None else None
        self.tracks = TrackScorer(GOSPA_CUTOFF, forget_after=FORGET_STEPS, series_max=SERIES_MAX)
        self.settled_before = -math.inf  # live: what is older than this has settled
        self.late = 0  # live: estimates that came after their time had settled (scored as they come)
        self.losses: dict[str, list[LossWatch]] = {}  # each lost process's losses, in order

    def lose(self, process: str, at: float) -> None:
        """``process`` was lost at scenario time ``at``: follow the aircraft of its region
        (its polygon and margin; the whole picture if it is no region's fuser) held in the
        :func:`radar_period` before it, from the steps not scored yet (a live run's
        settle well after a kill is seen)."""
        region = self.scenario.regions.get(process)
        watch = LossWatch(at, None if region is None else region.holds, at - radar_period(self.scenario, process))
        self.losses.setdefault(process, []).append(watch)

    def loss(self, process: str, k: int = 0) -> dict:
        """The ``k``-th loss of ``process`` (:func:`fusion.absence.loss_counts`), against
        :func:`radar_period`; once :meth:`method_summary` has scored the run."""
        return loss_counts(self.losses[process][k].absences(), radar_period(self.scenario, process))

    def _fold(self, step: Step) -> None:
        """Score one many-target step, and show it to the losses."""
        held = self.tracks.add(step)
        for watch in self._watches():
            watch.step(step.t, step.truths, held)

    def _fold_one(self, e: Estimate) -> dict:
        """One target's estimate (scenario time) scored; shown to the losses as a step of
        the target, held if within the many-target cut-off of its truth."""
        record = score_run([e], self.truth, 0, self.node)[0]
        if self.losses:
            truth = {e.track: self.truth(0, e.track, e.t)[:3]}
            held = [e.track] if math.sqrt(record["pos2"]) < GOSPA_CUTOFF else []
            for watch in self._watches():
                watch.step(e.t, truth, held)
        return record

    def _watches(self) -> list[LossWatch]:
        return [w for ws in self.losses.values() for w in ws]

    def add(self, e: Estimate) -> None:
        self.n += 1
        self.last_t = e.t
        self.latest = e.t if self.latest is None else max(self.latest, e.t)
        if self.epoch is None:
            self.kept.append(e)
            return
        key = (e.node, e.track, e.t)
        self.pending.pop(key, None)
        self.pending[key] = e
        if e.t < self.settled_before:
            self.late += 1
        if self.latest - self.settle_s > self.settled_before + 1.0:  # settle about once a second of data
            self.settle(self.latest - self.settle_s)

    def settle(self, before: float = math.inf) -> None:
        """Score and fold in the pending estimates older than ``before`` (all: the run's end)."""
        old = [e for key, e in self.pending.items() if e.t < before or e.t < self.settled_before]
        for e in old:
            del self.pending[(e.node, e.track, e.t)]
        self.settled_before = max(self.settled_before, before)
        for e in sorted((dataclasses.replace(e, t=e.t - self.epoch) for e in old), key=lambda e: e.t):
            if e.node != self.node:
                continue
            if self.many:
                for step in self.steps.add(e):
                    self._fold(step)
            else:
                self.running.add(self._fold_one(e))

    def played(self) -> float:
        """The scenario time of the newest estimate (0 before any)."""
        return 0.0 if self.latest is None else self.latest - (self.epoch or 0.0)

    def method_summary(self, scenario=None) -> dict:
        """The run's method summary (live: on the UTC time base). ``scenario``: the one to
        score many targets on (live: cut to the time played), if not the run's."""
        scenario = scenario or self.scenario
        if self.epoch is None:
            if not self.losses:
                return (tracks_summary([score_tracks_of(scenario, self.kept)]) if self.many
                        else method_summary([self.kept], self.truth, self.node))
            if not self.many:
                for e in sorted((e for e in self.kept if e.node == self.node), key=lambda e: e.t):
                    self._fold_one(e)
                return method_summary([self.kept], self.truth, self.node)
            self.tracks = TrackScorer(GOSPA_CUTOFF)  # score_tracks_of's, with the losses shown each step
            self.losses = {p: [LossWatch(w.at, w.area, w.since) for w in ws] for p, ws in self.losses.items()}
            for step in track_steps(scenario, self.kept, node=self.node):
                self._fold(step)
            return tracks_summary([self.tracks.score()])
        self.settle()
        if self.many:
            for step in self.steps.close(scenario.duration):
                self._fold(step)
        scored = tracks_summary([self.tracks.score()]) if self.many else self.running.summary()
        return on_time_base(scored, self.epoch)



def radar_period(scenario, process: str) -> float:
    """The period against which a loss's absences are judged (``period_s``): the slowest
    radar's of the lost process's region (a regional fuser's; any other process: of the
    scenario), the longest an aircraft the region's radars cover waits between two looks;
    without radars, the slowest sensor's."""
    region = scenario.regions.get(process)
    sensors = [scenario.sensors[s] for s in (region.sensors if region is not None else scenario.sensors)]
    radars = [s for s in sensors if s.kind.startswith("radar")] or sensors
    return float(max(s.period for s in radars))


def run_summary(scenario, topology: str, method: str, fusion_rule: str | None, scored: dict,
                sources: dict) -> dict:
    """The summary of one run (``zfusion run``, ``zfusion fuser --json``) from its method
    summary (:meth:`RunScorer.method_summary`)."""
    doc = summary(scenario, topology, fusion_rule, scenario.seed, 1, {method: scored}, sources=sources)
    if many_targets(scenario):
        doc["gospa_cutoff"] = GOSPA_CUTOFF
    return doc


def summary(scenario, topology: str, fusion_rule: str | None, seed: int, runs: int,
            methods: dict[str, dict], sources: dict | None = None, crb: dict | None = None) -> dict:
    return {
        "scenario": scenario.name,
        "topology": topology,
        "fusion_rule": fusion_rule,
        "seed": seed,
        "runs": runs,
        "methods": methods,
        "crb": crb or {"t": [], "rmse_pos": []},
        "sources": sources or {},
    }


def _fmt(v: float | None, w: int = 10) -> str:
    """A table cell of width ``w``, always with a space before it: four decimals below
    1000, one up to 10^6, else a power of ten (columns never run together)."""
    if v is None or not math.isfinite(v):
        return f"{'—':>{w}}"
    if v != 0.0 and (abs(v) >= 1e6 or abs(v) < 1e-3):
        return f" {v:>{w - 1}.3e}"
    return f" {v:>{w - 1}.{4 if abs(v) < 1000 else 1}f}"


def format_table(doc: dict) -> str:
    """The summary as a fixed-width table for the terminal (the source documents' table shape:
    one row per method, RMSE of position / velocity / acceleration or CEP, NEES beside)."""
    methods = doc["methods"]
    any_fix = any(m.get("median_point_distance") is not None for m in methods.values())
    width = max([10, *(len(n) + 2 for n in methods)])
    head = f"{'method':<{width}}{'rmse_pos':>10}{'rmse_vel':>10}{'rmse_acc':>10}{'cep50':>10}"
    head += f"{'median_pt':>10}" if any_fix else ""
    head += f"{'anees':>10}{'updates':>9}"
    rule = f" · fusion rule {doc['fusion_rule']}" if doc.get("fusion_rule") else ""
    lines = [f"scenario {doc['scenario']} · topology {doc['topology']}{rule} · seed {doc['seed']} · runs {doc['runs']}",
             head]
    for name, m in methods.items():
        row = f"{name:<{width}}{_fmt(m['rmse_pos'])}{_fmt(m['rmse_vel'])}{_fmt(m['rmse_acc'])}{_fmt(m['cep50'])}"
        row += _fmt(m.get("median_point_distance")) if any_fix else ""
        row += f"{_fmt(m['anees'])}{m['n_updates']:>9d}"
        lines.append(row)
    crb = doc.get("crb") or {}
    overall = crb.get("overall")
    if overall:
        row = f"{'CRB':<{width}}{_fmt(overall['rmse_pos'])}{_fmt(overall['rmse_vel'])}{_fmt(overall['rmse_acc'])}"
        row += _fmt(crb.get("cep50")) + (_fmt(None) if any_fix else "")
        note = ("Cramér–Rao bound on the same RMSE, from the trackers' start-up prior; it averages over that "
                "prior, so in the first scans (velocity, acceleration) a filter can beat it: "
                "docs/algorithms.md, Posterior bound")
        if crb.get("cep50") is not None:
            note += "; cep50: the bound's Gaussian CEP50 at the last epoch"
        lines += [row, f"CRB: {note}"]
    bounds = {tuple(m["anees_bounds"]) + (m["nees_dof"],) for m in methods.values() if m.get("anees_bounds")}
    for lo, hi, dof in sorted(bounds, key=lambda b: b[2]):
        lines.append(f"per-step ANEES 95 % interval for {doc['runs']} runs, dof {dof}: [{lo:.3f}, {hi:.3f}]")
    if any_fix:
        lines.append("cep50: median miss of the final fixes (textbook CEP radius); median_pt: the thesis's "
                     "'CEP 50 %' (distance of the median point from truth)")
    many = {n: m for n, m in methods.items() if "gospa" in m}
    if many:
        lines.append(f"{'tracks':<{width}}{'gospa':>10}{'held':>10}{'min hold':>10}{'breaks':>10}{'brk rate':>10}"
                     f"{'purity':>10}{'tracks':>10}{'false':>10}{'ghost':>10}{'all found':>10}   (GOSPA p = 2, "
                     f"cut-off {doc.get('gospa_cutoff', '—')} m)")
        for name, m in many.items():
            lines.append(f"{name:<{width}}{_fmt(m['gospa'])}{_fmt(m['held'])}{_fmt(m.get('worst_hold'))}"
                         f"{m['breaks']:>10d}{_fmt(m['break_rate'])}{_fmt(m['purity'])}"
                         f"{m['tracks']:>10d}{m['false_tracks']:>10d}{m.get('longest_ghost', 0):>10d}"
                         f"{m.get('all_found_runs', 0):>7d}/{doc['runs']:<2d}")
        lines.append("min hold: the least fraction of steps a target was held from the first (any run); "
                     "ghost: the most consecutive steps a track spent on no target; all found: runs whose last "
                     "step held every target")
    for src, s in doc.get("sources", {}).items():
        if s.get("dead_intervals") or s.get("rejected"):
            lines.append(f"source {src}: dead {s.get('dead_intervals')}, rejected {s.get('rejected', 0)}")
    return "\n".join(lines)
