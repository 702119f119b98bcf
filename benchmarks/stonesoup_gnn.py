"""A Stone Soup GNN tracker on rotating 2D radars, angle sensors and ADS-B (``paris-real``):
the test-only reference for zfusion's many-target tracker, on the plots ``zfusion eval``
feeds it (:func:`services.evaluation.merged_measurements`) and scored as it scores it
(:func:`services.scoring.score_tracks_of`, its :class:`~services.scoring.Looks` fed by the
stream). CPU: ``time.process_time`` of the tracking loop. Models from :mod:`stonesoup_jpda`.

Frames: a rotating radar's plot is valid when its beam crossed the target, so no two
plots share a time. One tracker step per frame as zfusion cuts them (TimeGrouper, the
plots within ``pair_tol`` of the first), each Detection at its own time. In a frame each
sensor's plots (one per aircraft at most) get a ``GNNWith2DAssignment`` over a Mahalanobis
``DistanceHypothesiser`` (which predicts a track to each detection's own timestamp), all
against the tracks as the frame found them; a track then takes its plots in time order
(the next re-predicted from the last update), and one no plot hit gets its prediction
appended, as ``MultiTargetTracker`` does. (One GNN over the frame drops a plot whenever
two sensors see an aircraft in it; a step per scan would predict backwards.) Gate
``χ²(gate_prob, n_z)``, n_z = 2 or 3 (ADS-B). A numpy screen gives a track only the plots
that can be in its gate (``S_cc ≤ |h_c|² tr P_pos + R_cc``): the hypotheses are Stone
Soup's unscreened ones (checked: none lost), at a seventh of the CPU.

Models: CA per axis, jerk PSD ``q`` horizontally and ``q_up`` up; EKF with Joseph-form,
symmetrised updates (the standard form went indefinite on 30 m ADS-B and 0.05° plots).
2D radar ``CartesianToBearingSlantRange`` (bearing = π/2 − az), angle sensor
``CartesianToElevationBearing``, ADS-B (kind ``position``, z = ENU m) ``LinearGaussian`` on
the position with the report's own ``R``; its identity is not used.

Initiation: ``MultiMeasurementInitiator`` stepped on frames too, ``min_points`` = 6 updates
(run 0's first 600 s, GOSPA: 5 → 783 m and 6 false tracks, 6 → 686 m and none, 7 → 710
m, 8 → 738 m; 4 gave 67 false tracks, ``confirm_m`` = 3 225 in 300 s). An ADS-B report starts a
holding track at its point; a 2D radar plot at an altitude prior of 3,000 ± 2,000 m (the
recording's aircraft over time: mean 2.9 km, σ 2.1 km, 95 % below 6.9 km; 6,000 ± 3,500
m, the stated 0-12 km band, gave GOSPA 1,092 m against 686 m); an angle plot none (a ray:
a range prior tens of km wide is no Gaussian through an EKF, and gathers other sensors'
plots along the ray). Deletion in time, not steps: a confirmed track after
``delete_misses · revisit_s`` (30 s) without an update or once its position σ passes
``max_pos_std``; a holding track after ``revisit_s`` + 1 s without one (the slowest
sensor's next look). Reported each frame: the confirmed tracks it updated or confirmed,
at that update, as zfusion's sweep tracker reports them (every confirmed track every frame,
coasting ones at their prediction, as stonesoup_jpda does: run 0 GOSPA 935 m, not 798 m).

    python benchmarks/stonesoup_gnn.py --scenario paris-real --runs 1 --duration-s 300
"""

from __future__ import annotations

import argparse
import datetime
import functools
import json
import math
import sys
import time

import numpy as np
from scipy.stats import chi2

from _common import machine_line

