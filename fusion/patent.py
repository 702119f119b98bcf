r"""The patent's six 3D fusion methods (document 004) and the single-sensor baselines.

Sensors: 2D radars (``range_az``), angle sensors (``azel``) and, for a baseline, 3D
radars (``az_el_range``); a sensor's role is its measurement kind, never its id, and the
methods take every kind of the ``3d`` family (:mod:`fusion.measurement.kinds`). Every
method shares one motion model (:mod:`fusion.motion`), the measurement models
(:mod:`fusion.measurement.models`), one filter step and one initialiser
(:mod:`fusion.init3d`), so their differences are the methods' own:

* LCDD ``z = [az_i, el_i, range_r]``; HNDD ``z = [az_f, el_i, range_r]`` with ``az_f``
  the inverse-variance fusion of the two azimuths, each from the scan's first ray (angle
  sensor) and sphere (2D radar), every other report one update of its own; SS the
  stacked ``z = [az_i, el_i, az_r, range_r, …]``, ``R = blkdiag(R_i, R_r, …)`` — one
  filter each;
* HNV / PHHNV / DDHNV: a :class:`LocalTracker` per sensor and a
  :class:`~fusion.track_fusion.TrackFuser` at the centre, split in :mod:`fusion.network`;
* RADAR2D / ANGLE / RADAR3D: one filter on one kind of sensor.

A centralised method takes measurements in ``(t, sensor, seq)`` order, groups them into
scans (:class:`fusion.grouping.TimeGrouper`), processes a scan at its first
measurement's time (a scan of one sensor alone, unpaired measurements one after
another) and emits one estimate per scan. The methods, scans, outputs and the
``[tracker]`` keys (:class:`TrackerConfig`): docs/algorithms.md, "The six methods",
"Scans", "The ``[tracker]`` table of a 3D method".
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Callable, Protocol, Sequence

import numpy as np

from .angles import wrap_2pi, wrap_pi
from .config import config_values
from .init3d import InitPriors, initial_state
from .motion import make_motion, NOISE_FORMS
from .filters import FILTERS, Filter, NewFilter, filter_factory
from .grouping import TimeGrouper
from .guards import MAX_GAP_S, epoch_nis, gap_too_long, positive_definite
from .imm import IMM_MODELS, model_set
from .links import Gaussian, LocalReport, ModelStates, ModelTerms, PredictionReport
from .measurement.kinds import KINDS, RAY, SPHERE, kinds_of, model_of
from .measurement.models import MeasurementModel, spherical, stack
from .track_fusion import CI_CRITERIA, FUSION_RULES
from .types import Estimate, Measurement

MOTIONS = ("ca", "cv", "imm")
KINDS_3D = kinds_of("3d")
COLOCATED_TOL = 1e-3  # m: HNDD fuses two azimuths only if they are measured from one point


class Method(Protocol):
    """The streaming interface every method (patent, DF, IMM, ...) implements."""

    name: str

    def process(self, m: Measurement) -> list[Estimate]: ...
    def advance(self, t: float) -> list[Estimate]: ...
    def finish(self) -> list[Estimate]: ...


# Configuration -----------------------------------------------------------------------
@dataclass(frozen=True)
class TrackerConfig:
    """The ``[tracker]`` table of a scenario; see the module docstring for the keys."""

    motion: str = "ca"
    q: float = 0.01
    q_up: float = math.nan  # the up axis's own q (fusion.motion); NaN: q
    process_noise: str = "continuous"
    fusion_rule: str = "info"
    ci_criterion: str = "trace"
    pair_tol: float = 1e-3
    init_range: float = InitPriors.range
    init_range_std: float = InitPriors.range_std
    init_el: float = InitPriors.el
    init_el_std: float = InitPriors.el_std
    init_vel_std: float = InitPriors.vel_std
    init_vel_std_up: float = InitPriors.vel_std_up
    init_acc_std: float = InitPriors.acc_std
    init_acc_std_up: float = InitPriors.acc_std_up
    ekf_iterations: int = 1
    filter: str = "ekf"
    imm_models: str = "cv,ct,ca"
    imm_q_cv: float = 0.01
    imm_q_ct: float = 10.0
    imm_q_turn: float = 10.0
    imm_q_ca: float = 900.0
    imm_turn_rates: str = "0.157,0.235"
    imm_sojourn_cv: float = 20.0
    imm_sojourn_ct: float = 15.0
    imm_sojourn_turn: float = 15.0
    imm_sojourn_ca: float = 2.0
    max_gap_s: float = MAX_GAP_S
    max_climb: float = math.inf  # m/s; the EKF's estimate projected onto |v_up| <= it (fusion.ekf)

    @classmethod
    def from_dict(cls, config: dict | None) -> "TrackerConfig":
        values = config_values(cls, config, "tracker config")
        if not float(values.get("ekf_iterations", 1)).is_integer():
            raise ValueError(f"tracker config 'ekf_iterations' must be an integer, got {values['ekf_iterations']}")
        cfg = cls(**{k: v if isinstance(v, str) else int(v) if k == "ekf_iterations" else float(v)
                     for k, v in values.items()})
        cfg._validate()
        return cfg

    def _validate(self) -> None:
        if self.motion not in MOTIONS:
            raise ValueError(f"tracker config 'motion' must be one of {MOTIONS}, got {self.motion!r}")
        if self.process_noise not in NOISE_FORMS:
            raise ValueError(f"tracker config 'process_noise' must be one of {NOISE_FORMS}, got {self.process_noise!r}")
        if self.fusion_rule not in FUSION_RULES:
            raise ValueError(f"tracker config 'fusion_rule' must be one of {FUSION_RULES}, got {self.fusion_rule!r}")
        if self.filter not in FILTERS:
            raise ValueError(f"tracker config 'filter' must be one of {tuple(FILTERS)}, got {self.filter!r}")
        if self.ci_criterion not in CI_CRITERIA:
            raise ValueError(f"tracker config 'ci_criterion' must be one of {CI_CRITERIA}, got {self.ci_criterion!r}")
        if self.q < 0.0:
            raise ValueError(f"tracker config 'q' must be >= 0, got {self.q}")
        if not math.isnan(self.q_up) and self.motion != "imm" and not (self.q_up >= 0.0 and self.q > 0.0):
            raise ValueError(f"tracker config 'q_up' must be >= 0, with q > 0, got {self.q_up}")
        if self.pair_tol < 0.0:
            raise ValueError(f"tracker config 'pair_tol' must be >= 0, got {self.pair_tol}")
        if not self.max_gap_s > 0.0:
            raise ValueError(f"tracker config 'max_gap_s' must be > 0, got {self.max_gap_s}")
        if not self.max_climb > 0.0:
            raise ValueError(f"tracker config 'max_climb' must be > 0, got {self.max_climb}")
        if math.isfinite(self.max_climb) and self.filter != "ekf":
            raise ValueError(f"tracker config 'max_climb' bounds the 'ekf' filter's estimate; "
                             f"filter is {self.filter!r}")
        for key in ("init_range", "init_range_std", "init_el_std", "init_vel_std", "init_vel_std_up", "init_acc_std", "init_acc_std_up"):
            if getattr(self, key) <= 0.0:
                raise ValueError(f"tracker config {key!r} must be > 0, got {getattr(self, key)}")
        if not 1 <= self.ekf_iterations <= 50:
            raise ValueError(f"tracker config 'ekf_iterations' must lie in 1..50, got {self.ekf_iterations}")
        names = self.imm_model_names()
        if not names or len(set(names)) != len(names) or not set(names) <= set(IMM_MODELS):
            raise ValueError(f"tracker config 'imm_models' must be distinct names among {IMM_MODELS} "
                             f"separated by commas, got {self.imm_models!r}")
        for key in ("imm_q_cv", "imm_q_ct", "imm_q_turn", "imm_q_ca"):
            if getattr(self, key) < 0.0:
                raise ValueError(f"tracker config {key!r} must be >= 0, got {getattr(self, key)}")
        try:
            rates = self.imm_turn_rate_values()
        except ValueError:
            rates = ()
        if not rates or not all(np.isfinite(w) and w > 0.0 for w in rates):
            raise ValueError(f"tracker config 'imm_turn_rates' must be rates > 0 rad/s separated by commas, "
                             f"got {self.imm_turn_rates!r}")
        for key in ("imm_sojourn_cv", "imm_sojourn_ct", "imm_sojourn_turn", "imm_sojourn_ca"):
            if not getattr(self, key) > 0.0:
                raise ValueError(f"tracker config {key!r} must be > 0 s, got {getattr(self, key)}")
        if abs(self.init_el) >= np.pi / 2:
            raise ValueError(f"tracker config 'init_el' must lie in (-π/2, π/2) rad, got {self.init_el}")

    def imm_model_names(self) -> tuple[str, ...]:
        return tuple(n.strip() for n in self.imm_models.split(",") if n.strip())

    def imm_turn_rate_values(self) -> tuple[float, ...]:
        return tuple(float(w) for w in self.imm_turn_rates.split(",") if w.strip())

    def motion_model(self):
        """The motion model, or for ``motion = "imm"`` the IMM's :class:`fusion.imm.ModelSet`."""
        if self.motion == "imm":
            q = {"cv": self.imm_q_cv, "ct": self.imm_q_ct, "turn": self.imm_q_turn, "ca": self.imm_q_ca}
            sojourn = {"cv": self.imm_sojourn_cv, "ct": self.imm_sojourn_ct, "turn": self.imm_sojourn_turn,
                       "ca": self.imm_sojourn_ca}
            return model_set(self.imm_model_names(), q, self.imm_turn_rate_values(), sojourn, self.process_noise)
        return make_motion(self.motion, self.q, self.process_noise, None if math.isnan(self.q_up) else self.q_up)

    def new_filter(self, motion, centralised: bool = False) -> NewFilter:
        """The track filter's factory; ``ekf_iterations`` applies to the centralised methods."""
        return filter_factory(self.filter, motion, self.ekf_iterations if centralised else 1,
                              max_climb=self.max_climb if math.isfinite(self.max_climb) else None)

    def priors(self) -> InitPriors:
        return InitPriors(
            range=self.init_range,
            range_std=self.init_range_std,
            el=self.init_el,
            el_std=self.init_el_std,
            vel_std=self.init_vel_std,
            vel_std_up=self.init_vel_std_up,
            acc_std=self.init_acc_std,
            acc_std_up=self.init_acc_std_up,
        )


