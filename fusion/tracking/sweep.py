r"""The many-target tracker on rotating radars: a frame is a sweep of plots, each at its
own time.

A rotating radar's plot is valid when the beam crossed its target, so no two plots of a
sensor share a time, and a frame (the plots within ``pair_tol`` of its first one) holds
the sectors the sensors' beams swept in that window. :class:`SweepTracker` runs the
:class:`~fusion.tracking.manager.MultiTargetTracker`'s steps on such a frame, with three
changes (switched on by ``revisit_s`` in ``[tracker]``):

1. **gating at each plot's own time.** A scan is one sensor's plots of the frame; a
   track is scored against plot ``j`` at its prediction to ``tⱼ``. A cheap screen first
   (:func:`near`, all tracks at once): the track's position moved along its velocity to
   the scan's time against the plot's azimuth, elevation and range, each within ``6σ``
   (the track's σ bounded by its covariance's largest eigenvalue, plus the plot's) and
   what the track can move besides, tried only on the plots within that width of the
   track in azimuth (:func:`_by_azimuth`, by bisection in the plots' sorted azimuths);
   only the pairs it keeps get ``d²``, all of a scan at once (:func:`pair_d2`): a
   spherical plot's ``h`` reads position only, so a pair needs the position block of
   the prediction, ``p = Σₐ fₐ xₐ`` and ``P_pp = G P Gᵀ + Q₁[0,0] I₃`` with ``G = f ⊗
   I₃`` and ``f = [1, dt, dt²/2]`` (CV: ``[1, dt]``) the first row of ``F₁(dt)``
   (:func:`position_row`), then ``d²`` from a stacked Cholesky.
2. **updates at each plot's time**: a track's plots of the frame in time order, the
   filter predicted to each one's time and updated (plots at one time: one scan).
3. **track management in time** (:class:`SweepLogic`): a track is looked at whenever a
   beam crosses it, each sensor at its own period, so a frame says nothing of the tracks
   it did not update. ``revisit_s`` is the longest time between two looks at a target
   (the slowest sensor's period). A tentative track is confirmed by its score (5.), or,
   without one (``llr`` None), at its ``confirm_m``-th
   hit once two sensors have seen it (clutter feeds a track from one radar at most; an
   aircraft is seen by three or four), one that measures elevation has (two 2D
   radars' ranges and azimuths fit a ghost kilometres off in height and position), and
   one has seen it on two of its looks (false plots do not repeat where a track
   predicts them, an aircraft's do). It is deleted if it is not confirmed within ``revisit_s`` of its birth (and
   ``REVISIT_SLACK_S``: a beam crosses a moving target a little later or earlier each
   turn): by then every sensor that sees its target has looked at it, while a
   tentative track kept alive by each hit gathers false plots in a gate its unknown
   velocity keeps growing (docs/results/region-400.md). A confirmed track is deleted
   once ``delete_misses · revisit_s`` passes without a hit (``K`` missed looks of the
   slowest sensor), or when its position σ passes ``max_pos_std``.
4. **no track from a lone 2D radar plot** (:func:`starts_alone`): it starts one here only
   paired with an angle plot; alone, its height prior is kilometres wide
   (``init_el_std``), its gate gathers the other sensors' false plots, and it could not
   be confirmed before a plot measuring elevation hits it anyway. The aircraft's track
   starts from that plot instead (a 3D radar's, an angle sensor's, or a pair).
5. **a track score** (Blackman & Popoli's sequential likelihood ratio) in place of
   counting hits: a track's ``llr`` is the sum, over the plots that hit it after the
   first, of ``ln(P_D N(ν; 0, S) / λ)`` — the plot's density under the track (its
   innovation at the state the plots before it left) over its density as a false
   plot, ``λ`` its sensor's false-plot density in measurement space
   (:class:`ClutterDensity`: the plots no track took, over the measurement volume the
   sensor swept); a miss adds nothing (a sweep does not say which beams crossed a
   track). Confirmed once ``llr ≥ ln(1/α)`` (Wald's threshold, ``α`` =
   ``FALSE_CONFIRM_PROB``) and, as before, two sensors and one measuring elevation have
   hit it (one angle sensor's plots do not fix a range). A plot at the edge of a wide
   gate, as a false plot in a young track's gate is, scores below zero; an aircraft's
   plot on a settled track, ``ln(P_D/(λ √|2πS|))`` ≈ 5–10 (docs/results/region-400.md).
6. **false plots only in λ**: a plot no track took is not counted if it is inside a
   track's gate (a target's, which a neighbour's track took), and one that started a
   track is uncounted when that track is confirmed (a target's). Counted, the plots of
   aircraft not yet tracked (every aircraft at a run's start) raised ``λ`` several times
   (``region-4000``, first minute: the 3D radars' left plots 4.9 times their false
   plots) and slowed every confirmation. The plots of aircraft that no track is near
   yet are still counted (docs/results/region-4000.md).
7. **a second range**: a track is confirmed only once a plot measuring range has hit it
   besides the one it started from (a radar's next look, or one gathered at its birth).
   A 2D radar plot and an angle plot pair wherever the ray crosses the range sphere at
   the radar's azimuth, a coincidence in one dimension that a dense picture offers at
   every frame; the angle sensor's next plots, on the same ray, scored it above Wald's
   threshold at once (the first 60 s of ``region-4000``: 12 of its 29 false tracks, on
   an aircraft's ray kilometres from it, while that aircraft's own track held it).
8. **pairs across frames** (``pair_window_s``): a 2D radar plot and an angle plot pair
   only within a frame, and a rotating radar's crossing of an aircraft may stay apart
   from an angle sensor's looks turn after turn (``paris-real``: 0.42 s every turn, for
   minutes). The plots of the last ``pair_window_s`` that nothing took are kept
   (``earlier``), and a frame's plots pair with them too, the radar plot moved to the
   angle plot's time (:meth:`fusion.tracking.initiators.Initiator.groups_across`).
9. **a position report's own look twice**: a track hit on two looks of one sensor that
   reports positions (ADS-B: the aircraft's own report of where it is, with no false
   plots of the kind a radar's extractor passes) has seen enough sensors (3.): near an
   airport an aircraft may be heard before any radar sees it, and on two sensors' hits
   alone it was never confirmed (``paris-real``: 27 s of one departure).

A frame reports the confirmed tracks it updated or confirmed (the others' estimates have
not changed). No duplicate review: few false tracks are near an aircraft another track
holds, and a review of the updated tracks against their neighbours at a common time
deleted tracks of aircraft (docs/results/region-400.md).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from .. import batch
from ..angles import wrap_pi
from ..ekf import TrackEKF
from ..measurement.components import AZ, EL, RANGE
from ..measurement.kinds import KINDS, RAY, SPHERE, fixes, model_of
from ..measurement.models import SphericalModel
from ..motion import ConstantAcceleration, ConstantVelocity
from ..types import Estimate
from .hypotheses import Hypotheses, by_sensor, gate_threshold, mahalanobis2
from .manager import Frame, MultiTargetTracker, Taken, initial_plots
from .table import CONFIRMED, DELETED, TENTATIVE, ManagementRule, Track, scores_hit

SCREEN_SIGMAS = 6.0  # the screen's width in σ of the track and of the plot
MAX_ACC = 20.0  # m/s²: what a track's velocity may be off by, per second, beyond its σ
# s: how much later than a period on a beam may cross a moving target, v·T²/(2π·r) (260 m/s,
# a 12 s turn, 10 km away: 0.6 s)
REVISIT_SLACK_S = 1.0
P_DETECT = 0.9  # a sensor's detection probability, in the track score (module docstring, 5.)
FALSE_CONFIRM_PROB = 1e-4  # α: the probability that a false track's score reaches the confirmation threshold
EARLIER_MAX = 20_000  # plots kept for pairing across frames (module docstring, 8.; region-4000 leaves ~300 a second)


@dataclass
class SweepLogic:
    """A track's life in time (module docstring, 3.): ``record(hit, P_pos, t, sensors,
    elevation)`` once per frame after its birth at ``last_hit`` from the plots of
    ``sensors``; ``elevation``: whether a plot that measures elevation has hit it."""

    rule: ManagementRule
    revisit_s: float
    last_hit: float
    sensors: frozenset = frozenset()
    elevation: bool = True
    status: str = TENTATIVE
    hits: int = 1
    repeated: bool = False  # whether a sensor has hit it on two of its looks
    born: float | None = None  # its birth's time (``last_hit`` at birth if None)
    llr: float | None = None  # its score (module docstring, 5.); None: confirmed by counting hits
    counted: tuple = ()  # the sensors of its birth's plots that the false-plot density counted (6.)
    ranged: bool = False  # whether a plot measuring range has hit it besides the one it started from (7.)
    reporters: frozenset = frozenset()  # the sensors of the position reports that hit it (9.)
    reported_twice: bool = False  # whether one of them has hit it on two of its looks (9.)
    #: no existence probability (the protocol of a track's logic, fusion.tracking.table.Track)
    existence = None

    def __post_init__(self):
        if self.born is None:
            self.born = self.last_hit
        self._confirm()

    def survive(self, t: float) -> None:
        """Nothing to age: the life is kept in time by :meth:`record`."""

    def _confirm(self) -> None:
        if self.status != TENTATIVE or not self.elevation:
            return
        seen = len(self.sensors) >= 2 or self.reported_twice
        if self.llr is not None:
            if self.llr >= confirm_threshold() and seen and self.ranged:
                self.status = CONFIRMED
        elif self.hits >= self.rule.confirm_m and seen and self.repeated:
            self.status = CONFIRMED

    def record(self, hit: bool, P_pos: np.ndarray | None = None, t: float | None = None,
               sensors=(), elevation: bool = False, score: float = 0.0, ranged: bool = False,
               reporters=()) -> str:
        """``score``: the hit's plots' log-likelihood ratio (module docstring, 5.), added
        to ``llr`` when it is kept; ``ranged``: whether a plot of the hit measures range;
        ``reporters``: the sensors of its position reports (9.)."""
        if self.status == DELETED:
            raise ValueError("a deleted track records no more frames")
        t = self.last_hit if t is None else t
        if self.status == TENTATIVE and t - self.born > self.revisit_s + REVISIT_SLACK_S:
            self.status = DELETED  # not confirmed within a revisit of its birth
            return self.status
        if hit:
            self.repeated = self.repeated or bool(self.sensors & frozenset(sensors))
            self.hits += 1
            self.last_hit = max(self.last_hit, t)
            self.sensors = self.sensors | frozenset(sensors)
            self.elevation = self.elevation or elevation
            self.ranged = self.ranged or ranged
            self.reported_twice = self.reported_twice or bool(self.reporters & frozenset(reporters))
            self.reporters = self.reporters | frozenset(reporters)
            if self.llr is not None:
                self.llr += score
            self._confirm()
        if self.status == CONFIRMED and t - self.last_hit > self.revisit_s * self.rule.delete_misses:
            self.status = DELETED
        elif P_pos is not None and math.sqrt(float(np.trace(P_pos))) > self.rule.max_pos_std:
            self.status = DELETED
        return self.status


def confirm_threshold(alpha: float = FALSE_CONFIRM_PROB) -> float:
    """Wald's upper threshold of a sequential test that misses no target: ``ln(1/α)``."""
    return math.log(1.0 / alpha)