from stonesoup.base import Property
from stonesoup.dataassociator.neighbour import GNNWith2DAssignment
from stonesoup.deleter.error import CovarianceBasedDeleter
from stonesoup.deleter.multi import CompositeDeleter
from stonesoup.deleter.time import UpdateTimeDeleter
from stonesoup.hypothesiser.distance import DistanceHypothesiser
from stonesoup.initiator.simple import MultiMeasurementInitiator, SimpleMeasurementInitiator
from stonesoup.measures import Mahalanobis
from stonesoup.models.measurement.linear import LinearGaussian
from stonesoup.models.measurement.nonlinear import CartesianToElevationBearing
from stonesoup.models.transition.linear import ConstantAcceleration
from stonesoup.predictor.kalman import ExtendedKalmanPredictor
from stonesoup.tracker.simple import MultiTargetTracker
from stonesoup.types.array import StateVector
from stonesoup.types.detection import Detection
from stonesoup.types.hypothesis import SingleHypothesis
from stonesoup.types.state import GaussianState
from stonesoup.types.update import Update
from stonesoup.updater.kalman import ExtendedKalmanUpdater

from stonesoup_jpda import (PERM, POS, T0, CachedTransition, CartesianToBearingSlantRange, RadarPlotInitiator,
                            sensor_model, to_detection)

from fusion.grouping import TimeGrouper
from fusion.mtt_metrics import TrackScore
from fusion.types import Estimate
from services.evaluation import merged_measurements
from services.scenario import load
from services.scoring import Looks, score_tracks_of

HOLD_SLACK_S = 1.0  # s: a holding track outlives the slowest sensor's period by this much
ALT0, ALT_STD = 3000.0, 2000.0  # m: the altitude prior of a 2D radar plot (module docstring)
MIN_POINTS = 6  # updates that confirm a holding track (module docstring)


class ScreenedHypothesiser(DistanceHypothesiser):
    """Stone Soup's distance hypothesiser on one sensor's plots of a frame, each track
    handed only the plots a screen leaves it (module docstring): a bound of the EKF gate
    ``χ²(gate_prob, n_z)`` for every track and plot at once, so that a prediction is made
    only for a pair that may be in the gate. :meth:`start_frame` takes the tracks as the
    frame finds them, :meth:`near` screens a scan."""

    gate_prob: float = Property(default=0.999)
    q_axes: tuple = Property(default=(0.1, 0.1, 0.1), doc="the jerk PSD of the x, y, z axes")

    def start_frame(self, tracks) -> None:
        self._tracks = list(tracks)
        states = [track.state for track in self._tracks]
        self._x = np.array([np.asarray(s.state_vector, dtype=float)[:, 0] for s in states]).reshape(-1, 3, 3)
        P = np.array([np.asarray(s.covar, dtype=float) for s in states]).reshape(-1, 3, 3, 3, 3)
        self._P = np.einsum("nkakb->nkab", P) if len(states) else np.empty((0, 3, 3, 3))  # per axis k: [p v a]
        self._t = np.array([(s.timestamp - T0).total_seconds() for s in states])
        self._near: dict = {}

    def near(self, scan: list) -> dict:
        """The tracks with a plot of ``scan`` in their gate's bound, and those plots."""
        model = scan[0].measurement_model
        threshold = _gate(self.gate_prob, model.ndim_meas)
        self.missed_distance = math.sqrt(threshold)
        tau = np.array([(d.timestamp - T0).total_seconds() for d in scan])
        dt = tau[None, :] - self._t[:, None]  # tracks × plots, ≥ 0
        g = np.stack([np.ones_like(dt), dt, dt * dt / 2], axis=-1)  # F's first row per axis
        pos = np.einsum("nmc,nkc->nmk", g, self._x)
        trace = (np.einsum("nmc,nkcd,nmd->nm", g, self._P, g)
                 + dt**5 / 20 * sum(self.q_axes))  # trace of the predicted position covariance
        Z = np.array([np.asarray(d.state_vector, dtype=float)[:, 0] for d in scan])
        R = np.diag(np.asarray(model.covar(), dtype=float))
        centre, weight, angles = _measurement_bound(model, pos)
        diff = Z[None, :, :] - centre
        diff[..., angles] = (diff[..., angles] + math.pi) % (2 * math.pi) - math.pi
        with np.errstate(invalid="ignore", divide="ignore"):
            keep = np.all(diff**2 <= threshold * (weight * trace[..., None] + R) * (1 + 1e-6), axis=-1)
        self._near = {}
        for i, j in zip(*np.nonzero(keep)):
            self._near.setdefault(self._tracks[i], set()).add(scan[j])
        return self._near

    def hypothesise(self, track, detections, timestamp, **kwargs):
        return super().hypothesise(track, self._near.get(track, set()) & detections, timestamp, **kwargs)