def uses(name: str, kinds: frozenset, m: Measurement) -> bool:
    """Whether method ``name``, which takes measurements of ``kinds``, uses ``m``; a
    measurement no 3D method can use (a bearing) is an error, not silently ignored."""
    if m.kind not in KINDS_3D:
        raise ValueError(f"{name} cannot use a {m.kind!r} measurement (sensor {m.sensor!r})")
    return m.kind in kinds


class GroupedMethod:
    """The streaming shell of a 3D method that works on groups of measurements (a
    one-target method's scans, a many-target method's frames): the measurements it
    uses go to its grouper, and every group the grouper closes to :meth:`_group`.
    Subclasses set ``name``, ``kinds`` and ``_grouper``."""

    name: str
    kinds: frozenset = KINDS_3D  # kinds used; other 3D kinds are ignored

    def process(self, m: Measurement) -> list[Estimate]:
        if not uses(self.name, self.kinds, m):
            return []
        return self._run(self._grouper.push(m))

    def advance(self, t: float) -> list[Estimate]:
        return self._run(self._grouper.advance(t))

    def finish(self) -> list[Estimate]:
        return self._run(self._grouper.finish())

    @property
    def group_tol(self) -> float:
        """The time window of a group (``pair_tol``): a group at ``t`` holds what is up to ``t`` + this."""
        return self._grouper.tol

    def _run(self, groups: list[list[Measurement]]) -> list[Estimate]:
        out: list[Estimate] = []
        for group in groups:
            out += self._group(group)
        return out

    def _group(self, group: list[Measurement]) -> list[Estimate]:
        raise NotImplementedError


