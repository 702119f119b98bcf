"""The bearings-only localisation methods as streaming Methods.

Every method follows the library's streaming interface: ``process(m)`` takes bearings in
``(t, sensor, seq)`` order, ``advance(t)`` a watermark (nothing with time ≤ t will
come), ``finish()`` the end of the stream; each returns the estimates it can release.

**Epochs.** Bearings within ``pair_tol`` of the first bearing of a group form one epoch
(one scan of the DF network; one bearing for a single moving observer), cut by
:class:`fusion.grouping.TimeGrouper` like every method's groups, so the output depends
on the bearings alone. An epoch's bearings are processed in arrival order and one
:class:`~fusion.types.Estimate` (``[px, py]``, or ``[px, py, vx, vy]`` with
``motion = "cv"``) is emitted, stamped with its latest bearing's time, from the first
epoch with a fix; an incomplete epoch is processed as it is. Its track id is ``E1``, as
the first emitter of a many-emitter picture (:mod:`fusion.df.multi`), so a fix is called
the same from a site, a scenario and the many-emitter tracker.

**Start-up and restarts.** Until two bearings give a fix, the recursive methods hold
bearings: at most :data:`HELD_PER_STATION` per station (its latest) and none more than
``max_gap_s`` older than the newest; what the bound drops is counted (``n_dropped`` in
every estimate's ``extra``). A filter not updated for ``max_gap_s``, or whose covariance
is no longer positive definite, starts afresh from the epoch at hand; an epoch's NIS
sums at most 64 terms, its latest (:mod:`fusion.guards`).

**Methods** (``DF_METHODS[name](config)``): EKF, MEKF1..5 (two cross-fed filters), IMM
(clean and outlier bearing models), TORRIERI (weighted least squares on all bearings),
KF+TR and MKF+TR (per-station bearing smoothers, then Torrieri). The table of what each
does, the motion models, the initialisation and the maths: docs/algorithms.md
("Bearings-only emitter localisation", "The methods"); :class:`DFConfig` the keys.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from typing import Callable, Mapping, NamedTuple

import numpy as np

from ..config import config_values
from ..grouping import TimeGrouper
from ..guards import MAX_GAP_S, epoch_nis, gap_too_long, positive_definite
from ..types import Estimate, Measurement
from .filters import MEKF, MEKF_VARIANTS, BearingEKF, CrossFed
from .imm import TRANSITIONS, BearingIMM, transition_matrix
from .init import SAME_SITE, ranked_pairs, usable_pairs
from .models import (
    EMITTER_MOTIONS,
    THESIS_SIGMA,
    ConstantVelocityEmitter,
    EmitterModel,
    StaticEmitter,
    bearing_of,
    emitter_Q,
    stated_sigma,
)
from .smoothing import BearingSmoother, CrossFedBearingSmoother
from .triangulation import Fix, GeometryError, fix_from_bearings, ipu, leave_one_out, pairwise_intersection_mean

#: initialisations of the recursive methods (config ``init``).
INITS = ("ipu", "robust")
#: bearings of one station a recursive method holds while it waits for a fix (its latest)
HELD_PER_STATION = 16
EMITTER_PREFIX = "E"  # an emitter's track id: E1 (one emitter), E1, E2, ... (many, fusion.df.multi)


@dataclass(frozen=True)
class DFConfig:
    """Validated ``[tracker]`` table of the DF methods. Every DF method accepts every key,
    so one table can drive several methods; any other key is an error.

    ====================== =========== =======================================================
    key                    default     meaning
    ====================== =========== =======================================================
    motion                 "static"    emitter motion: ``"static"`` (state [x, y]) or ``"cv"`` (constant
                                       velocity, [x, y, vx, vy]; EKF, MEKF1..5 and IMM only)
    q                      1.0         ``"cv"``: white-acceleration PSD per axis (m²/s³); 1 m²/s³ lets
                                       the velocity wander ≈1 m/s in a second (a vehicle turning)
    init_vel_std           20.0        ``"cv"``: initial velocity std per axis around zero (m/s;
                                       covers road speeds)
    q22                    0.0         ``"static"``: process noise on y (m²) added before every bearing; 0: the
                                       static-emitter model, which keeps converging (to the CRB)
                                       however long it runs. The theses' random walk, 625 m²
                                       (``THESIS_Q22``, 0.025² km²), is for reproducing them (their
                                       scenarios set it): it stalls (docs/algorithms.md)
    q11                    0.0         ``"static"``: process noise on x (m²); the theses have 0
    sigma                  0.0175      bearing std assumed by the filters (rad), or
                                       ``"sensor"`` to use each measurement's stated std
    pair_tol               0.0         epoch grouping tolerance (s); 0 = one epoch per timestamp, so
                                       the watermark at that time closes it with no extra latency
    ipu_cov                "full"      ``"full"`` or ``"diagonal"`` (the thesis's) initial covariance
    ipu_max_rel            1.0         refuse an ``ipu`` fix whose 1σ semi-major axis exceeds this
                                       multiple of its range (ill-conditioned crossing); 0 = accept any
    init                   "ipu"       initialisation of EKF/MEKF/IMM: ``"ipu"`` (first usable pair) or
                                       ``"robust"`` (best-supported pair of the first ``init_epochs``)
    init_epochs            5           epochs in the robust initialiser's window (integer >= 1;
                                       docs/notes.md, "Robust initialiser window")
    mekf_handoff           "swap"      MEKF/MKF hand-over: ``"swap"`` (states and covariances) or
                                       ``"printed"`` (the thesis listing: A2's covariance stays P₀)
    imm_p                  0.1         IMM mode-switch/outlier probability p, in (0, 1)
    imm_sigma2             0.25        IMM outlier-model bearing std σ₂ (rad; a std, not a variance)
    imm_transition         "symmetric" ``"symmetric"`` [[1−p,p],[p,1−p]] or ``"iid"`` [[1−p,p],[1−p,p]]
    imm_mu0                0.05        initial probability of the outlier model (the thesis's 0.05)
    torrieri_iterations    0           0 = Gauss–Newton to convergence; k ≥ 1 = k Torrieri steps
    torrieri_bearings      10000       TORRIERI: the latest bearings it keeps (integer >= 2; a
                                       live fuser's memory and per-epoch time are bounded by it)
    smoother_q             0.0         KF/MKF bearing-smoother process noise (rad² per bearing)
    gate                   0.0         leave-one-out bound (studentised residual, in σ) for
                                       TORRIERI and the KF+TR/MKF+TR centre; 0 = off
    max_gap_s              600.0       EKF/MEKF/IMM: a filter not updated for longer starts
                                       afresh from the next epoch, and held bearings older
                                       than this before the newest are dropped (s; :mod:`fusion.guards`)
    ====================== =========== =======================================================
    """

    motion: str = "static"
    q: float = 1.0
    init_vel_std: float = 20.0
    q22: float = 0.0
    q11: float = 0.0
    sigma: float | str = THESIS_SIGMA
    pair_tol: float = 0.0
    ipu_cov: str = "full"
    ipu_max_rel: float = 1.0
    init: str = "ipu"
    init_epochs: int = 5
    mekf_handoff: str = "swap"
    imm_p: float = 0.1
    imm_sigma2: float = 0.25
    imm_transition: str = "symmetric"
    imm_mu0: float = 0.05
    torrieri_iterations: int = 0
    torrieri_bearings: int = 10_000
    smoother_q: float = 0.0
    gate: float = 0.0
    max_gap_s: float = MAX_GAP_S

    def sigma_of(self, m: Measurement) -> float:
        """The std the filters and gates assume for the bearing ``m``: ``sigma``, or the
        sensor's stated std with ``sigma = "sensor"``."""
        return stated_sigma(m) if self.sigma == "sensor" else float(self.sigma)

    @classmethod
    def from_dict(cls, config: dict | None) -> "DFConfig":
        cfg = cls(**config_values(cls, config, "DF tracker config", {"sigma": ("sensor",)}))
        cfg._validate()
        return cfg

    def _validate(self) -> None:
        def need(ok: bool, key: str, what: str) -> None:
            if not ok:
                raise ValueError(f"config {key!r} = {getattr(self, key)!r}: {what}")

        need(self.motion in EMITTER_MOTIONS, "motion", f"must be one of {EMITTER_MOTIONS}")
        need(self.q >= 0, "q", "must be >= 0")
        need(self.init_vel_std > 0, "init_vel_std", "must be > 0")
        if self.motion == "cv":
            need(self.q22 == 0 and self.q11 == 0, "q22" if self.q22 else "q11",
                 "is the static emitter's process noise; with motion = \"cv\" set q (m²/s³)")
        need(self.q22 >= 0, "q22", "must be >= 0")
        need(self.q11 >= 0, "q11", "must be >= 0")
        need(self.sigma == "sensor" or self.sigma > 0, "sigma", "must be > 0 or \"sensor\"")
        need(self.pair_tol >= 0, "pair_tol", "must be >= 0")
        need(self.ipu_cov in ("full", "diagonal"), "ipu_cov", "must be \"full\" or \"diagonal\"")
        need(self.ipu_max_rel >= 0, "ipu_max_rel", "must be >= 0")
        need(self.init in INITS, "init", f"must be one of {INITS}")
        need(float(self.init_epochs).is_integer() and self.init_epochs >= 1, "init_epochs", "must be an integer >= 1")
        need(self.mekf_handoff in CrossFed.HANDOFFS, "mekf_handoff", f"must be one of {CrossFed.HANDOFFS}")
        need(0 < self.imm_p < 1, "imm_p", "must be in (0, 1)")
        need(self.imm_sigma2 > 0, "imm_sigma2", "must be > 0")
        need(self.imm_transition in TRANSITIONS, "imm_transition", f"must be one of {TRANSITIONS}")
        need(0 < self.imm_mu0 < 1, "imm_mu0", "must be in (0, 1)")
        need(float(self.torrieri_iterations).is_integer() and self.torrieri_iterations >= 0,
             "torrieri_iterations", "must be an integer >= 0")
        need(float(self.torrieri_bearings).is_integer() and self.torrieri_bearings >= 2,
             "torrieri_bearings", "must be an integer >= 2")
        need(self.smoother_q >= 0, "smoother_q", "must be >= 0")
        need(self.gate >= 0, "gate", "must be >= 0")
        need(self.max_gap_s > 0, "max_gap_s", "must be > 0")

    @property
    def Q(self) -> np.ndarray:
        return emitter_Q(self.q22, self.q11)

    @property
    def model(self) -> EmitterModel:
        """The emitter model the recursive filters take (:mod:`fusion.df.models`)."""
        return ConstantVelocityEmitter(self.q) if self.motion == "cv" else StaticEmitter(self.Q)


class DFMethod:
    """Base of the DF methods: config, stream checks and epoch grouping.

    Subclasses implement :meth:`_epoch`, which processes one closed epoch and returns
    an Estimate or None (no fix yet).
    """

    name: str = "DF"
    #: the ``motion`` values the method accepts
    motions: tuple[str, ...] = ("static",)

    def __init__(self, config: dict | None = None):
        self.config = DFConfig.from_dict(config)
        if self.config.motion not in self.motions:
            raise ValueError(f"{self.name} fits one fixed position to all the bearings so far: motion = "
                             f"{self.config.motion!r} does not apply (a moving emitter: EKF, MEKF1..5 or IMM)")
        self._grouper = TimeGrouper(self.config.pair_tol)
        self._finished = False

    # -- streaming interface -------------------------------------------------------
    def process(self, m: Measurement) -> list[Estimate]:
        if self._finished:
            raise ValueError(f"{self.name}: process() after finish()")
        if not np.isfinite(m.t):
            raise ValueError(f"{self.name}: measurement from {m.sensor!r} has non-finite time {m.t}")
        bearing_of(m)  # validate early, so a bad message fails at its arrival
        try:
            return self._close(self._grouper.push(m))
        except ValueError as e:  # out of order, or at or before a watermark
            raise ValueError(f"{self.name}: {e}") from None

    def advance(self, t: float) -> list[Estimate]:
        if not np.isfinite(t):
            raise ValueError(f"{self.name}: watermark must be finite, got {t}")
        return self._close(self._grouper.advance(t))

    def finish(self) -> list[Estimate]:
        out = self._close(self._grouper.finish())
        self._finished = True
        return out

    # -- helpers ---------------------------------------------------------------------
    def _close(self, groups: list[list[Measurement]]) -> list[Estimate]:
        return [est for est in map(self._epoch, groups) if est is not None]

    def _estimate(self, group: list[Measurement], x, P, nis=None, nis_dof=None, **extra) -> Estimate:
        return Estimate(t=max(m.t for m in group), x=np.array(x, dtype=float), P=np.array(P, dtype=float),
                        method=self.name, track=f"{EMITTER_PREFIX}1", nis=nis, nis_dof=nis_dof, extra=extra)

    def _epoch(self, group: list[Measurement]) -> Estimate | None:
        raise NotImplementedError


class Held(NamedTuple):
    """A bearing as the recursive methods take it: site, math bearing β (rad), the std
    the filters assume, time and station."""

    site: np.ndarray
    beta: float
    sigma: float
    t: float
    sensor: str


class _RecursiveMethod(DFMethod):
    """EKF, MEKF and IMM: ``ipu`` or robust initialisation, then one filter step per bearing.

    The filter's state is at ``self._t``, the latest time it has processed; a bearing is
    predicted to over ``dt = t − self._t``. The fix of a pair is stamped with the later
    bearing's time; with ``motion = "cv"`` a bearing older than the state (replayed
    after the initial pair) is left out, since the emitter has moved since
    (``replays_past``), with the static model it is processed.

    Until the first fix the bearings are held (:meth:`_hold`: the latest
    :data:`HELD_PER_STATION` of each station, none ``max_gap_s`` older than the newest),
    then replayed in arrival order. The filter starts afresh, holding again, at an epoch
    more than ``max_gap_s`` after its state, and after an epoch that leaves its
    covariance not positive definite (:mod:`fusion.guards`).
    """

    motions = EMITTER_MOTIONS

    def __init__(self, config: dict | None = None):
        super().__init__(config)
        self._model = self.config.model
        self.n_dropped = 0  # held bearings the start-up bound dropped
        self.n_restarts = 0  # filters started afresh (gap or covariance)
        self._reset()

    def _reset(self) -> None:
        """No filter: hold bearings again (and reopen the robust initialiser's window)."""
        self._filter = None
        self._t = -np.inf
        self._pending: list[Held] = []
        self._n = 0
        # robust initialisation: the window's bearings while it is open, else None
        self._window: list[Held] | None = [] if self.config.init == "robust" else None
        self._window_epochs = 0

    def _restart(self) -> None:
        self.n_restarts += 1
        self._reset()

    def _hold(self, held: list[Held], new: list[Held]) -> list[Held]:
        """``held`` then ``new`` (arrival order), within the start-up bound: of each
        station its latest :data:`HELD_PER_STATION`, and none more than ``max_gap_s``
        before the newest. Counts what it drops in ``n_dropped``."""
        out = held + new
        newest = max(b.t for b in out)
        per_station: dict[str, int] = {}
        keep = [False] * len(out)
        for k in range(len(out) - 1, -1, -1):
            b = out[k]
            n = per_station.get(b.sensor, 0)
            if n < HELD_PER_STATION and not gap_too_long(newest - b.t, self.config.max_gap_s):
                per_station[b.sensor] = n + 1
                keep[k] = True
        kept = [b for b, k in zip(out, keep) if k]
        self.n_dropped += len(out) - len(kept)
        return kept

    def _ipu(self, a, b, sa: float, sb: float, check: bool = True):
        """``ipu`` of bearings ``a``, ``b`` (site, β, σ); with ``check``, refuse (GeometryError)
        a fix whose 1σ semi-major axis exceeds ``ipu_max_rel`` × its range from the nearer
        site: such an intersection says nothing about range, and an EKF linearised there
        is meaningless."""
        p, P = ipu(a[0], a[1], sa, b[0], b[1], sb)
        k = self.config.ipu_max_rel
        if check and k > 0:
            r = min(np.linalg.norm(p - a[0]), np.linalg.norm(p - b[0]))
            if np.sqrt(np.linalg.eigvalsh(P)[-1]) > k * r:
                raise GeometryError(f"ipu: ill-conditioned fix (1σ axis > {k} × range {r:.0f} m)")
        return p, (np.diag(np.diag(P)) if self.config.ipu_cov == "diagonal" else P)

    def _build(self, a, b):
        raise NotImplementedError

    def _initial(self, p, P):
        """The filter's initial state from a position fix (:meth:`EmitterModel.initial`)."""
        return self._model.initial(p, P, self.config.init_vel_std)

    def _start(self, a: Held, b: Held) -> None:
        """The filter from the pair ``a``, ``b`` (GeometryError if it is not usable)."""
        self._filter = self._build(a, b)
        self._t = max(a.t, b.t)

    def _step(self, site, beta, sigma, dt) -> float | None:
        """One bearing through the filter, ``dt`` after its state; returns its NIS (None
        if not defined)."""
        return self._filter.step(site, beta, sigma, dt).nis

    def _feed(self, bearing: Held) -> float | None:
        """One bearing after the start: predicted to and processed, or, older than the
        state of a moving emitter, left out. Returns its NIS."""
        if bearing.t < self._t and not self._model.replays_past:
            return None
        dt = max(bearing.t - self._t, 0.0)
        self._t = max(self._t, bearing.t)
        self._n += 1
        return self._step(bearing.site, bearing.beta, bearing.sigma, dt)

    def _ingest(self, bearing: Held) -> list[float | None]:
        if self._filter is not None:
            return [self._feed(bearing)]
        held = self._hold(self._pending, [bearing])
        self._pending = held
        if not held or held[-1] is not bearing:  # (only with max_gap_s below pair_tol)
            return []
        for i, a in enumerate(held[:-1]):
            if np.linalg.norm(a.site - bearing.site) <= SAME_SITE:
                continue
            try:
                self._start(a, bearing)
            except GeometryError:
                continue
            self._n = 2
            rest = held[:i] + held[i + 1:-1]
            self._pending = []
            return [r for b in rest for r in self._ingest(b)]
        return []

    def _robust(self, bearings: list[Held]) -> list[float | None]:
        """Robust initialisation (:mod:`fusion.df.init`) over the window so far plus
        ``bearings`` (within the start-up bound, :meth:`_hold`): rebuild the filter from
        the best usable pair and replay the others in arrival order; the choice is final
        at the close of the ``init_epochs``-th epoch, or at the first epoch after it that
        gives a usable pair. Returns the NIS of the replayed bearings of this epoch."""
        new = {id(b) for b in bearings}
        self._window = w = self._hold(self._window, bearings)
        start = next((k for k, b in enumerate(w) if id(b) in new), len(w))
        self._window_epochs += 1
        c = self.config
        sites = np.array([b.site for b in w])
        betas = np.array([b.beta for b in w])
        sigmas = np.array([b.sigma for b in w])
        if self._window_epochs > c.init_epochs:  # overdue: only the new bearings' pairs need checking
            if not len(usable_pairs(sites, betas, sigmas, c.ipu_max_rel, new_from=start)[0]):
                return []
        self._filter = None
        for choice in ranked_pairs(sites, betas, sigmas, c.imm_p, c.imm_sigma2, c.ipu_max_rel):
            try:  # the method's own ipu (covariance rule, conditioning test)
                self._start(w[choice.i], w[choice.j])
            except GeometryError:
                continue
            break
        if self._filter is None:
            return []
        self._n = 2
        nis = []
        for k, b in enumerate(w):
            if k in (choice.i, choice.j):
                continue
            v = self._feed(b)
            if k >= start:
                nis.append(v)
        if self._window_epochs >= c.init_epochs:
            self._window = None
        return nis

    def _run(self, bearings: list[Held]) -> list[float | None]:
        """One epoch's bearings through the start-up or the filter; their NIS."""
        if self._window is not None:
            return self._robust(bearings)
        return [v for b in bearings for v in self._ingest(b)]

    def _epoch(self, group):
        bearings = [Held(*bearing_of(m), self.config.sigma_of(m), m.t, m.sensor) for m in group]
        if self._filter is not None and gap_too_long(max(b.t for b in bearings) - self._t, self.config.max_gap_s):
            self._restart()
        nis = self._run(bearings)
        if self._filter is not None and not positive_definite(self._filter.P):
            self._restart()  # this epoch again, from nothing
            nis = self._run(bearings)
            if self._filter is not None and not positive_definite(self._filter.P):
                self._restart()
        if self._filter is None:
            return None
        nis, dof = epoch_nis((v, 1) for v in nis if v is not None)
        return self._estimate(group, self._filter.x, self._filter.P, nis=nis, nis_dof=dof,
                              n_bearings=self._n, n_dropped=self.n_dropped, **self._extra())

    def _extra(self) -> dict:
        return {}


class EKFMethod(_RecursiveMethod):
    """EKF (= EKFT): the proper bearing EKF of the theses."""

    name = "EKF"

    def _build(self, a, b):
        x, P = self._initial(*self._ipu(a, b, a[2], b[2]))
        return BearingEKF(x, P, self._model, "EKFT")


class MEKFMethod(_RecursiveMethod):
    """MEKF#k: two cross-fed bearing filters (:data:`fusion.df.filters.MEKF_VARIANTS`)."""

    def __init__(self, variant: int, config: dict | None = None):
        if variant not in MEKF_VARIANTS:
            raise ValueError(f"unknown MEKF variant {variant!r}")
        self.variant = variant
        self.name = f"MEKF{variant}"
        super().__init__(config)

    def _build(self, a, b):
        x, P = self._initial(*self._ipu(a, b, a[2], b[2]))
        return MEKF(self.variant, x, P, self._model, self.config.mekf_handoff)

    def _extra(self):
        return {"fallbacks": self._filter.n_fallbacks}


class IMMMethod(_RecursiveMethod):
    """IMM of a clean-noise and an outlier-noise EKFT (:mod:`fusion.df.imm`)."""

    name = "IMM"

    def _build(self, a, b):
        c = self.config
        self._ipu(a, b, a[2], b[2])  # conditioning judged on the clean model, as for the EKF
        mix = [np.sqrt((1.0 - c.imm_mu0) * s ** 2 + c.imm_mu0 * c.imm_sigma2 ** 2) for s in (a[2], b[2])]
        x, P = self._initial(*self._ipu(a, b, mix[0], mix[1], check=False))
        return BearingIMM([x, x], [P, P], self._model, transition_matrix(c.imm_p, c.imm_transition),
                          [1.0 - c.imm_mu0, c.imm_mu0])

    def _step(self, site, beta, sigma, dt):
        self._filter.step(site, beta, (sigma, self.config.imm_sigma2), dt)
        return None

    def _extra(self):
        return {"mode_probs": self._filter.mu.tolist()}


class TorrieriMethod(DFMethod):
    """TORRIERI: at every epoch, Torrieri's weighted LS on all bearings so far (the latest
    ``torrieri_bearings`` of them: a batch method over a stream without end needs a bound).

    Reference point: the previous epoch's fix (the pairwise-intersection average at the
    first fix). With ``torrieri_iterations = 1`` this is Torrieri's one-step estimator
    about that reference; with 0, the converged (ML) fix. ``gate > 0`` applies
    leave-one-out rejection to the whole batch at every epoch.
    """

    name = "TORRIERI"

    def __init__(self, config: dict | None = None):
        super().__init__(config)
        keep = int(self.config.torrieri_bearings)
        self._sites: deque[np.ndarray] = deque(maxlen=keep)
        self._betas: deque[float] = deque(maxlen=keep)
        self._sigmas: deque[float] = deque(maxlen=keep)
        self._x = None

    def _epoch(self, group):
        for m in group:
            site, beta = bearing_of(m)
            self._sites.append(site)
            self._betas.append(beta)
            self._sigmas.append(self.config.sigma_of(m))
        sites, betas, sigmas = np.array(self._sites), np.array(self._betas), np.array(self._sigmas)
        if len(betas) < 2:
            return None
        try:  # GeometryError: one site only, or no two bearings intersect yet
            x0 = self._x if self._x is not None else pairwise_intersection_mean(sites, betas)
            fix = leave_one_out(sites, betas, sigmas, self.config.gate, x0=x0,
                                iterations=int(self.config.torrieri_iterations))
        except GeometryError:
            return None
        self._x = fix.x
        return self._estimate(group, fix.x, fix.P, n_bearings=len(betas), n_used=int(fix.used.sum()),
                              chi2=fix.chi2, iterations=fix.iterations, converged=fix.converged)


def make_station_smoother(config: DFConfig | dict | None = None, cross_fed: bool = False) -> BearingSmoother:
    """The per-station bearing smoother of KF+TR (``cross_fed=False``) or MKF+TR, set up
    from a ``[tracker]`` table: what a station's local tracker runs in the distributed
    topology (``sigma``, ``smoother_q``, ``mekf_handoff``)."""
    c = config if isinstance(config, DFConfig) else DFConfig.from_dict(config)
    sigma = None if c.sigma == "sensor" else float(c.sigma)
    if cross_fed:
        return CrossFedBearingSmoother(c.smoother_q, sigma, c.mekf_handoff)
    return BearingSmoother(c.smoother_q, sigma)


def centre_fix(latest: Mapping[str, Measurement], config: DFConfig | dict | None = None, x_prev=None) -> Fix | None:
    """The KF+TR / MKF+TR centre: Torrieri (``torrieri_iterations``, leave-one-out
    ``gate``) on the latest smoothed bearing of every station, taken in sensor-id order
    and weighted by their stated (smoothed) std, warm-started at the previous fix
    ``x_prev``. None while fewer than two stations have reported or the bearings do not
    cross."""
    c = config if isinstance(config, DFConfig) else DFConfig.from_dict(config)
    if len(latest) < 2:
        return None
    try:
        return fix_from_bearings([latest[k] for k in sorted(latest)], sigma=None, gate=c.gate, x0=x_prev,
                                 iterations=int(c.torrieri_iterations))
    except GeometryError:
        return None


class SmootherTorrieriMethod(DFMethod):
    """KF+TR / MKF+TR: per-station bearing smoothers (:func:`make_station_smoother`),
    Torrieri at the centre (:func:`centre_fix`) — the two halves the distributed
    topology runs in separate processes, composed in one. With ``smoothed_upstream``
    the bearings arrive already smoothed (the distributed centre) and are used as they
    are."""

    def __init__(self, cross_fed: bool, config: dict | None = None, smoothed_upstream: bool = False):
        self.name = "MKF+TR" if cross_fed else "KF+TR"
        self.cross_fed = cross_fed
        self.smoothed_upstream = smoothed_upstream
        super().__init__(config)
        self._smoothers: dict[str, BearingSmoother] = {}
        self._latest: dict[str, Measurement] = {}
        self._x = None

    def _epoch(self, group):
        for m in group:
            if self.smoothed_upstream:
                self._latest[m.sensor] = m
                continue
            if m.sensor not in self._smoothers:
                self._smoothers[m.sensor] = make_station_smoother(self.config, self.cross_fed)
            self._latest[m.sensor] = self._smoothers[m.sensor].update(m)
        fix = centre_fix(self._latest, self.config, self._x)
        if fix is None:
            return None
        self._x = fix.x
        return self._estimate(group, fix.x, fix.P, n_stations=len(self._latest), n_used=int(fix.used.sum()),
                              chi2=fix.chi2, iterations=fix.iterations, converged=fix.converged)


DF_METHODS: dict[str, Callable[[dict], DFMethod]] = {
    "EKF": EKFMethod,
    **{f"MEKF{k}": (lambda config, k=k: MEKFMethod(k, config)) for k in sorted(MEKF_VARIANTS)},
    "IMM": IMMMethod,
    "TORRIERI": TorrieriMethod,
    "KF+TR": lambda config: SmootherTorrieriMethod(False, config),
    "MKF+TR": lambda config: SmootherTorrieriMethod(True, config),
}


def make(name: str, config: dict | None = None) -> DFMethod:
    """Build DF method ``name`` from a ``[tracker]`` table."""
    if name not in DF_METHODS:
        raise ValueError(f"unknown DF method {name!r}; expected one of {sorted(DF_METHODS)}")
    return DF_METHODS[name](config or {})
