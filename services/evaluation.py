"""In-process evaluation: the same scenario, the same generators, the same estimators,
without processes or Zenoh.

:func:`merged_measurements` produces exactly the stream a distributed fuser feeds its
method — every sensor's events from its own generator, merged in ``(t, sensor, seq)``
order — so for a given scenario and seed the in-process estimates equal those of a
distributed run.

:func:`evaluate` is the Monte Carlo harness behind ``zfusion eval`` and the reports in
``docs/results/``:

* **Common random numbers.** In run ``r`` the measurement stream is built once and every
  method (every :class:`Variant`) is fed that same stream, so differences between
  methods are not sampling noise between different data. (Each sensor draws from
  ``process_rng(seed, sensor, r)``, so a variant restricted to some sensors sees
  exactly those sensors' measurements of the full stream.)
* Each run is scored as soon as it is estimated (:func:`services.scoring.score_run`)
  and only the per-estimate errors are kept; runs may be spread over worker processes
  (``jobs``) with results identical to a serial evaluation (every run's randomness is a
  function of the run index only).
* The Cramér–Rao bound (:func:`crb_summary`) is computed from the scenario itself:
  the posterior CRB of :mod:`fusion.crb3d` for 3D targets, the static-emitter bound of
  :mod:`fusion.df.crb` for bearings-only emitters; with jamming outliers, each
  measurement's Fisher information is that of the actual noise mixture.
"""

from __future__ import annotations

import dataclasses
import heapq
import math
import multiprocessing
import os
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass, field
from typing import Callable, Iterable, Sequence

import numpy as np

from fusion.crb3d import block_rmse, expected_information, noise_fisher_information, posterior_crb
from fusion.df.crb import fisher_information, moving_emitter_pcrb
from fusion.df.methods import DFConfig
from fusion.init3d import initial_state
from fusion.measurement.kinds import KINDS, RAY, SPHERE, kinds_of, model_for
from fusion.methods import METHODS, make_method, method_config
from fusion.metrics import cep50
from fusion.motion import ConstantAcceleration
from fusion.patent import COLOCATED_TOL, KINDS_3D, TrackerConfig
from fusion.regional import RegionalMethod
from fusion.types import Estimate, Measurement
from sensors_sim import jam_effect, sensor_events, truth_trajectory
from sensors_sim.geometry import in_coverage
from sensors_sim.segments import ConstantAcceleration as CASegment
from sensors_sim.segments import Static

from .scoring import (GOSPA_CUTOFF, Looks, many_targets, pair_tol_of, region_crossings, scan_groups, score_run,
                      score_tracks_of, truth_function)
from .summary import aggregate, summary, tracks_summary

def merged_measurements(scenario, run: int = 0, sensors: Iterable[str] | None = None,
                        looks: Looks | None = None) -> list[Measurement]:
    """The run's measurements in ``(t, sensor, seq)`` order; ``looks`` sees every event."""
    def published(sid: str):
        for ev in sensor_events(scenario, sid, run=run):
            if looks is not None:
                looks.see(ev)
            if ev.measurement is not None:
                yield ev.measurement

    streams = [published(sid) for sid in (sensors if sensors is not None else scenario.sensors)]
    return list(heapq.merge(*streams, key=lambda m: m.order_key))


TOPOLOGIES = ("regional",)  # what ``zfusion eval --topology`` runs besides each method's own


def build_method(scenario, method_name: str, overrides: dict | None = None, topology: str | None = None,
                 clock=None):
    """Method ``method_name`` with the scenario's ``[tracker]`` and ``overrides``; with
    ``topology = "regional"``, its regional fusers over the scenario's ``[regions]``
    under a system fuser (:mod:`fusion.regional`; ``clock`` times the parts)."""
    config = method_config(scenario.tracker, method_name, overrides)
    if topology is None:
        return make_method(method_name, config)
    if topology != "regional":
        raise ValueError(f"unknown evaluation topology {topology!r} (one of {', '.join(TOPOLOGIES)})")
    if not scenario.regions:
        raise ValueError(f"--topology regional needs [regions] in the scenario; {scenario.name} has none")
    return RegionalMethod.from_config(method_name, scenario.regions, config, make_method, clock=clock)