class ScanMethod(GroupedMethod):
    """Base of the patent methods: a :class:`GroupedMethod` on :class:`~fusion.grouping.TimeGrouper`
    scans. Subclasses implement :meth:`process_scan`.
    """

    def __init__(self, name: str, config: TrackerConfig, track: str = "T1"):
        self.name = name
        self.config = config
        self.track = track
        self.motion = config.motion_model()
        self.n_x = self.motion.n_x
        self.priors = config.priors()
        self._grouper = TimeGrouper(config.pair_tol, one_per_sensor=True)

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.name!r})"

    def _group(self, scan: list[Measurement]) -> list[Estimate]:
        return self.process_scan(scan)

    def process_scan(self, scan: list[Measurement]) -> list[Estimate]:
        """The estimates of one closed scan."""
        raise NotImplementedError


# Centralised methods: how a scan becomes measurement updates --------------------------
Piece = tuple[MeasurementModel, np.ndarray]


def _model(m: Measurement, n_x: int) -> Piece:
    return model_of(m, n_x), np.asarray(m.z, dtype=float)


def _component(m: Measurement, name: str) -> tuple[float, float]:
    i = KINDS[m.kind].index(name)
    return float(m.z[i]), float(m.std[i])


def _pair(scan: Sequence[Measurement]):
    """The first angle sensor (a ray) and first 2D radar (a sphere) of a scan, and the rest."""
    angle = next((m for m in scan if KINDS[m.kind].start == RAY), None)
    radar = next((m for m in scan if KINDS[m.kind].start == SPHERE), None)
    if angle is None or radar is None:
        return None, None, list(scan)
    return angle, radar, [m for m in scan if m is not angle and m is not radar]