@functools.lru_cache
def _gate(prob: float, n_z: int) -> float:
    return float(chi2.ppf(prob, n_z))


def _measurement_bound(model, pos):
    """For positions ``pos`` (… × 3): the model's predicted measurement, the squared norm
    of each component's Jacobian row (``S_cc ≤ |h_c|² trace P_pos + R_cc``) and which
    components are angles."""
    if isinstance(model, LinearGaussian):
        return pos, np.ones(3), np.zeros(3, dtype=bool)
    d = pos - np.asarray(model.translation_offset, dtype=float)[:, 0]
    rho2 = d[..., 0] ** 2 + d[..., 1] ** 2
    r2 = rho2 + d[..., 2] ** 2
    bearing = np.arctan2(d[..., 1], d[..., 0])
    if isinstance(model, CartesianToBearingSlantRange):
        return (np.stack([bearing, np.sqrt(r2)], axis=-1), np.stack([1 / rho2, np.ones_like(r2)], axis=-1),
                np.array([True, False]))
    if isinstance(model, CartesianToElevationBearing):
        elevation = np.arctan2(d[..., 2], np.sqrt(rho2))
        return (np.stack([elevation, bearing], axis=-1), np.stack([1 / r2, 1 / rho2], axis=-1),
                np.array([True, True]))
    raise TypeError(f"no gate bound for {type(model).__name__}")


class FrameStep:
    """One frame on a set of tracks (module docstring): GNN per sensor scan, updates in
    time order. For a tracker or an initiator (both have ``data_associator``, ``updater``)."""

    def _frame(self, tracks, detections, timestamp) -> tuple[set, set]:
        """Updates ``tracks`` with the frame's ``detections``; returns the plots taken
        and the tracks they hit."""
        hypothesiser = self.data_associator.hypothesiser
        hypothesiser.start_frame(tracks)
        hits: dict = {}
        scans: dict = {}
        for d in sorted(detections, key=lambda d: d.metadata["key"]):
            scans.setdefault(d.metadata["sensor"], []).append(d)
        for scan in scans.values():
            near = hypothesiser.near(scan)
            if not near:
                continue
            for track, hypothesis in self.data_associator.associate(set(near), set(scan), scan[0].timestamp).items():
                if hypothesis:
                    hits.setdefault(track, []).append(hypothesis)
        predictor = hypothesiser.predictor
        for track in tracks:
            mine = sorted(hits.get(track, ()), key=lambda h: h.measurement.metadata["key"])
            for k, hypothesis in enumerate(mine):
                if k:  # the track has moved on to its previous plot: predict from there
                    plot = hypothesis.measurement
                    hypothesis = SingleHypothesis(predictor.predict(track, timestamp=plot.timestamp), plot)
                track.append(self.updater.update(hypothesis))
            if not mine:
                track.append(predictor.predict(track, timestamp=timestamp))
        return {h.measurement for mine in hits.values() for h in mine}, set(hits)


class SweepTracker(FrameStep, MultiTargetTracker):
    """``MultiTargetTracker`` whose step is a frame of several sensors' plots."""

    def __next__(self):
        timestamp, detections = next(self.detector_iter)
        taken, _ = self._frame(self.tracks, detections, timestamp)
        self._tracks -= self.deleter.delete_tracks(self.tracks)
        self._tracks |= self.initiator.initiate(detections - taken, timestamp)
        return timestamp, self.tracks


class SweepInitiator(FrameStep, MultiMeasurementInitiator):
    """``MultiMeasurementInitiator`` whose step is a frame (its ``min_points`` rule)."""

    def initiate(self, detections, timestamp, **kwargs):
        taken, hit = self._frame(self.holding_tracks, detections, timestamp) if self.holding_tracks else (set(), set())
        sure = {track for track in hit if sum(isinstance(s, Update) for s in track) >= self.min_points}
        self.holding_tracks -= sure
        self.holding_tracks -= self.deleter.delete_tracks(self.holding_tracks)
        self.holding_tracks |= self.initiator.initiate(detections - taken, timestamp)
        return sure