def run_method(scenario, method_name: str, overrides: dict | None = None, run: int = 0,
               measurements: list[Measurement] | None = None, method=None) -> list[Estimate]:
    """Run one method over one Monte Carlo run; returns every estimate it emits. ``method``:
    one already built (:func:`build_method`), else the method of that name."""
    method = method or make_method(method_name, method_config(scenario.tracker, method_name, overrides))
    stream = measurements if measurements is not None else merged_measurements(scenario, run)
    out: list[Estimate] = []
    t_prev = None
    for m in stream:
        if t_prev is not None and m.t > t_prev:
            out.extend(method.advance(t_prev))  # as a watermark would, at each scan boundary
        out.extend(method.process(m))
        t_prev = m.t
    out.extend(method.finish())
    return out


# Which methods a scenario can run ------------------------------------------------------
def measurement_kinds(scenario) -> set[str]:
    return {s.measurement_kind for s in scenario.sensors.values()}


def default_methods(scenario) -> list[str]:
    """Every registered method the scenario's sensors can feed, in the source documents' table order.

    3D scenarios: the single-sensor baselines whose sensor kind is present, and the six
    patent methods (LCDD/HNDD only with both a 2D radar and an angle sensor; HNDD only if
    they are co-located). Bearings-only scenarios: every DF method.
    """
    kinds = measurement_kinds(scenario)
    fixed = all(s.site.fixed for s in scenario.sensors.values() if KINDS[s.measurement_kind].family == "df")
    colocated = _colocated_pair(scenario)
    return [m for m, s in METHODS.items() if s.runs_on(kinds, fixed_stations=fixed, colocated=colocated)]


def method_misfit(scenario, method: str) -> str | None:
    """Why ``method`` cannot run on ``scenario`` (an unknown name, a DF method on 3D
    sensors, a sensor kind the scenario lacks), with the methods that can; None if it can."""
    fits = default_methods(scenario)
    if method in fits:
        return None
    choose = f"choose one of {', '.join(fits)}" if fits else "no method can use its sensors"
    spec = METHODS.get(method)
    if spec is None:
        return f"unknown method {method!r}; for scenario {scenario.name} {choose}"
    kinds = measurement_kinds(scenario)
    family = "a DF (bearings-only) method" if spec.family == "df" else "a 3D tracking method"
    if not spec.kinds & kinds:
        return (f"{method} is {family} using {'/'.join(sorted(spec.kinds))} measurements; scenario {scenario.name} "
                f"has {', '.join(sorted(kinds))}: {choose}")
    return f"{method} cannot use the sensors of scenario {scenario.name} ({', '.join(sorted(kinds))}): {choose}"


def _colocated_pair(scenario) -> bool:
    starts = {s.id: KINDS[s.measurement_kind].start for s in scenario.sensors.values()
              if KINDS[s.measurement_kind].family == "3d"}
    radars = [s for s in scenario.sensors.values() if starts.get(s.id) == SPHERE]
    angles = [s for s in scenario.sensors.values() if starts.get(s.id) == RAY]
    return any(r.site.fixed and a.site.fixed and np.max(np.abs(r.site.points[0] - a.site.points[0])) <= COLOCATED_TOL
               for r in radars for a in angles)


# Monte Carlo harness ------------------------------------------------------------------
@dataclass(frozen=True)
class Variant:
    """One column of an evaluation: a method, its tracker overrides, and optionally the
    sensors it may use (default: all). ``label`` is its key in the summary."""

    label: str
    method: str
    overrides: dict = field(default_factory=dict)
    sensors: tuple[str, ...] | None = None
    topology: str | None = None  # "regional": the method as regional fusers under a system fuser


def variants_for(methods: Sequence[str], overrides: dict | None = None, topology: str | None = None) -> list[Variant]:
    return [Variant(m, m, dict(overrides or {}), topology=topology) for m in methods]


