"""A Stone Soup JPDA tracker on a many-target scenario's plots: the reference the JIPDA
association is measured against, scored exactly as ``zfusion eval`` scores
zfusion's trackers.

Same plots: run ``r``'s stream is :func:`services.evaluation.merged_measurements`, the
one ``zfusion eval`` feeds every method. Same score: the confirmed tracks after each frame
become :class:`fusion.types.Estimate` s scored as ``zfusion eval`` scores a run
(:func:`services.scoring.track_steps`, GOSPA c = 1000 m, p = 2, track breaks, false
tracks), with the dense report's GOSPA parts and formation merges
(:mod:`services.report.dense`). CPU: ``time.process_time`` of the tracking loop alone
(plots made and scored outside it).

The tracker is Stone Soup's own components, configured as its documentation and
tutorials use them:

* ``MultiTargetMixtureTracker`` with ``JPDAwithEHM2`` (exact JPDA by efficient hypothesis
  management) over ``PDAHypothesiser`` (P_D and the clutter density ``λ/V`` the
  scenario states for each sensor, the scenario's gate probability) and the extended
  Kalman predictor and updater; the same constant-acceleration motion and jerk PSD as
  the scenario's ``[tracker]``.
* Stone Soup has no 2D radar measuring slant range: :class:`CartesianToBearingSlantRange`
  is one, written like its ``CartesianToElevationBearingRange``. Angle sensors are its
  ``CartesianToElevationBearing``. Stone Soup's bearing is counter-clockwise from x:
  ``π/2 − az``.
* Initiation: ``MultiMeasurementInitiator`` (tentative tracks held until ``min_points``
  updates; GNN with a Mahalanobis ``DistanceHypothesiser`` over every sensor's plots;
  deleted after a frame without an update) starting tracks from 2D radar plots read as
  3D plots at the elevation of an altitude prior, 6,000 ± 3,000 m (the traffic's band;
  an elevation prior of 0.3 ± 0.3 rad, as zfusion gives a lone radar plot, put a track
  60 km out 10 km too high and it never converged: without clutter, 9 of 32 aircraft
  had no track at 30 s, against none with the altitude prior); velocity and
  acceleration from the scenario's priors.
* Deletion: ``UpdateTimeStepsDeleter`` after the scenario's ``delete_misses`` frames
  without an update, or ``CovarianceBasedDeleter`` when the position covariance's trace
  exceeds ``max_pos_std²``.

Hypothesisers see only the plots inside a box that contains their gate (half-widths
``√(G·Sₖₖ)`` about the predicted measurement), because Stone Soup would otherwise predict
every track to every plot (200 plots a scan): the gate drops the others anyway, so the
hypotheses are those Stone Soup makes unfiltered.

    python benchmarks/stonesoup_jpda.py --scenario air-picture-dense --runs 3
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import json
import math
import sys
import time

import numpy as np
from scipy.stats import chi2

from _common import machine_line  # noqa: F401  (puts the repository on sys.path)

from stonesoup.base import Property
from stonesoup.dataassociator.neighbour import GNNWith2DAssignment
from stonesoup.dataassociator.probability import JPDAwithEHM2
from stonesoup.deleter.error import CovarianceBasedDeleter
from stonesoup.deleter.multi import CompositeDeleter
from stonesoup.deleter.time import UpdateTimeStepsDeleter
from stonesoup.hypothesiser.distance import DistanceHypothesiser
from stonesoup.hypothesiser.probability import PDAHypothesiser
from stonesoup.initiator.simple import MultiMeasurementInitiator, SimpleMeasurementInitiator
from stonesoup.measures import Mahalanobis
from stonesoup.models.measurement.nonlinear import (CartesianToElevationBearing, CartesianToElevationBearingRange,
                                                    NonLinearGaussianMeasurement)
from stonesoup.models.transition.linear import CombinedLinearGaussianTransitionModel, ConstantAcceleration
from stonesoup.predictor.kalman import ExtendedKalmanPredictor
from stonesoup.tracker.simple import MultiTargetMixtureTracker
from stonesoup.types.angle import Bearing, Elevation
from stonesoup.types.array import StateVector, StateVectors
from stonesoup.types.detection import Detection
from stonesoup.types.state import GaussianState
from stonesoup.updater.kalman import ExtendedKalmanUpdater

from fusion.types import Estimate
from services.evaluation import merged_measurements
from services.report.dense import formation_merges, formation_pairs, gospa_parts
from services.scoring import GOSPA_CUTOFF, track_steps
from fusion.mtt_metrics import TrackScore, score_tracks
from sensors_sim import load_scenario
from sensors_sim.geometry import coverage_span

T0 = datetime.datetime(2024, 1, 1)
PERM = [0, 3, 6, 1, 4, 7, 2, 5, 8]  # ours[k] = stonesoup[PERM[k]]: [x vx ax y vy ay z vz az] -> [p v a]
POS = (0, 3, 6)
MAX_EL = math.sin(math.radians(80.0))  # sine of the steepest elevation a radar plot is lifted to


class CartesianToBearingSlantRange(NonLinearGaussianMeasurement):
    """A 2D radar: bearing (counter-clockwise from x) and slant range from a site."""

    translation_offset: StateVector = Property(default_factory=lambda: StateVector([[0.0], [0.0], [0.0]]),
                                               doc="the site (x, y, z)")

    @property
    def ndim_meas(self) -> int:
        return 2

    def function(self, state, noise=False, **kwargs):
        d = state.state_vector[self.mapping, :] - self.translation_offset
        d = np.asarray(d, dtype=float)
        bearing = np.arctan2(d[1], d[0])
        rng = np.sqrt(np.sum(d * d, axis=0))
        out = StateVectors([[Bearing(b) for b in bearing], rng])
        if noise:
            out = out + self.rvs(num_samples=d.shape[1], **kwargs)
        return out

    def jacobian(self, state, **kwargs):
        x, y, z = np.asarray(state.state_vector[self.mapping, :] - self.translation_offset, dtype=float)[:, 0]
        rho2 = x * x + y * y
        r = math.sqrt(rho2 + z * z)
        H = np.zeros((2, self.ndim_state))
        H[:, list(self.mapping)] = [[-y / rho2, x / rho2, 0.0], [x / r, y / r, z / r]]
        return H


class CachedTransition(CombinedLinearGaussianTransitionModel):
    """Stone Soup's combined transition with ``F(dt)`` and ``Q(dt)`` built once per ``dt``
    (it rebuilds both for every track and step, a third of the run's time): same values."""

    def matrix(self, **kwargs):
        return self._cached("F", kwargs, super().matrix)

    def covar(self, **kwargs):
        return self._cached("Q", kwargs, super().covar)

    def _cached(self, what, kwargs, make):
        cache = self.__dict__.setdefault("_cache", {})
        key = (what, kwargs["time_interval"].total_seconds())
        if key not in cache:
            cache[key] = make(**kwargs)
        return cache[key]


class AnalyticElevationBearing(CartesianToElevationBearing):
    """Stone Soup's angle-sensor model with its Jacobian in closed form (its own is by
    finite differences: the same to ~1e-7, at ten times the cost)."""

    def jacobian(self, state, **kwargs):
        x, y, z = np.asarray(state.state_vector[self.mapping, :] - self.translation_offset, dtype=float)[:, 0]
        rho2 = x * x + y * y
        rho = math.sqrt(rho2)
        r2 = rho2 + z * z
        H = np.zeros((2, self.ndim_state))
        H[:, list(self.mapping)] = [[-x * z / (rho * r2), -y * z / (rho * r2), rho / r2], [-y / rho2, x / rho2, 0.0]]
        return H


class _BoxGate:
    """Hands the hypothesiser only the plots inside a box that holds its gate
    (module docstring). ``threshold`` is the gate on d²."""

    _scan = (None, None, None, None)

    def _in_box(self, track, detections, timestamp, threshold):
        if self._scan[0] is not detections:
            listed = list(detections)
            Z = np.array([np.asarray(d.state_vector, dtype=float)[:, 0] for d in listed]) if listed else None
            angles = ([isinstance(v, (Bearing, Elevation)) for v in listed[0].state_vector[:, 0]] if listed else [])
            self._scan = (detections, listed, Z, np.flatnonzero(angles))
        _, listed, Z, angles = self._scan
        if not listed:
            return set()
        model = listed[0].measurement_model
        prediction = self.predictor.predict(track, timestamp=timestamp)
        mp = self.updater.predict_measurement(prediction, model)
        diff = Z - np.asarray(mp.state_vector, dtype=float)[:, 0]
        diff[:, angles] = (diff[:, angles] + math.pi) % (2 * math.pi) - math.pi
        half = np.sqrt(threshold * np.diag(np.asarray(mp.covar, dtype=float))) * (1 + 1e-9)
        keep = np.all(np.abs(diff) <= half, axis=1)
        return {listed[i] for i in np.flatnonzero(keep)}


class BoxPDAHypothesiser(_BoxGate, PDAHypothesiser):
    """Stone Soup's PDA hypothesiser, with the clutter density of the scan's sensor."""

    densities: dict = Property(default=None, doc="clutter density per sensor id")

    def hypothesise(self, track, detections, timestamp, **kwargs):
        if detections:
            self.clutter_spatial_density = self.densities[next(iter(detections)).metadata["sensor"]]
        gate = chi2.ppf(float(self.prob_gate), 2)  # every sensor here measures two components
        return super().hypothesise(track, self._in_box(track, detections, timestamp, gate), timestamp, **kwargs)


class BoxDistanceHypothesiser(_BoxGate, DistanceHypothesiser):
    def hypothesise(self, track, detections, timestamp, **kwargs):
        return super().hypothesise(track, self._in_box(track, detections, timestamp, self.missed_distance ** 2),
                                   timestamp, **kwargs)


class RadarPlotInitiator(SimpleMeasurementInitiator):
    """Stone Soup's measurement initiator on 2D radar plots, each read as a 3D plot at the
    elevation of an altitude prior ``alt0 ± alt_std`` (angle plots start nothing)."""

    alt0: float = Property(default=6000.0)
    alt_std: float = Property(default=3000.0)

    def initiate(self, detections, timestamp, **kwargs):
        lifted = set()
        for d in detections:
            m = d.measurement_model
            if not isinstance(m, CartesianToBearingSlantRange):
                continue
            std_b, std_r = np.sqrt(np.diag(m.covar()))
            r = float(d.state_vector[1, 0])
            up = (self.alt0 - float(m.translation_offset[2, 0])) / r
            el0 = math.asin(max(-MAX_EL, min(MAX_EL, up)))  # a plot nearer than alt0: steep, not overhead
            el_std = self.alt_std / (r * max(math.cos(el0), 0.1))
            model = CartesianToElevationBearingRange(
                ndim_state=9, mapping=POS, translation_offset=m.translation_offset,
                noise_covar=np.diag([el_std**2, std_b**2, std_r**2]))
            z = StateVector([Elevation(el0), d.state_vector[0, 0], d.state_vector[1, 0]])
            lifted.add(Detection(z, timestamp=d.timestamp, measurement_model=model, metadata=d.metadata))
        return super().initiate(lifted, timestamp, **kwargs)


def build_tracker(scenario, detector, min_points: int, alt0: float = 6000.0, alt_std: float = 3000.0):
    tr = scenario.tracker
    q = float(tr.get("q", 0.1))
    gate_prob = float(tr.get("gate_prob", 0.999))
    sensors = scenario.sensors
    p_detect = min(s.p_detect for s in sensors.values())
    densities = {sid: s.clutter_rate / math.prod(coverage_span(s, c)[1] for c in s.components)
                 for sid, s in sensors.items()}  # λ / V, V the cover in measurement space
    transition = CachedTransition([ConstantAcceleration(noise_diff_coeff=q)] * 3)
    predictor = ExtendedKalmanPredictor(transition)
    updater = ExtendedKalmanUpdater(measurement_model=None)
    hypothesiser = BoxPDAHypothesiser(predictor, updater, clutter_spatial_density=1.0, prob_detect=p_detect,
                                      prob_gate=gate_prob, densities=densities)
    v, vu = float(tr.get("init_vel_std", 300.0)), float(tr.get("init_vel_std_up", 30.0))
    a, au = float(tr.get("init_acc_std", 10.0)), float(tr.get("init_acc_std_up", 1.0))
    prior = GaussianState(np.zeros((9, 1)), np.diag([0, v**2, a**2, 0, v**2, a**2, 0, vu**2, au**2]))
    frames = int(tr.get("delete_misses", 3))
    n_sensors = len(sensors)
    max_pos_std = float(tr.get("max_pos_std", math.inf))
    deleters = [UpdateTimeStepsDeleter(time_steps_since_update=frames * n_sensors)]
    if math.isfinite(max_pos_std):
        deleters.append(CovarianceBasedDeleter(covar_trace_thresh=max_pos_std**2, mapping=list(POS)))
    initiator = MultiMeasurementInitiator(
        prior_state=prior,
        deleter=UpdateTimeStepsDeleter(time_steps_since_update=n_sensors),
        data_associator=GNNWith2DAssignment(BoxDistanceHypothesiser(
            predictor, updater, Mahalanobis(), missed_distance=math.sqrt(chi2.ppf(gate_prob, 2)))),
        updater=updater, min_points=min_points,
        initiator=RadarPlotInitiator(prior, alt0=alt0, alt_std=alt_std))
    return MultiTargetMixtureTracker(initiator=initiator, deleter=CompositeDeleter(deleters, intersect=False),
                                     detector=detector, data_associator=JPDAwithEHM2(hypothesiser), updater=updater)


def sensor_model(s):
    """The Stone Soup model of a 2D radar or an angle sensor (None: another kind)."""
    site = StateVector(np.asarray(s.site.position(0.0), dtype=float).reshape(3, 1))
    std = s.std
    if s.measurement_kind == "range_az":
        return CartesianToBearingSlantRange(ndim_state=9, mapping=POS, translation_offset=site,
                                            noise_covar=np.diag([std[0] ** 2, std[1] ** 2]))
    if s.measurement_kind == "azel":
        return AnalyticElevationBearing(ndim_state=9, mapping=POS, translation_offset=site,
                                        noise_covar=np.diag([std[1] ** 2, std[0] ** 2]))
    return None


def _models(scenario):
    out = {}
    for sid, s in scenario.sensors.items():
        out[sid] = sensor_model(s)
        if out[sid] is None:
            raise SystemExit(f"{sid}: this reference handles 2D radars and angle sensors, not {s.measurement_kind}")
    return out


def to_detection(m, model) -> Detection:
    """A 2D radar's or an angle sensor's plot as a Stone Soup detection (bearing converted)."""
    bearing = Bearing(math.pi / 2 - m.z[0])
    z = (StateVector([Bearing(bearing), m.z[1]]) if m.kind == "range_az"
         else StateVector([Elevation(m.z[1]), Bearing(bearing)]))
    t = T0 + datetime.timedelta(seconds=float(m.t))
    return Detection(z, timestamp=t, measurement_model=model, metadata={"sensor": m.sensor})


def _scans(scenario, plots):
    """``(time, detections)`` per sensor scan, in the stream's order; z converted."""
    models = _models(scenario)
    scan, key = [], None
    for m in plots:
        if (m.t, m.sensor) != key and scan:
            yield scan
            scan = []
        key = (m.t, m.sensor)
        scan.append(to_detection(m, models[m.sensor]))
    if scan:
        yield scan


def run_once(scenario, run: int, min_points: int) -> tuple[TrackScore, float, dict]:
    plots = merged_measurements(scenario, run)
    scans = list(_scans(scenario, plots))
    detector = ((scan[0].timestamp, set(scan)) for scan in scans)
    tracker = build_tracker(scenario, detector, min_points)
    ids: dict = {}
    estimates = []
    cpu0 = time.process_time()
    for k, (t, tracks) in enumerate(tracker):
        if k + 1 < len(scans) and scans[k + 1][0].timestamp == t:  # not the frame's last scan
            continue
        secs = (t - T0).total_seconds()
        for track in sorted(tracks, key=lambda tr: tr.id):
            tid = ids.setdefault(track.id, f"S{len(ids) + 1}")
            st = track.state
            x = np.asarray(st.state_vector, dtype=float)[PERM, 0]
            P = np.asarray(st.covar, dtype=float)[np.ix_(PERM, PERM)]
            estimates.append(Estimate(t=secs, x=x, P=P, method="stonesoup-jpda", track=tid))
    cpu = time.process_time() - cpu0
    steps = track_steps(scenario, estimates, run)
    return score_tracks(steps, GOSPA_CUTOFF), cpu, formation_merges(steps, formation_pairs(scenario))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenario", default="air-picture-dense")
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--first-run", type=int, default=0)
    ap.add_argument("--min-points", type=int, default=10,
                    help="updates a tentative track needs to be confirmed (MultiMeasurementInitiator)")
    ap.add_argument("--duration-s", type=float, default=None)
    ap.add_argument("--json", default=None)
    args = ap.parse_args(argv)
    scenario = load_scenario(args.scenario)
    if args.duration_s is not None:
        scenario = dataclasses.replace(scenario, duration=args.duration_s)
    print(f"# Stone Soup JPDA on {args.scenario}, runs {args.first_run}–{args.first_run + args.runs - 1}, "
          f"min_points {args.min_points}")
    print(f"{machine_line()}\n")
    print("| run | mean GOSPA (m) | held | tracks | false | breaks | longest merge | CPU (s) |")
    print("|---|---|---|---|---|---|---|---|")
    scores, rows = [], []
    for run in range(args.first_run, args.first_run + args.runs):
        score, cpu, merges = run_once(scenario, run, args.min_points)
        scores.append(score)
        s = score.summary()
        rows.append({"run": run, "cpu_s": cpu, "merges": merges, **s})
        print(f"| {run} | {s['mean_gospa']:.1f} | {s['held']:.3f} | {s['tracks']} | {s['false_tracks']} | "
              f"{s['breaks']} | {max(merges.values(), default=0)} | {cpu:.1f} |", flush=True)
    total = TrackScore.merged(scores).summary()
    cpu = float(np.mean([r["cpu_s"] for r in rows]))
    parts = gospa_parts(scores)
    print(f"| all | {total['mean_gospa']:.1f} | {total['held']:.3f} | {total['tracks']} | {total['false_tracks']} | "
          f"{total['breaks']} | {max(max(r['merges'].values(), default=0) for r in rows)} | {cpu:.1f} (mean) |")
    print("GOSPA parts: " + json.dumps(parts))
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"scenario": args.scenario, "min_points": args.min_points, "runs": rows, "all": total,
                       "cpu_s_mean": cpu, "gospa_parts": parts}, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