def pieces_stacked(scan: Sequence[Measurement], n_x: int) -> list[Piece]:
    """SS: every measurement of the scan in one stacked update."""
    models = [_model(m, n_x) for m in scan]
    return [(stack([p[0] for p in models]), np.concatenate([p[1] for p in models]))]


def pieces_lcdd(scan: Sequence[Measurement], n_x: int) -> list[Piece]:
    """LCDD: ``[az_i, el_i, range_r]`` (each row from its own sensor's site), then the rest."""
    angle, radar, rest = _pair(scan)
    pieces = []
    if angle is not None:
        (az, s_az), (el, s_el), (rg, s_rg) = _component(angle, "az"), _component(angle, "el"), _component(radar, "range")
        a, r = (tuple(np.asarray(m.site, dtype=float).tolist()) for m in (angle, radar))
        model = spherical(("az", "el", "range"), (a, a, r), (s_az, s_el, s_rg), n_x)
        pieces.append((model, np.array([az, el, rg])))
    return pieces + [_model(m, n_x) for m in rest]


def pieces_hndd(scan: Sequence[Measurement], n_x: int) -> list[Piece]:
    """HNDD: ``[az_f, el_i, range_r]`` with the inverse-variance fused azimuth, then the rest."""
    angle, radar, rest = _pair(scan)
    pieces = []
    if angle is not None:
        gap = float(np.max(np.abs(np.asarray(angle.site, float) - np.asarray(radar.site, float))))
        if gap > COLOCATED_TOL:
            raise ValueError(
                f"HNDD fuses the azimuths of {angle.sensor!r} and {radar.sensor!r}, which needs co-located "
                f"sensors; their sites differ by {gap:.3g} m (use LCDD or SS)"
            )
        (az_i, s_i), (el, s_el), (az_r, s_r), (rg, s_rg) = (
            _component(angle, "az"),
            _component(angle, "el"),
            _component(radar, "az"),
            _component(radar, "range"),
        )
        w_r = s_i**2 / (s_i**2 + s_r**2)
        az_f = wrap_2pi(az_i + w_r * wrap_pi(az_r - az_i))
        s_f = s_i * s_r / np.hypot(s_i, s_r)
        model = spherical(("az", "el", "range"), tuple(np.asarray(angle.site, dtype=float).tolist()),
                          (float(s_f), s_el, s_rg), n_x)
        pieces.append((model, np.array([az_f, el, rg])))
    return pieces + [_model(m, n_x) for m in rest]