def _score_runs(scenario, variants: Sequence[Variant], run_ids: Sequence[int]) -> dict[int, dict[str, list]]:
    """Per run, each variant's score (by label); with ``[regions]`` also the run's
    ``crossings`` (key ``None``), and each regional variant's CPU seconds per part (key
    ``(label, "cpu_s")``)."""
    truth = truth_function(scenario)
    out: dict[int, dict] = {}
    for r in run_ids:
        streams: dict[tuple | None, list[Measurement]] = {}
        looks = Looks() if many_targets(scenario) else None
        full = merged_measurements(scenario, r, looks=looks)  # common random numbers: built once per run
        streams[None] = full
        scores: dict[str, list] = {}
        for v in variants:
            key = v.sensors
            if key not in streams:
                wanted = set(key)
                streams[key] = [m for m in full if m.sensor in wanted]
            method = build_method(scenario, v.method, v.overrides, v.topology, time.process_time)
            estimates = run_method(scenario, v.method, v.overrides, r, streams[key], method)
            scores[v.label] = (score_tracks_of(scenario, estimates, r, looks=looks)
                               if many_targets(scenario) else score_run(estimates, truth, r))
            if v.topology == "regional":
                scores[(v.label, "cpu_s")] = dict(method.cpu)
        if scenario.regions and many_targets(scenario):
            scores[None] = region_crossings(scenario, r)
        out[r] = scores
    return out


_WORKER: dict = {}


def _worker_init(scenario, variants):
    _WORKER["args"] = (scenario, variants)


def _worker(run_ids):
    scenario, variants = _WORKER["args"]
    return _score_runs(scenario, variants, run_ids)