def plot_score(log_likelihood: float, log_density: float, p_detect: float = P_DETECT) -> float:
    """A plot's term of the track score (module docstring, 5.): ``ln(P_D N(ν; 0, S) / λ)``
    from ``ln N(ν; 0, S)`` and the sensor's ``ln λ``."""
    return math.log(p_detect) + log_likelihood - log_density


@dataclass
class _Seen:
    """One sensor's plots so far, for :class:`ClutterDensity`."""

    left: int = 0
    t0: float = math.inf
    t1: float = -math.inf
    scans: int = 0  # its distinct plot times (a staring sensor's scans)
    swept: float = 0.0  # Σ azimuth swept within its scans, and their Σ time
    swept_t: float = 0.0
    lo: np.ndarray = None
    hi: np.ndarray = None


# The least span a sensor's component is taken to cover (a sensor that has seen few
# plots, or one target, has seen only a sliver of its coverage): radians, metres.
MIN_SPAN = {EL: math.radians(10.0), RANGE: 10_000.0}


class ClutterDensity:
    r"""Each sensor's false-plot density ``λ`` in its measurement space, per look, from
    its plots no track took (module docstring, 5., 6.: :meth:`see`'s ``left``, less what
    :meth:`unsee` takes back):

    ``λ = n_left / (T · ω · Π spans)``, with ``T`` the time its plots span, ``ω`` the
    azimuth it sweeps per second — a rotating radar's from its plots' times and azimuths
    within a scan (a beam crosses azimuth ``az`` at ``t_scan + az/ω``), a staring
    sensor's a turn per scan — and ``Π spans`` the spans of its other components (range
    from 0, elevation from least to most, at least ``MIN_SPAN``). Without azimuth,
    ``n_left`` over its scans and the spans of all components. At least one plot is
    counted (``λ > 0``)."""

    def __init__(self):
        self.seen: dict[str, _Seen] = {}
        self.counted: set = set()  # the order keys of the plots counted since :meth:`start_frame`

    def start_frame(self) -> None:
        self.counted = set()

    def see(self, scan: Sequence, left: Sequence) -> None:
        """A scan (one sensor's plots of a frame) and those of them no track took."""
        self.counted.update(m.order_key for m in left)
        first = scan[0]
        s = self.seen.get(first.sensor)
        comps = KINDS[first.kind].components
        Z = np.array([m.z for m in scan], float)
        if s is None:
            s = self.seen[first.sensor] = _Seen(lo=Z.min(axis=0), hi=Z.max(axis=0))
        s.left += len(left)
        times = [m.t for m in scan]
        s.t0, s.t1 = min(s.t0, min(times)), max(s.t1, max(times))
        s.scans += len(set(times))  # frames, so scans, do not share a time
        s.lo, s.hi = np.minimum(s.lo, Z.min(axis=0)), np.maximum(s.hi, Z.max(axis=0))
        if AZ in comps:
            k = comps.index(AZ)
            a, b = scan[int(np.argmin(times))], scan[int(np.argmax(times))]
            if b.t > a.t:
                s.swept += abs(float(wrap_pi(b.z[k] - a.z[k])))
                s.swept_t += b.t - a.t

    def unsee(self, sensors: Sequence[str]) -> None:
        """A plot of each of ``sensors`` that was counted was a target's after all (it
        started a track that was confirmed)."""
        for sensor in sensors:
            self.seen[sensor].left -= 1

    def log_density(self, plot) -> float:
        """``ln λ`` of the plot's sensor (``inf``: not seen yet, so no plot of it scores)."""
        s = self.seen.get(plot.sensor)
        if s is None:
            return math.inf
        comps = KINDS[plot.kind].components
        T = max(s.t1 - s.t0, 1e-9)
        volume = 1.0
        for k, c in enumerate(comps):
            if c is AZ:
                continue
            span = s.hi[k] - (0.0 if c is RANGE else s.lo[k])
            volume *= max(span, MIN_SPAN.get(c, 1.0))
        if AZ in comps:
            if s.swept_t > 0.0:
                volume *= s.swept / s.swept_t * T
            else:
                volume *= 2.0 * math.pi * s.scans
        else:
            volume *= s.scans
        return math.log(max(s.left, 1) / max(volume, 1e-300))