class CentralisedMethod(ScanMethod):
    """One track filter at the centre; ``pieces(scan, n_x)`` turns a scan into updates
    applied in turn.

    LCDD, HNDD, SS and the single-sensor baselines are this class with different
    ``pieces`` and ``kinds``. :attr:`filter` (a :class:`fusion.filters.Filter`, None
    before the first scan) is the track's state; :meth:`process_scan` and :meth:`coast`
    are what a many-target manager drives per track (:class:`fusion.mtt.MultiTargetMethod`).
    """

    def __init__(self, name, config, pieces: Callable[[Sequence[Measurement], int], list[Piece]], kinds=KINDS_3D):
        super().__init__(name, config)
        self.kinds = frozenset(kinds)
        self._pieces = pieces
        self._new_filter = config.new_filter(self.motion, centralised=True)
        self.filter: Filter | None = None
        self.restarts = 0  # tracks started afresh (fusion.guards)

    def process_scan(self, scan):
        """The scan's update; a first scan, or one after a gap of more than ``max_gap_s``
        or that leaves the covariance not positive definite, starts the track afresh
        (:mod:`fusion.guards`; counted in ``restarts``)."""
        t = scan[0].t
        if self.filter is None or gap_too_long(t - self.filter.t, self.config.max_gap_s):
            return [self.start(*initial_state(scan, self.n_x, self.priors), t)]
        self.filter.predict(t)
        terms = [(self.filter.update(model, z).nis, model.n_z) for model, z in self._pieces(scan, self.n_x)]
        if not positive_definite(self.filter.P):
            return [self.start(*initial_state(scan, self.n_x, self.priors), t)]
        return [Estimate(t, self.filter.x, self.filter.P, self.name, "centre", self.track, *epoch_nis(terms))]

    def start(self, x: np.ndarray, P: np.ndarray, t: float) -> Estimate:
        """Start the track's filter at ``(x, P)`` at ``t`` (what :meth:`process_scan` does
        with a first scan's initial state; a many-target manager passes its own)."""
        self.restarts += self.filter is not None
        self.filter = self._new_filter(x, P, t)
        return Estimate(t, x, P, self.name, "centre", self.track)

    def coast(self, t: float) -> Estimate:
        """Predict to ``t`` without a measurement (a missed frame); the estimate has no track id."""
        f = self.filter
        f.predict(t)
        return Estimate(f.t, f.x, f.P, self.name, "centre")