def evaluate(scenario, variants: Sequence[Variant], runs: int, *, jobs: int = 1,
             progress: Callable[[int, int], None] | None = None, crb: bool = True,
             topology: str = "in-process", fusion_rule: str | None = None) -> dict:
    """Monte Carlo evaluation of ``variants`` over runs ``0..runs-1``; returns the
    ``--json`` summary of docs/design.md (``methods`` keyed by variant label, ``crb`` filled
    where :func:`crb_summary` applies). ``progress(done, total)`` is called per run."""
    if runs < 1:
        raise ValueError(f"evaluate: runs must be >= 1, got {runs}")
    labels = [v.label for v in variants]
    if len(set(labels)) != len(labels):
        raise ValueError(f"evaluate: duplicate variant labels {labels}")
    for v in variants:
        build_method(scenario, v.method, v.overrides, v.topology)  # fail early on a bad name/config/topology
        for s in v.sensors or ():
            scenario.sensor(s)
    jobs = max(1, min(int(jobs), runs))
    per_run: dict[int, dict[str, list]] = {}
    if jobs == 1:
        for r in range(runs):
            per_run.update(_score_runs(scenario, variants, [r]))
            if progress:
                progress(r + 1, runs)
    else:
        chunk = max(1, min(10, runs // (4 * jobs)))
        batches = [list(range(i, min(i + chunk, runs))) for i in range(0, runs, chunk)]
        ctx = multiprocessing.get_context("fork" if "fork" in multiprocessing.get_all_start_methods() else "spawn")
        with ProcessPoolExecutor(jobs, mp_context=ctx, initializer=_worker_init,
                                 initargs=(scenario, list(variants))) as pool:
            futures = [pool.submit(_worker, b) for b in batches]
            for fut in as_completed(futures):
                per_run.update(fut.result())
                if progress:
                    progress(len(per_run), runs)
    combine = tracks_summary if many_targets(scenario) else aggregate
    methods = {v.label: combine([per_run[r][v.label] for r in range(runs)]) for v in variants}
    for v in variants:
        if v.label != v.method or v.overrides or v.sensors:
            methods[v.label]["variant"] = {"method": v.method, "overrides": dict(v.overrides),
                                           "sensors": list(v.sensors) if v.sensors else None}
        if scenario.regions and many_targets(scenario):
            methods[v.label]["crossings"] = sum(per_run[r][None] for r in range(runs))
        if v.topology == "regional":  # process time of each part, summed over the runs (not deterministic)
            cpu = [per_run[r][(v.label, "cpu_s")] for r in range(runs)]
            methods[v.label]["cpu_s"] = {part: sum(c[part] for c in cpu) for part in cpu[0]}
    bound = crb_summary(scenario, runs) if crb and not many_targets(scenario) else None
    doc = summary(scenario, topology, fusion_rule, scenario.seed, runs, methods, crb=bound)
    if many_targets(scenario):
        doc["gospa_cutoff"] = GOSPA_CUTOFF
    return doc


def default_jobs() -> int:
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - not Linux
        return max(1, os.cpu_count() or 1)


# Cramér–Rao bounds --------------------------------------------------------------------
def _noise_std(scenario, sensor_id: str, t: float, position: np.ndarray) -> tuple[np.ndarray, bool]:
    """Per-component effective std (``1/√Fisher``) of a sensor's noise at ``t``, jamming
    included; and whether the noise density is regular (False for uniform outliers)."""
    spec = scenario.sensor(sensor_id)
    std = np.asarray(spec.std, dtype=float)
    effect = jam_effect(scenario, sensor_id, t, position) if scenario.jammers else None
    if effect is None:
        return std, True
    out, regular = np.empty_like(std), True
    for i, comp in enumerate(KINDS[spec.measurement_kind].components):
        s1 = std[i] * math.sqrt(effect.variance_gain)
        s2 = effect.outlier_std if comp.angle else effect.outlier_std_range
        if s2 is None or effect.p_outlier == 0.0:
            out[i] = s1
            continue
        info = noise_fisher_information(s1, effect.p_outlier, s2, effect.outlier_law)
        out[i], regular = info.effective_std, regular and info.regular
    return out, regular


def crb_summary(scenario, runs: int) -> dict | None:
    """The bound on position RMSE at the methods' output times, or None if none applies.

    The first target of the scenario is used. 3D sensors: posterior CRB (9-state CA
    truth model with the target's jerk PSD; expectation over the ``runs`` Monte Carlo
    truths). Bearings: Fisher information of a static emitter (no prior). Detection
    probability scales the information; a truth outside a sensor's coverage contributes
    none.
    """
    if not scenario.targets:
        return None
    target = next(iter(scenario.targets))
    kinds = {s.measurement_kind for s in scenario.sensors.values() if target in s.targets}
    if kinds & kinds_of("df"):
        return _crb_emitter(scenario, target)
    if kinds & kinds_of("3d"):
        return _crb_3d(scenario, target, runs)
    return None


def _nullable(values) -> list:
    return [float(v) if np.isfinite(v) else None for v in values]


def _crb_3d(scenario, target: str, runs: int) -> dict | None:
    try:
        # The bound uses every 3D sensor's measurements, i.e. the centralised SS filter's
        # information, from SS's prior.
        cfg = TrackerConfig.from_dict(method_config(scenario.tracker, "SS"))
    except ValueError:
        return None
    sensors = [s for s, spec in scenario.sensors.items() if target in spec.targets and spec.measurement_kind in KINDS_3D]
    groups = scan_groups(scenario, sensors, cfg.pair_tol)
    spec_t = scenario.target(target)
    trajs = [truth_trajectory(scenario, target, r) for r in range(runs)]
    times = np.array([g[0] for g in groups])
    notes = []
    if not (len(spec_t.segments) == 1 and isinstance(spec_t.segments[0], CASegment)
            and spec_t.segments[0].acc is None):
        notes.append("the truth is not a single constant-acceleration segment: the bound's CA model is approximate")
    regular = True
    info = np.zeros((times.size, 9, 9))
    for k, (t, _, members) in enumerate(groups):
        X = np.array([tr.state(t) for tr in trajs])
        if k == 0:
            continue  # the tracker's initial covariance holds the first scan's information
        for s in members:
            spec = scenario.sensor(s)
            cov = np.array([in_coverage(spec, x[:3] - spec.site.position(t)) for x in X])
            if not cov.any():
                continue
            std, reg = _noise_std(scenario, s, t, X[0, :3])
            regular &= reg
            model = model_for(spec.measurement_kind, spec.site.position(t), std, 9)
            info[k] += spec.p_detect * cov.mean() * expected_information([model], X[cov])
    # P0: the trackers' initialiser on the noise-free first scan (fusion.crb3d, "initial information")
    t0, _, first = groups[0]
    x0 = np.mean([tr.state(t0) for tr in trajs], axis=0)
    scan0 = []
    for s in first:
        spec = scenario.sensor(s)
        model = model_for(spec.measurement_kind, spec.site.position(t0), spec.std, 9)
        scan0.append(Measurement(t0, s, spec.measurement_kind, model.h(x0), np.asarray(spec.std, float),
                                 spec.site.position(t0)))
    _, P0 = initial_state(scan0, 9, cfg.priors())
    C = posterior_crb(P0, times, ConstantAcceleration(spec_t.jerk_psd, "continuous"), info)
    if not regular:
        notes.append("uniform outliers: their density is not regular, the bound is indicative only")
    if scenario.jammers:
        notes.append("jammed measurements enter with the Fisher information of their noise mixture")
    pos, vel, acc = (block_rmse(C, slice(3 * i, 3 * i + 3)) for i in range(3))
    late = times >= 0.5 * (times[0] + times[-1])  # as services.summary's "second_half"
    return {
        "t": times.tolist(),
        "rmse_pos": pos.tolist(),
        "rmse_vel": vel.tolist(),
        "rmse_acc": acc.tolist(),
        "overall": {"rmse_pos": float(np.sqrt(np.mean(pos**2))), "rmse_vel": float(np.sqrt(np.mean(vel**2))),
                    "rmse_acc": float(np.sqrt(np.mean(acc**2)))},
        "second_half": {"from_t": float(0.5 * (times[0] + times[-1])),
                        "rmse_pos": float(np.sqrt(np.mean(pos[late] ** 2))),
                        "rmse_vel": float(np.sqrt(np.mean(vel[late] ** 2))),
                        "rmse_acc": float(np.sqrt(np.mean(acc[late] ** 2)))},
        "final": {"t": float(times[-1]), "rmse_pos": float(pos[-1]), "rmse_vel": float(vel[-1]),
                  "rmse_acc": float(acc[-1])},
        "kind": "posterior CRB, 9-state CA truth model, J0 = inverse of the trackers' initial covariance",
        "target": target,
        "regular": regular,
        "notes": notes,
    }


def _crb_emitter(scenario, target: str) -> dict | None:

    spec_t = scenario.target(target)
    sensors = [s for s, spec in scenario.sensors.items()
               if target in spec.targets and KINDS[spec.measurement_kind].family == "df"]
    groups = scan_groups(scenario, sensors, pair_tol_of(scenario, DFConfig.pair_tol))
    try:  # the recursive methods' model: EKF's table
        cfg = DFConfig.from_dict(method_config(scenario.tracker, "EKF"))
    except ValueError:
        cfg = None
    if cfg is not None and cfg.motion == "cv":
        return _crb_moving_emitter(scenario, target, groups, cfg)
    if spec_t.jerk_psd > 0 or not all(isinstance(s, Static) for s in spec_t.segments):
        return {"t": [], "rmse_pos": [], "notes": ["the emitter moves and the tracker's motion is static: no bound"]}
    p = truth_trajectory(scenario, target, 0).state(0.0)[:3]
    J = np.zeros((2, 2))
    times, rms, regular = [], [], True
    C = None
    for t, t_last, members in groups:
        for s in members:
            spec = scenario.sensor(s)
            site = spec.site.position(t)
            if not in_coverage(spec, p - site):
                continue
            std, reg = _noise_std(scenario, s, t, p)
            regular &= reg
            J = J + spec.p_detect * fisher_information(p, site[None, :], std[0])
        times.append(t_last)
        if np.linalg.cond(J) <= 1e12:
            C = np.linalg.inv(J)
            rms.append(float(np.sqrt(np.trace(C))))
        else:
            rms.append(math.inf)
    notes = ["static emitter, no prior information: J = Σ gᵀg/σ² over the bearings so far"]
    if not regular:
        notes.append("uniform outliers: their density is not regular, the bound is indicative only")
    if scenario.jammers:
        notes.append("jammed bearings enter with the Fisher information of their noise mixture")
    out = {"t": times, "rmse_pos": _nullable(rms), "kind": "CRB, static emitter from bearings",
           "target": target, "regular": regular, "notes": notes}
    finite = [r for r in rms if math.isfinite(r)]
    if finite:  # over the epochs where a fix exists, as the methods' overall rmse_pos
        out["overall"] = {"rmse_pos": float(np.sqrt(np.mean(np.square(finite)))), "rmse_vel": None, "rmse_acc": None}
    if C is not None:
        out["final_P"] = (0.5 * (C + C.T)).tolist()
        out["cep50"] = cep50(C)
        out["rmse_pos_final"] = rms[-1]
    return out


def _crb_moving_emitter(scenario, target: str, groups, cfg) -> dict:
    """Posterior CRB of the constant-velocity emitter (:func:`fusion.df.crb.moving_emitter_pcrb`)
    along run 0's truth, with the ``[tracker]``'s ``q`` and ``init_vel_std``; jammed
    bearings with the information of their noise mixture, detection probability scaling
    it, a station out of coverage giving none."""
    traj = truth_trajectory(scenario, target, 0)
    times, positions, epochs, regular = [], [], [], True
    for t, t_last, members in groups:
        p = traj.position(t_last)
        sites, stds = [], []
        for s in members:
            spec = scenario.sensor(s)
            site = spec.site.position(t)
            if not in_coverage(spec, p - site) or spec.p_detect == 0.0:
                continue
            std, reg = _noise_std(scenario, s, t, p)
            regular &= reg
            sites.append(site[:2])
            stds.append(std[0] / math.sqrt(spec.p_detect))  # information × P_D
        times.append(t_last)
        positions.append(p[:2])
        epochs.append((np.array(sites).reshape(-1, 2), np.array(stds)))
    C = moving_emitter_pcrb(cfg.model, times, positions, epochs, cfg.init_vel_std)
    pos = np.sqrt(C[:, 0, 0] + C[:, 1, 1])
    vel = np.sqrt(C[:, 2, 2] + C[:, 3, 3])
    tt = np.array(times)
    late = tt >= 0.5 * (tt[0] + tt[-1])  # as services.summary's "second_half"
    notes = [f"constant-velocity model of the tracker (q = {cfg.q:g} m²/s³, velocity prior "
             f"0 ± {cfg.init_vel_std:g} m/s), information at run 0's true positions"]
    if not regular:
        notes.append("uniform outliers: their density is not regular, the bound is indicative only")
    if scenario.jammers:
        notes.append("jammed bearings enter with the Fisher information of their noise mixture")
    P = C[-1, :2, :2]
    return {
        "t": times,
        "rmse_pos": pos.tolist(),
        "rmse_vel": vel.tolist(),
        "overall": {"rmse_pos": float(np.sqrt(np.mean(pos ** 2))), "rmse_vel": float(np.sqrt(np.mean(vel ** 2))),
                    "rmse_acc": None},
        "second_half": {"from_t": float(0.5 * (tt[0] + tt[-1])), "rmse_pos": float(np.sqrt(np.mean(pos[late] ** 2))),
                        "rmse_vel": float(np.sqrt(np.mean(vel[late] ** 2))), "rmse_acc": None},
        "final": {"t": float(tt[-1]), "rmse_pos": float(pos[-1]), "rmse_vel": float(vel[-1]), "rmse_acc": None},
        "final_P": (0.5 * (P + P.T)).tolist(),
        "cep50": cep50(P),
        "rmse_pos_final": float(pos[-1]),
        "kind": "posterior CRB, constant-velocity emitter from bearings",
        "target": target,
        "regular": regular,
        "notes": notes,
    }


def with_sensors(scenario, sensors: dict, name: str | None = None):
    """A copy of ``scenario`` with another sensor table (for baseline variants)."""
    return dataclasses.replace(scenario, sensors=dict(sensors), name=name or scenario.name)


def score_tracks_run(scenario, method_name: str, run: int = 0, c: float = GOSPA_CUTOFF, p: float = 2.0,
                     overrides: dict | None = None):
    """One run of a many-target method, scored (:func:`score_tracks_of`)."""
    return score_tracks_of(scenario, run_method(scenario, method_name, overrides, run), run, c, p)