class LatestUpdateTimeDeleter(UpdateTimeDeleter):
    """``UpdateTimeDeleter``'s rule read from the track's end back to its latest update
    (Stone Soup's slices the whole history by time: O(history) per track and step)."""

    def check_for_deletion(self, track, timestamp=None, **kwargs):
        timestamp = track.timestamp if timestamp is None else timestamp
        for state in reversed(track.states):
            if isinstance(state, Update) and state.hypothesis:
                return timestamp - state.timestamp > self.time_since_update
        return True


class PlotInitiator(RadarPlotInitiator):
    """stonesoup_jpda's 2D radar plot initiator (angle plots start nothing), and an
    ADS-B report starts a track at its point (``SimpleMeasurementInitiator``)."""

    def initiate(self, detections, timestamp, **kwargs):
        points = {d for d in detections if isinstance(d.measurement_model, LinearGaussian)}
        return (super().initiate(detections - points, timestamp, **kwargs)
                | SimpleMeasurementInitiator.initiate(self, points, timestamp, **kwargs))


class Plots:
    """A scenario's plots as Stone Soup detections, in frames."""

    def __init__(self, scenario):
        self.models = {sid: sensor_model(s) for sid, s in scenario.sensors.items()}
        self.points: dict = {}  # a position report's model, per stated covariance
        self.tol = float(scenario.tracker.get("pair_tol", 0.25))

    def detection(self, m) -> Detection:
        """``m`` as a detection; its metadata: its sensor and its key in the stream."""
        if m.kind != "position":
            d = to_detection(m, self.models[m.sensor])
        else:
            R = np.asarray(m.R, dtype=float)
            model = self.points.get(R.tobytes())
            if model is None:
                model = self.points[R.tobytes()] = LinearGaussian(ndim_state=9, mapping=POS, noise_covar=R)
            d = Detection(StateVector(np.asarray(m.z, dtype=float)), measurement_model=model,
                          timestamp=T0 + datetime.timedelta(seconds=float(m.t)), metadata={"sensor": m.sensor})
        d.metadata["key"] = m.order_key
        return d

    def frames(self, plots) -> list[tuple[datetime.datetime, set]]:
        grouper = TimeGrouper(self.tol)
        groups = [g for m in plots for g in grouper.push(m)] + grouper.finish()
        return [(T0 + datetime.timedelta(seconds=float(g[0].t)), {self.detection(m) for m in g}) for g in groups]


def build_tracker(scenario, detector, min_points: int, alt0: float = ALT0, alt_std: float = ALT_STD):
    tr = scenario.tracker
    q = float(tr.get("q", 0.1))
    q_up = float(tr.get("q_up", q))
    gate_prob = float(tr.get("gate_prob", 0.999))
    revisit = float(tr.get("revisit_s", max(s.period for s in scenario.sensors.values())))
    max_pos_std = float(tr.get("max_pos_std", math.inf))
    transition = CachedTransition([ConstantAcceleration(noise_diff_coeff=q)] * 2
                                  + [ConstantAcceleration(noise_diff_coeff=q_up)])
    predictor = ExtendedKalmanPredictor(transition)
    updater = ExtendedKalmanUpdater(measurement_model=None, use_joseph_cov=True, force_symmetric_covariance=True)

    def gnn():
        return GNNWith2DAssignment(ScreenedHypothesiser(predictor, updater, Mahalanobis(), gate_prob=gate_prob,
                                                        q_axes=(q, q, q_up)))

    v, vu = float(tr.get("init_vel_std", 300.0)), float(tr.get("init_vel_std_up", 30.0))
    a, au = float(tr.get("init_acc_std", 10.0)), float(tr.get("init_acc_std_up", 1.0))
    prior = GaussianState(np.zeros((9, 1)), np.diag([0, v**2, a**2, 0, v**2, a**2, 0, vu**2, au**2]))
    after = datetime.timedelta(seconds=int(tr.get("delete_misses", 3)) * revisit)
    deleters = [LatestUpdateTimeDeleter(after)]
    if math.isfinite(max_pos_std):
        deleters.append(CovarianceBasedDeleter(covar_trace_thresh=max_pos_std**2, mapping=list(POS)))
    initiator = SweepInitiator(
        prior_state=prior, deleter=LatestUpdateTimeDeleter(datetime.timedelta(seconds=revisit + HOLD_SLACK_S)),
        data_associator=gnn(), updater=updater, min_points=min_points,
        initiator=PlotInitiator(prior, alt0=alt0, alt_std=alt_std))
    return SweepTracker(initiator=initiator, deleter=CompositeDeleter(deleters, intersect=False), detector=detector,
                        data_associator=gnn(), updater=updater)