# Distributed methods: local trackers + centre fuser ------------------------------------
class LocalTracker:
    """The local track filter of HNV/PHHNV/DDHNV, as a node runs it (one per local track).

    * :meth:`initialise` / :meth:`accept_prior`: (re)start from an estimate sent by the
      centre (the shared initial state, or the fused estimate fed back);
    * :meth:`update`: predict to ``t`` and update with a measurement, as a
      :class:`~fusion.links.LocalReport` (the prior, ``K·H``, the time of the centre
      estimate it restarted from since its previous report, and the filter's per-model
      terms if it has models: ``model_terms()``, :mod:`fusion.track_fusion`);
    * :meth:`predict`: predict to a measurement's time, as a
      :class:`~fusion.links.PredictionReport` carrying that measurement.

    ``node`` is the id of the node that runs it (the reports' ``node``); ``new_filter``
    builds the filter (:data:`fusion.filters.NewFilter`; default the EKF).
    """

    def __init__(self, node: str, motion, method: str = "HNV", track: str = "T1",
                 new_filter: NewFilter | None = None):
        self.node = node
        self.motion = motion
        self.method = method
        self.track = track
        self.new_filter = new_filter or filter_factory("ekf", motion)
        self.filter: Filter | None = None
        self._feedback_t: float | None = None

    @property
    def initialised(self) -> bool:
        return self.filter is not None

    @property
    def t(self) -> float:
        return self.filter.t

    @property
    def x(self) -> np.ndarray:
        return self.filter.x

    @property
    def P(self) -> np.ndarray:
        return self.filter.P

    def predicted(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        return self.filter.predicted(t)

    def initialise(self, x: np.ndarray, P: np.ndarray, t: float) -> None:
        self.filter = self.new_filter(x, P, t)
        self._feedback_t = float(t)

    def accept_prior(self, x: np.ndarray, P: np.ndarray, t: float, models: ModelStates | None = None) -> None:
        """Feedback: the centre's estimate becomes the next prior (the filter restarts
        from it, keeping what it holds beyond ``(x, P)``, e.g. an IMM's mode probabilities).
        ``models``: a per-model centre's states (:meth:`fusion.track_fusion.TrackFuser.model_states`),
        which a filter with models restarts from instead (its ``set_model_states``)."""
        if self.filter is None:
            self.initialise(x, P, t)
        if models is not None:
            restart = getattr(self.filter, "set_model_states", None)
            if restart is None:
                raise ValueError(f"local tracker of {self.node!r}: per-model states for a filter without models")
            restart(models.xs, models.Ps, models.mu, t)
        else:
            self.filter.set_state(x, P, t)
        self._feedback_t = float(t)

    def _estimate(self, nis=None, dof=None) -> Estimate:
        f = self.filter
        return Estimate(f.t, f.x, f.P, self.method, self.node, self.track, nis, dof)

    def _since_feedback(self) -> tuple[float | None, ModelTerms | None]:
        """The report's ``feedback_t`` (then forgotten: a report says it once) and the
        filter's per-model terms, if it has models."""
        fb, self._feedback_t = self._feedback_t, None
        terms = getattr(self.filter, "model_terms", None)
        return fb, terms() if terms is not None else None

    def _require(self):
        if self.filter is None:
            raise ValueError(f"local tracker of {self.node!r} has no prior yet (initialise it from the centre)")

    def predict(self, m: Measurement, seq: int) -> PredictionReport:
        """Predict to ``m``'s time: the report of the prediction, with ``m`` (the node's
        ``seq``-th message)."""
        self._require()
        self.filter.predict(m.t)
        return PredictionReport(m.t, self.node, seq, self._estimate(), m, *self._since_feedback())

    def update(self, m: Measurement, seq: int, t: float | None = None) -> LocalReport:
        """Update with ``m`` at time ``t`` (default ``m.t``; the scan time at a centre that
        runs the update itself): the report (the node's ``seq``-th message)."""
        self._require()
        self.filter.predict(m.t if t is None else t)
        prior = Gaussian(self.filter.x, self.filter.P)
        model, z = _model(m, self.filter.x.size)
        res = self.filter.update(model, z)
        return LocalReport(self.filter.t, self.node, seq, self._estimate(res.nis, model.n_z), prior, self.filter.KH,
                           *self._since_feedback())

    def update_weighted(self, model, Z: np.ndarray, beta, beta0: float, t: float, seq: int,
                        existence: float | None = None) -> LocalReport:
        """Predict to ``t`` and make the weighted (PDA) update with this sensor's plots
        ``Z`` of one scan, ``beta`` each and ``beta0`` for none (JIPDA's local tracks;
        :mod:`fusion.pda`): the report (the node's ``seq``-th message), carrying the
        track's ``existence``. Its NIS is the combined innovation's, ``ν̄ᵀS⁻¹ν̄`` (below a
        χ² variable: ν̄ shrinks with β₀)."""
        self._require()
        self.filter.predict(t)
        prior = Gaussian(self.filter.x, self.filter.P)
        res = self.filter.update_weighted(model, Z, beta, beta0)
        nis = float(res.nu @ np.linalg.solve(res.S, res.nu))
        estimate = dataclasses.replace(self._estimate(nis, model.n_z), existence=existence)
        return LocalReport(self.filter.t, self.node, seq, estimate, prior, self.filter.KH, *self._since_feedback())


# Factories ---------------------------------------------------------------------------
def centralised(name: str, pieces, kinds, config: dict | None) -> CentralisedMethod:
    """A centralised method (LCDD, HNDD, SS, a baseline) from a resolved ``[tracker]`` table."""
    return CentralisedMethod(name, TrackerConfig.from_dict(config), pieces, kinds)