@dataclass(frozen=True)
class Spread:
    """The tracks as the screen and the costs read them, once per frame: position and
    velocity ``X (n, 6)`` at the filters' times ``t (n,)``, and the square roots of the
    largest eigenvalues of the horizontal and 3D position (and velocity) covariances,
    which bound the σ of any linear function of unit gradient (module docstring, 1.);
    the states ``x (n, n_x)``, ``P (n, n_x, n_x)``, and ``motion``: the one linear
    motion model (:func:`position_row`) of the tracks ``linear`` marks, whose pairs are
    scored in a stack (:func:`pair_d2`; the others one by one)."""

    X: np.ndarray
    t: np.ndarray
    pos_h: np.ndarray
    pos: np.ndarray
    vel_h: np.ndarray
    vel: np.ndarray
    x: np.ndarray | None = None
    P: np.ndarray | None = None
    linear: np.ndarray | None = None
    motion: object = None

    @classmethod
    def of(cls, tracks: Sequence[Track]) -> "Spread":
        n = len(tracks)
        n_x = tracks[0].filter.x.size if n else 6
        x = np.array([tr.filter.x for tr in tracks], dtype=float).reshape(n, n_x)
        P = np.array([tr.filter.P for tr in tracks], dtype=float).reshape(n, n_x, n_x)
        motion = next((tr.filter.motion for tr in tracks if _linear(tr.filter)), None)
        linear = np.array([_linear(tr.filter) and _same(tr.filter.motion, motion) for tr in tracks], dtype=bool)
        lam = lambda B: np.sqrt(np.clip(np.linalg.eigvalsh(B)[..., -1], 0.0, None))  # noqa: E731
        return cls(x[:, :6].copy(), np.array([tr.filter.t for tr in tracks], dtype=float).reshape(n),
                   lam(P[:, :2, :2]), lam(P[:, :3, :3]), lam(P[:, 3:5, 3:5]), lam(P[:, 3:6, 3:6]),
                   x, P, linear, motion)