def run_once(scenario, run: int, min_points: int, alt0: float = ALT0, alt_std: float = ALT_STD):
    """One run: its :class:`TrackScore`, the tracking loop's CPU seconds, and counts."""
    looks = Looks()
    plots = merged_measurements(scenario, run, looks=looks)
    frames = Plots(scenario).frames(plots)
    tracker = build_tracker(scenario, iter(frames), min_points, alt0, alt_std)
    ids: dict = {}
    estimates = []
    cpu0 = time.process_time()
    for t, tracks in tracker:
        updated = [track for track in tracks if isinstance(track.state, Update) and track.state.timestamp >= t]
        for track in sorted(updated, key=lambda track: track.state.hypothesis.measurement.metadata["key"]):
            st = track.state
            tid = ids.setdefault(track.id, f"S{len(ids) + 1}")
            x = np.asarray(st.state_vector, dtype=float)[PERM, 0]
            P = np.asarray(st.covar, dtype=float)[np.ix_(PERM, PERM)]
            estimates.append(Estimate(t=(st.timestamp - T0).total_seconds(), x=x, P=P, method="stonesoup-gnn",
                                      track=tid))
    cpu = time.process_time() - cpu0
    estimates.sort(key=lambda e: e.t)
    counts = {"plots": len(plots), "frames": len(frames), "confirmed": len(ids)}
    return score_tracks_of(scenario, estimates, run, looks=looks), cpu, counts


FIELDS = ("mean_gospa", "held", "held_after_init", "false_tracks", "breaks", "duplicates", "id_changes",
          "rmse_pos_assigned", "tracks")


def _row(label, s: dict, cpu: str) -> str:
    cells = [f"{s[k]:.4f}" if k.startswith("held") else f"{s[k]:.1f}" if isinstance(s[k], float) else str(s[k])
             for k in FIELDS]
    return f"| {label} | " + " | ".join(cells) + f" | {cpu} |"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenario", default="paris-real")
    ap.add_argument("--runs", type=int, default=1)
    ap.add_argument("--first-run", type=int, default=0)
    ap.add_argument("--duration-s", type=float, default=None)
    ap.add_argument("--min-points", type=int, default=MIN_POINTS,
                    help="updates a holding track needs to be confirmed (MultiMeasurementInitiator)")
    ap.add_argument("--alt0", type=float, default=ALT0, help="altitude prior of a 2D radar plot (m)")
    ap.add_argument("--alt-std", type=float, default=ALT_STD)
    ap.add_argument("--json", default=None)
    args = ap.parse_args(argv)
    scenario = load(args.scenario, None, args.duration_s)
    min_points = args.min_points
    print(f"# Stone Soup GNN on {args.scenario}, {scenario.duration:g} s, runs {args.first_run}–"
          f"{args.first_run + args.runs - 1}, min_points {min_points}, "
          f"altitude prior {args.alt0:g} ± {args.alt_std:g} m")
    print(f"{machine_line()}\n")
    print("| run | " + " | ".join(FIELDS) + " | CPU (s) |")
    print("|---" * (len(FIELDS) + 2) + "|")
    scores, rows = [], []
    for run in range(args.first_run, args.first_run + args.runs):
        score, cpu, counts = run_once(scenario, run, min_points, args.alt0, args.alt_std)
        scores.append(score)
        s = score.summary()
        rows.append({"run": run, "cpu_s": cpu, **counts, **s})
        print(_row(str(run), s, f"{cpu:.1f}"), flush=True)
    total = TrackScore.merged(scores).summary()
    cpu = float(np.mean([r["cpu_s"] for r in rows]))
    print(_row("all", total, f"{cpu:.1f} (mean)"))
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"scenario": args.scenario, "duration_s": scenario.duration, "min_points": min_points,
                       "first_run": args.first_run,
                       "alt_prior": [args.alt0, args.alt_std], "runs": rows, "all": total, "cpu_s_mean": cpu},
                      f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