def _linear(f) -> bool:
    """Whether a track's filter predicts as :func:`position_row` says: an EKF of a
    constant-velocity or constant-acceleration model (exactly those classes)."""
    return type(f) is TrackEKF and type(f.motion) in (ConstantVelocity, ConstantAcceleration)


def _same(a, b) -> bool:
    return a is b or (type(a) is type(b) and a.q == b.q and a.noise == b.noise and a.q_up == b.q_up)


def position_row(motion, dt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(f (k, m), q₀₀ (k,))``: the first row of the per-axis transition ``F₁(dt)``,
    ``fₐ = dtᵃ/a!``, and the position entry of ``Q₁(dt)`` of a
    :class:`~fusion.motion.ConstantVelocity` or :class:`~fusion.motion.ConstantAcceleration`
    model, for every interval of ``dt (k,)`` at once (:mod:`fusion.motion`'s closed
    forms): continuous white noise of PSD ``q`` on derivative ``m − 1``, ``q dt²ᵐ⁻¹ /
    ((2m − 1)·((m − 1)!)²)`` (CV ``q dt³/3``, CA ``q dt⁵/20``); discrete, ``q (dt²/2)²``
    (per axis times the model's ``axis_scale``, if any)."""
    dt = np.asarray(dt, dtype=float)
    m = motion.order
    f = np.empty((dt.size, m))
    f[:, 0] = 1.0
    f[:, 1] = dt
    if m == 3:
        f[:, 2] = 0.5 * dt * dt
    if motion.noise == "discrete":
        q00 = motion.q * (0.5 * dt * dt) ** 2
    else:
        s = 2 * m - 1
        q00 = motion.q * dt**s / (s * math.factorial(m - 1) ** 2)
    return f, q00


def near(tracks, t: float, plots: Sequence) -> np.ndarray:
    """``(tracks, plots)``: the pairs worth a ``d²`` (module docstring, 1.) for plots of one
    sited sensor with azimuth, elevation or range components (``tracks``: a
    :class:`Spread` or the tracks); a pair it drops is at least ``SCREEN_SIGMAS`` σ away
    in one component, so outside any gate up to χ² of that many σ. Every pair for other
    kinds. With azimuth, only the pairs :func:`_by_azimuth` finds are tested."""
    spread = tracks if isinstance(tracks, Spread) else Spread.of(tracks)
    n = len(spread.t)
    kind = KINDS[plots[0].kind]
    comps = kind.components
    if not kind.sited or not ({AZ, EL, RANGE} & set(comps)) or not n:
        return np.ones((n, len(plots)), dtype=bool)
    X = spread.X
    span = max(abs(p.t - t) for p in plots)
    dt = np.abs(t - spread.t) + span
    pos = X[:, :3] + X[:, 3:6] * (t - spread.t)[:, None] - np.asarray(plots[0].site, float)
    drift = 0.5 * MAX_ACC * dt**2 + np.linalg.norm(X[:, 3:6], axis=1) * span  # beyond the CV line to t
    sig_h = spread.pos_h + spread.vel_h * dt + drift
    sig = spread.pos + spread.vel * dt + drift
    ground = np.hypot(pos[:, 0], pos[:, 1])
    rng = np.hypot(ground, pos[:, 2])
    Z = np.array([p.z for p in plots], float)
    S = np.array([p.std for p in plots], float)
    if AZ in comps:
        k = comps.index(AZ)
        az = np.arctan2(pos[:, 0], pos[:, 1])
        with np.errstate(divide="ignore", invalid="ignore"):  # over the site: every plot
            width = SCREEN_SIGMAS * (sig_h + rng * S[:, k].max()) / ground
        r, j = _by_azimuth(az, width, Z[:, k])
    else:
        r, j = (a.ravel() for a in np.indices((n, len(plots))))
    ok = np.ones(len(r), dtype=bool)
    for k, c in enumerate(comps):
        if c is AZ:  # an azimuth's gradient in metres is horizontal
            miss = np.abs(wrap_pi(az[r] - Z[j, k])) * ground[r]
            bound = sig_h[r] + rng[r] * S[j, k]
        elif c is EL:
            miss = np.abs(np.arctan2(pos[:, 2], ground)[r] - Z[j, k]) * rng[r]
            bound = sig[r] + rng[r] * S[j, k]
        elif c is RANGE:
            miss = np.abs(rng[r] - Z[j, k])
            bound = sig[r] + S[j, k]
        else:
            continue
        ok &= miss <= SCREEN_SIGMAS * bound
    keep = np.zeros((n, len(plots)), dtype=bool)
    keep[r[ok], j[ok]] = True
    return keep


def _by_azimuth(az: np.ndarray, width: np.ndarray, Z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(rows, cols)``: the pairs of tracks at azimuth ``az (n,)`` (seen from the
    sensor) and plots at ``Z (m,)`` within ``width (n,)`` radians of each other (a
    little wider, for round-off), found by bisection in the plots' sorted azimuths
    (each repeated 2π below and above, for the wrap) rather than tried all against all:
    a pair :func:`near` keeps misses by at most ``6 (σ_h + r·σ_az)`` metres across, so
    by at most its track's ``width`` in azimuth."""
    m = len(Z)
    width = np.where(np.isfinite(width), width * (1.0 + 1e-9) + 1e-12, np.inf)
    wide = ~(width < math.pi)  # the whole turn (and any NaN): every plot
    ext = np.concatenate([Z - 2.0 * math.pi, Z, Z + 2.0 * math.pi])
    order = np.argsort(ext, kind="stable")
    ext = ext[order]
    w = np.where(wide, 0.0, width)
    lo = np.searchsorted(ext, az - w, side="left")
    hi = np.searchsorted(ext, az + w, side="right")
    count = np.where(wide, m, hi - lo)
    start = np.where(wide, 0, lo)
    rows = np.repeat(np.arange(len(az)), count)
    at = np.arange(len(rows)) - np.repeat(np.cumsum(count) - count, count) + np.repeat(start, count)
    cols = np.where(np.repeat(wide, count), at, order[np.minimum(at, 3 * m - 1)] % max(m, 1))
    return rows, cols


class SweepTracker(MultiTargetTracker):
    """The tracker's steps on a sweep of plots (module docstring). The parts are a
    :class:`~fusion.tracking.manager.MultiTargetTracker`'s; ``updater`` is a
    :class:`fusion.mtt.ScanUpdater` (its ``scan`` and ``start``), ``rule`` and
    ``revisit_s`` the management (:class:`SweepLogic`)."""

    def __init__(self, initiator, updater, table, associator, gate_prob: float, rule: ManagementRule,
                 revisit_s: float, pair_window_s: float = 0.0):
        super().__init__(None, associator, initiator, updater, table, None)
        if not revisit_s > 0.0:
            raise ValueError(f"revisit_s must be > 0, got {revisit_s}")
        if not pair_window_s >= 0.0:
            raise ValueError(f"pair_window_s must be >= 0, got {pair_window_s}")
        self.gate_prob, self.rule, self.revisit_s = gate_prob, rule, float(revisit_s)
        self.pair_window_s = float(pair_window_s)
        self.clutter = ClutterDensity()
        # (module docstring, 8.) the plots of the last pair_window_s that nothing took, and
        # the order keys of those the false-plot density counted
        self.earlier: list = []
        self.earlier_counted: set = set()

    def taken_over(self, track: Track) -> None:
        """``track`` confirmed as one taken over from another tracker's picture: its life
        kept in time from its estimate's time as a last hit (deleted ``delete_misses``
        revisits after it, as any confirmed track); its sensors and score are not known."""
        track.logic = SweepLogic(self.rule, self.revisit_s, track.last.t, status=CONFIRMED, hits=self.rule.confirm_m,
                                 repeated=True, ranged=True)

    def frame(self, plots: Sequence) -> list[Track]:
        """One frame; returns the confirmed tracks it updated or confirmed, in id order."""
        frame = Frame(plots)
        t_end = plots[-1].t
        tracks = list(self.table.tracks)
        self.clutter.start_frame()
        taken, left = self.associate(tracks, frame)
        births, moved = self.initiator.groups_across(sorted(left, key=lambda m: m.order_key), self.earlier,
                                                     self.pair_window_s)
        births = [g for g in births if starts_alone(g)]
        counted = self.clutter.counted | self.earlier_counted
        origin = lambda m: moved.get(id(m), m)  # noqa: E731
        changed = set()
        for i, track in enumerate(tracks):
            was = track.confirmed
            mine = taken[i]
            plots_i = sorted((m for tk in mine for m in tk.plots), key=lambda m: m.order_key)
            score = 0.0
            if plots_i:
                score = self.update(track, plots_i)
                track.claim(plots_i)
            hit = bool(plots_i) and scores_hit([m.kind for m in {m.sensor: m for m in plots_i}.values()],
                                               track.confirmed, 1)
            track.logic.record(hit, track.filter.P[:3, :3] if plots_i else None, t_end, {m.sensor for m in plots_i},
                               any(fixes(m, EL) for m in plots_i), score, any(fixes(m, RANGE) for m in plots_i),
                               _reporters(plots_i))
            if track.confirmed and not was:
                self.clutter.unsee(track.logic.counted)
            if plots_i or (track.confirmed and not was):
                changed.add(id(track))
        for group in births:
            track, score = self.start(group)
            first, more = group[0], group[1]
            track.logic = SweepLogic(self.rule, self.revisit_s, track.last.t, frozenset(m.sensor for m in (*first, *more)),
                                     any(fixes(m, EL) for m in (*first, *more)), llr=score,
                                     ranged=any(fixes(m, RANGE) for m in more),
                                     reporters=_reporters((*first, *more)),
                                     counted=tuple(m.sensor for m in (*first, *more) if origin(m).order_key in counted))
            if track.confirmed:
                self.clutter.unsee(track.logic.counted)
            self.table.add(track)
            track.claim(initial_plots(group))
            changed.add(id(track))
        self._keep_earlier(left, {origin(m).order_key for g in births for m in (*g[0], *g[1])}, counted, t_end)
        return [tr for tr in self.table.close_frame() if id(tr) in changed]

    def _keep_earlier(self, left: list, used: set, counted: set, t: float) -> None:
        """The plots a later frame may still pair with (module docstring, 8.): the 2D radar
        and angle plots of the last ``pair_window_s`` that no track took and none started."""
        if not self.pair_window_s:
            return
        self.earlier = [m for m in (*self.earlier, *left)
                        if m.order_key not in used and t - m.t <= self.pair_window_s
                        and KINDS[m.kind].start in (RAY, SPHERE)][-EARLIER_MAX:]
        self.earlier_counted = {m.order_key for m in self.earlier if m.order_key in counted}

    def associate(self, tracks: list[Track], frame: Frame) -> tuple[list[list[Taken]], list]:
        """Scan by scan (one sensor's plots), each pair scored at the plot's time; the
        associator sees the tracks with a pair in the screen."""
        taken: list[list[Taken]] = [[] for _ in tracks]
        left: list = []
        spread = Spread.of(tracks)
        confirmed = np.array([tr.confirmed for tr in tracks], dtype=bool)
        for scan in by_sensor(frame.plots):
            keep = near(spread, scan[0].t, scan)
            rows = np.flatnonzero(keep.any(axis=1))
            if not len(rows):
                self.clutter.see(scan, scan)
                left += scan
                continue
            model = model_of(scan[0], tracks[0].filter.x.size)
            gate = gate_threshold(model.n_z, self.gate_prob)
            d2 = np.full((len(rows), len(scan)), np.inf)
            r, j = np.nonzero(keep[rows])
            d2[r, j] = pair_d2(tracks, spread, rows[r], scan, j, model)
            hyp = Hypotheses(scan, rows, d2, np.full(len(rows), gate), confirmed[rows], model)
            association = self.associator.associate(hyp)
            for r, cols, beta, miss in association.per_row():
                taken[rows[r]].append(Taken(tuple(scan[c] for c in cols), tuple(d2[r, list(cols)]), beta, miss))
            used = association.used
            unused = [scan[c] for c in range(len(scan)) if c not in used]
            gated = (d2 <= gate).any(axis=0)  # a target's, which a neighbour's track took
            self.clutter.see(scan, [scan[c] for c in range(len(scan)) if c not in used and not gated[c]])
            left += unused
        return taken, left

    def update(self, track: Track, plots: list) -> float:
        """The filter predicted to each plot's time and updated (plots at one time: one
        scan); returns the plots' score (module docstring, 5.)."""
        plots = [m for m in plots if m.t >= track.filter.t]
        score, i = 0.0, 0
        while i < len(plots):
            j = i
            while j < len(plots) and plots[j].t == plots[i].t:
                j += 1
            score += self._scan(track, plots[i:j])
            i = j
        return score

    def _scan(self, track: Track, scan: list) -> float:
        """:meth:`fusion.mtt.ScanUpdater.scan`'s update of one scan, and its score: each
        piece's ``ln N(ν; 0, S)`` at the state the pieces before it left, each plot's
        ``ln(P_D / λ)``."""
        f = track.filter
        f.predict(scan[0].t)
        steps = [(f.update(model, z), model.n_z) for model, z in self.updater.pieces(scan, self.updater.n_x)]
        nis = sum(r.nis for r, _ in steps)
        track.last = Estimate(scan[0].t, f.x, f.P, self.updater.name, "centre", None, nis, sum(n for _, n in steps))
        log_lik = sum(-0.5 * (r.nis + np.linalg.slogdet(2.0 * math.pi * r.S)[1]) for r, _ in steps)
        return sum(plot_score(0.0, self.clutter.log_density(m)) for m in scan) + log_lik

    def start(self, group) -> tuple[Track, float]:
        """A track from an initiation group ``(first, more, x, P)``: its filter started at
        ``(x, P)`` at the time of ``first``, updated with ``more`` at their own times; and
        its score, that of ``more`` (module docstring, 5.)."""
        first, more, x, P = group
        f = self.updater.new_filter(x, P, first[0].t)
        track = Track(f, Estimate(first[0].t, x, P, self.updater.name, "centre"))
        later = sorted((m for m in more if m.t >= f.t), key=lambda m: m.order_key)  # none before its start
        return track, (self.update(track, later) if later else 0.0)


def pair_d2(tracks: Sequence[Track], spread: Spread, rows: np.ndarray, plots: Sequence, cols: np.ndarray,
            model) -> np.ndarray:
    """``d² (k,)`` of the pairs ``(tracks[rows[i]], plots[cols[i]])``, each track
    predicted to its plot's time, the plots of one sensor ``model`` (:func:`mahalanobis2`;
    ``inf`` where the geometry is undefined). The pairs of a :class:`Spread`'s linear
    tracks and a spherical model in one stack (module docstring, 1.); any other pair,
    and a stack with a pair over a site, one by one."""
    rows, cols = np.asarray(rows, dtype=int), np.asarray(cols, dtype=int)
    times = np.array([plots[c].t for c in cols.tolist()], dtype=float).reshape(len(cols))
    out = np.empty(len(rows))
    stacked = np.zeros(len(rows), dtype=bool)
    if isinstance(model, SphericalModel) and spread.linear is not None:
        stacked = spread.linear[rows] & (times >= spread.t[rows])
    if stacked.any():
        Z = np.array([plots[c].z for c in cols[stacked].tolist()], dtype=float)
        try:
            out[stacked] = _stacked_d2(spread, rows[stacked], times[stacked], Z, model)
        except ValueError:  # a pair over a site: its d² is inf, found one by one
            stacked[:] = False
    for i in np.flatnonzero(~stacked).tolist():
        x, P = tracks[rows[i]].filter.predicted(plots[cols[i]].t)
        out[i] = mahalanobis2(model, x, P, plots[cols[i]].z)[0]
    return out


def _stacked_d2(spread: Spread, rows: np.ndarray, times: np.ndarray, Z: np.ndarray,
                model: SphericalModel) -> np.ndarray:
    """:func:`pair_d2` of linear tracks and a spherical model, in one stack."""
    k = len(rows)
    f, q00 = position_row(spread.motion, times - spread.t[rows])
    m = f.shape[1]
    x = np.zeros((k, model.n_x))
    x[:, :3] = np.einsum("ka,kai->ki", f, spread.x[rows, :3 * m].reshape(k, m, 3))
    G = (f[:, None, :, None] * np.eye(3)[None, :, None, :]).reshape(k, 3, 3 * m)  # f ⊗ I₃
    P = G @ spread.P[rows, :3 * m, :3 * m] @ G.transpose(0, 2, 1)
    P[:, range(3), range(3)] += q00[:, None] * (1.0 if spread.motion.axis_scale is None else spread.motion.axis_scale)
    zp, Hp = batch.spherical(model, x)
    nu = batch.innovation(model, Z, zp)
    S = Hp @ P @ Hp.transpose(0, 2, 1) + model.R
    S = batch._spd_inverse(0.5 * (S + S.transpose(0, 2, 1)))
    return np.einsum("ki,kij,kj->k", nu, S, nu)


def starts_alone(group) -> bool:
    """Whether an initiation group ``(first, more, x, P)`` starts a track here (module
    docstring, 4.): a pair, or a plot that is not a 2D radar's range sphere."""
    first = group[0]
    return len(first) > 1 or KINDS[first[0].kind].start != SPHERE


def _reporters(plots) -> frozenset:
    """The sensors of the position reports among ``plots`` (module docstring, 9.)."""
    return frozenset(m.sensor for m in plots if not KINDS[m.kind].sited)
