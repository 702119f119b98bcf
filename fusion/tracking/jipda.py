r"""JIPDA: joint integrated probabilistic data association (Mušicki and Evans), the
associator of dense clutter, and the existence logic of its tracks.

Tracks ``i`` predicted to ``(xᵢ, Pᵢ)`` with existence ``rᵢ``; plots ``zⱼ`` of one sensor
(model ``h``, Jacobian ``Hᵢ`` at ``xᵢ``, noise ``R``); ``νᵢⱼ = zⱼ − h(xᵢ)`` (angles
wrapped), ``Sᵢ = HᵢPᵢHᵢᵀ + R``, gate ``νᵀS⁻¹ν ≤ G = χ²⁻¹(P_G; n_z)``; clutter density ρ.
A joint event ``ε`` gives each track at most one gated plot and each plot at most one
track (the rest are clutter). With ``Nᵢⱼ = N(νᵢⱼ; 0, Sᵢ)``::

    P(ε) ∝ ∏_{i missed} (1 − P_D P_G rᵢ) · ∏_{i ← j} P_D rᵢ Nᵢⱼ / ρ

Marginals ``βᵢⱼ = Σ_{ε ∋ (i←j)} P(ε)``, ``βᵢ₀ = 1 − Σⱼ βᵢⱼ``; with every ``rᵢ = 1`` this
is JPDA. The sum runs per *cluster* (tracks joined by shared plots), exactly where it is
small (:data:`EXACT_EVENTS`), by loopy belief propagation where not; JPDA* (``jpda_star``)
keeps of the events that permute plots among the same tracks only the likeliest, so
tracks close together do not coalesce. Then per track::

    rᵢ⁺ = 1 − βᵢ₀ + βᵢ₀ aᵢ,    aᵢ = (1 − P_D P_G) rᵢ / (1 − P_D P_G rᵢ)
    c₀ = βᵢ₀ aᵢ / rᵢ⁺,  cⱼ = βᵢⱼ / rᵢ⁺            (association weights given existence)

and the PDA update with ``(cⱼ, c₀)`` (:mod:`fusion.pda`). Between frames ``r⁻ = p_S^Δt r``.
:class:`JIPDA` is the tracker's associator (its :class:`~fusion.tracking.associators.Weights`
carry ``r⁺``), ρ estimated per sensor from its last scans (:class:`ClutterWindow`);
:class:`ExistenceLogic` confirms and deletes by existence; :func:`scan_update` is one
scan on its own. docs/algorithms.md, "JIPDA: association with track existence".
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field
from typing import Mapping, Sequence

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.special import gammaln

from .. import kalman
from ..angles import TWO_PI
from ..measurement.components import RANGE
from ..measurement.kinds import fixes
from .associators import Weights
from .hypotheses import Hypotheses, gate_threshold
from .table import CONFIRMED, DELETED, TENTATIVE

EXACT_EVENTS = 10_000  # a cluster is summed exactly when ∏ᵢ (1 + gᵢ) ≤ this (gᵢ: track i's gated plots)
LBP_TOL = 1e-12  # loopy belief propagation stops when no message moves by more than this
LBP_MAX_ITER = 1000
FULL_CIRCLE_TEST = 0.01  # an angle row's plots span the full circle unless their widest gap is this unlikely
CLUTTER_SCANS = 10  # a sensor's clutter density is estimated from its last this many scans
USED = 0.5  # a plot some track made with at least this probability starts no track at full existence


# Existence -------------------------------------------------------------------------------
@dataclass(frozen=True)
class ExistenceRule:
    """The existence side of JIPDA: survival, the existence of a new track, and the
    thresholds that confirm and delete a track (the ``[tracker]`` keys of the same names).

    Args:
        p_survive: probability that a target exists one second later (Markov chain one:
            ``r⁻ = p_survive^Δt · r``).
        existence_birth: existence probability of a track after its first frame.
        existence_confirm: a tentative track is confirmed once its existence reaches this.
        existence_delete: a track is deleted once its existence falls below this.
    """

    p_survive: float = 0.98
    existence_birth: float = 0.1
    existence_confirm: float = 0.9
    existence_delete: float = 0.01

    def __post_init__(self):
        if not 0.0 < self.p_survive <= 1.0:
            raise ValueError(f"p_survive must lie in (0, 1], got {self.p_survive}")
        if not 0.0 <= self.existence_delete < self.existence_birth < self.existence_confirm <= 1.0:
            raise ValueError(f"existence thresholds need 0 <= existence_delete < existence_birth < existence_confirm "
                             f"<= 1, got existence_delete={self.existence_delete}, existence_birth="
                             f"{self.existence_birth}, existence_confirm={self.existence_confirm}")

    def predict(self, r, dt: float):
        """Existence after ``dt`` seconds without a scan: ``p_survive^dt · r``."""
        if dt < 0.0:
            raise ValueError(f"cannot predict existence backwards (dt = {dt})")
        return r * self.p_survive ** dt


@dataclass
class ExistenceLogic:
    """One track's life by its existence probability (the track table's logic under
    JIPDA): born tentative at ``existence_birth``, confirmed once ``existence`` reaches
    ``existence_confirm``, deleted once it falls below ``existence_delete`` or once the
    position σ (√trace P_pos) exceeds ``max_pos_std``. The tracker moves ``existence``:
    :meth:`survive` at each frame, the associator's ``r⁺`` after each scan.

    Attributes:
        status: ``tentative``, ``confirmed`` or ``deleted``.
        existence: the probability that the track's target exists, at ``t``.
        t: the time of ``existence`` (None before the track's first frame).
    """

    rule: ExistenceRule
    max_pos_std: float = math.inf
    status: str = TENTATIVE
    existence: float = field(default=None)
    t: float | None = None

    def __post_init__(self):
        if self.existence is None:
            self.existence = self.rule.existence_birth

    def survive(self, t: float) -> None:
        """The start of a frame at ``t``: ``existence ← p_S^(t − t_prev) · existence``."""
        if self.t is not None:
            self.existence = float(self.rule.predict(self.existence, t - self.t))
        self.t = float(t)

    def record(self, hit: bool, P_pos: np.ndarray | None = None) -> str:
        """The end of a frame: the status the existence now gives (``hit`` plays no part);
        returns it."""
        if self.status == DELETED:
            raise ValueError("a deleted track records no more frames")
        if self.existence < self.rule.existence_delete or (
                P_pos is not None and math.sqrt(float(np.trace(P_pos))) > self.max_pos_std):
            self.status = DELETED
        elif self.status == TENTATIVE and self.existence >= self.rule.existence_confirm:
            self.status = CONFIRMED
        return self.status


def existence_update(r, beta0, p_detect: float, gate_prob: float, assigned=None):
    """``(r⁺, c₀)``: existence after a scan whose joint association left the track
    unassigned with probability ``beta0``, and the weight of "missed" among the
    association hypotheses given that the target exists (module docstring).

    ``assigned``: ``Σⱼ βᵢⱼ`` as summed (else ``1 − beta0``). ``r⁺ = Σⱼ βᵢⱼ + β₀ a`` from
    it keeps its relative precision where ``β₀`` is within rounding of 1 (an unlikely
    track), so that ``cⱼ = βᵢⱼ/r⁺`` and ``c₀`` still sum to 1."""
    r = np.asarray(r, dtype=float)
    beta0 = np.asarray(beta0, dtype=float)
    assigned = 1.0 - beta0 if assigned is None else np.asarray(assigned, dtype=float)
    pdg = p_detect * gate_prob
    a = (1.0 - pdg) * r / (1.0 - pdg * r)  # P(exists | unassigned)
    r_post = assigned + beta0 * a
    with np.errstate(invalid="ignore", divide="ignore"):
        c0 = np.where(r_post > 0.0, beta0 * a / r_post, 1.0)
    return r_post, c0


def ipda_existence(r: float, likelihood_ratios: Sequence[float], p_detect: float, gate_prob: float) -> float:
    """The one-track closed form (IPDA): ``r⁺ = (1 − δ) r / (1 − δ r)`` with
    ``δ = P_D P_G − P_D Σⱼ Nⱼ/ρ`` over the gated plots' ``Nⱼ/ρ``."""
    delta = p_detect * gate_prob - p_detect * float(np.sum(likelihood_ratios))
    return (1.0 - delta) * r / (1.0 - delta * r)


# Hypotheses of one scan ------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class TrackHypotheses:
    """One track against one scan: the plots in its gate and what the update needs.

    Attributes:
        plots: indices of the gated plots (g,), in scan order.
        nu: their innovations (g, n_z), angles wrapped.
        log_lik: ``log N(ν; 0, S)`` of each (g,).
        H: the Jacobian at the prediction (n_z, n_x), or None if the geometry is undefined.
        gate_volume: volume of the gate ellipsoid ``{ν: νᵀS⁻¹ν ≤ G}`` in measurement space.
    """

    plots: np.ndarray
    nu: np.ndarray
    log_lik: np.ndarray
    H: np.ndarray | None
    gate_volume: float


def hypothesise(model, x: np.ndarray, P: np.ndarray, Z: np.ndarray, gate_prob: float) -> TrackHypotheses:
    """The gated plots of one scan ``Z (m, n_z)`` for a track predicted to ``(x, P)``.

    ``model`` is a :class:`fusion.measurement.models.MeasurementModel` (``h``,
    ``jacobian``, ``R``, ``residual`` with the angle rows wrapped). A track where the
    geometry is undefined (over a sensor's site) gates nothing."""
    Z = np.asarray(Z, dtype=float).reshape(-1, model.n_z)
    empty = TrackHypotheses(np.zeros(0, int), np.zeros((0, model.n_z)), np.zeros(0), None, 0.0)
    try:
        z_pred = model.h(x)
        H = model.jacobian(x)
    except ValueError:
        return empty
    nu = model.residual(Z, z_pred)
    S = kalman.symmetrise(H @ P @ H.T + model.R)
    L_inv = kalman.inverse_cholesky_factor(S)
    d2 = np.sum((nu @ L_inv.T) ** 2, axis=1)
    gate = gate_threshold(model.n_z, gate_prob)
    inside = np.flatnonzero(d2 <= gate)
    n = model.n_z
    log_norm = float(np.sum(np.log(np.diag(L_inv)))) - 0.5 * n * math.log(TWO_PI)  # log det(2πS)^(−½)
    return TrackHypotheses(inside, nu[inside], log_norm - 0.5 * d2[inside], H, float(gate_volume(n, gate, log_norm)))


def gate_volume(n_z: int, gate, log_norm):
    """Volume of the gate ``{ν: νᵀS⁻¹ν ≤ G}`` in measurement space from ``G`` and
    ``log_norm = log det(2πS)^(−½)``: ``π^(n/2) / Γ(n/2 + 1) · G^(n/2) · √det S``."""
    n = n_z
    log_root_det = -np.asarray(log_norm, dtype=float) - 0.5 * n * math.log(TWO_PI)  # ½ log det S
    return np.exp(0.5 * n * math.log(math.pi) - gammaln(0.5 * n + 1.0) + 0.5 * n * np.log(gate) + log_root_det)


# Clutter density -----------------------------------------------------------------------
def clutter_density(Z: np.ndarray, angles: np.ndarray, expected_targets: float, min_volume: float = 0.0,
                    scans: int = 1) -> float:
    """The clutter density of a sensor, estimated from the plots of its last ``scans``
    scans: ``ρ̂ = max(m − n̂, 1) / (scans · V̂)``.

    ``m`` plots, ``n̂`` of them expected from targets (``Σ P_D P_G rᵢ`` per scan); ``V̂`` the box the
    plots span in measurement space, each side scaled by ``(m + 1)/(m − 1)`` — the unbiased
    length of a uniform interval from its sample range; an angle row spans the full circle
    unless its plots leave a gap that m plots all round leave with probability below
    :data:`FULL_CIRCLE_TEST` (``P(gap > g) ≈ m (1 − g/2π)^(m−1)``), else the shortest arc
    holding them; ``V̂`` is ``min_volume`` (the largest gate) where the plots span no box
    (one plot). docs/algorithms.md, "JIPDA: association with track existence".
    """
    Z = np.atleast_2d(np.asarray(Z, dtype=float))
    m = len(Z)
    volume = 0.0
    if m >= 2:
        volume = 1.0
        for k in range(Z.shape[1]):
            col = Z[:, k]
            if angles[k]:
                a = np.sort(np.mod(col, TWO_PI))
                gap = float(np.max(np.diff(np.append(a, a[0] + TWO_PI))))
                # m plots all round leave a gap this wide with probability FULL_CIRCLE_TEST
                full = gap <= TWO_PI * (1.0 - (FULL_CIRCLE_TEST / m) ** (1.0 / (m - 1)))
                side = TWO_PI if full else min((TWO_PI - gap) * (m + 1) / (m - 1), TWO_PI)
            else:
                side = float(np.ptp(col)) * (m + 1) / (m - 1)
            volume *= side
    if not volume > 0.0:
        volume = float(min_volume)
    if not volume > 0.0:
        raise ValueError("clutter density: the plots span no volume and no gate volume was given")
    return max(m - float(expected_targets), 1.0) / (int(scans) * volume)


class ClutterWindow:
    """The clutter density of one sensor from its last ``scans`` scans
    (:func:`clutter_density` over their plots together): a few clutter plots a scan span
    little of the cover, the plots of several span it (docs/algorithms.md, "JIPDA:
    association with track existence")."""

    def __init__(self, scans: int = 10):
        if scans < 1:
            raise ValueError(f"a clutter window needs at least one scan, got {scans}")
        self._scans: deque[tuple[np.ndarray, float]] = deque(maxlen=int(scans))

    def add(self, Z: np.ndarray, expected_targets: float) -> None:
        """Add a scan's plots (and the target plots expected in it)."""
        self._scans.append((np.atleast_2d(np.asarray(Z, dtype=float)), float(expected_targets)))

    def update(self, Z: np.ndarray, angles: np.ndarray, expected_targets: float, min_volume: float = 0.0) -> float:
        """Add a scan's plots (and the target plots expected in it); the density now."""
        self.add(Z, expected_targets)
        plots = np.concatenate([z for z, _ in self._scans])
        expected = sum(e for _, e in self._scans)
        return clutter_density(plots, angles, expected, min_volume, len(self._scans))


# Clusters and joint association probabilities ---------------------------------------------
def clusters(gated: Sequence[np.ndarray], n_plots: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """``(tracks, plots)`` of each cluster: the connected components of the graph whose
    edges join each track to its gated plots (``gated[i]``: plot indices of track i).
    Tracks with no gated plot and plots no track gates are in none. Ordered by their
    first track."""
    n = len(gated)
    rows = np.concatenate([np.full(len(g), i) for i, g in enumerate(gated)] + [np.zeros(0, int)]).astype(int)
    cols = np.concatenate(list(gated) + [np.zeros(0, int)]).astype(int)
    if rows.size == 0:
        return []
    graph = coo_matrix((np.ones(rows.size), (rows, n + cols)), shape=(n + n_plots, n + n_plots))
    _, label = connected_components(graph, directed=False)
    out = []
    for lab in dict.fromkeys(label[rows].tolist()):  # in order of first track
        members = np.flatnonzero(label == lab)
        out.append((members[members < n], members[members >= n] - n))
    return out


def n_events_bound(W: np.ndarray) -> float:
    """``∏ᵢ (1 + gᵢ)``: an upper bound on a cluster's joint events (``gᵢ`` the plots with
    ``Wᵢⱼ > 0``)."""
    return float(np.prod(1.0 + np.count_nonzero(W > 0.0, axis=1).astype(float)))


def _rows_scaled(w0: np.ndarray, W: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(w0, W)`` as floats, each track's row divided by its largest weight: every joint
    event holds each row once, so the scale cancels in the marginals and moves no argmax,
    and it keeps the products in range."""
    w0 = np.asarray(w0, dtype=float)
    W = np.asarray(W, dtype=float)
    scale = np.maximum(w0, W.max(axis=1, initial=0.0))
    return w0 / scale, W / scale[:, None]


def exact_marginals(w0: np.ndarray, W: np.ndarray) -> np.ndarray:
    """Marginal association probabilities of a cluster by summing every joint event.

    ``w0 (n,)`` the tracks' miss weights, ``W (n, m)`` their plot weights (0: not gated);
    a joint event's weight is the product of its tracks' weights (module docstring).
    Returns ``β (n, m + 1)``: column 0 the miss, column ``1 + j`` plot j; rows sum to 1.

    The sum is a dynamic programme over the tracks whose state is the set of plots
    taken so far (events that reach the same set merge), once per track with that
    track left out: ``βᵢⱼ ∝ Wᵢⱼ · T₋ᵢ(j free)``, ``βᵢ₀ ∝ w0ᵢ · T₋ᵢ``.
    """
    n, m = np.shape(W)
    if m > 62:
        raise ValueError(f"exact marginals take at most 62 plots a cluster, got {m}")
    w0, W = _rows_scaled(w0, W)
    options = [[(1 << j, float(W[i, j])) for j in np.flatnonzero(W[i] > 0.0)] for i in range(n)]
    beta = np.zeros((n, m + 1))
    for i in range(n):
        states = {0: 1.0}
        for k in range(n):
            if k == i:
                continue
            nxt: dict[int, float] = {}
            miss = float(w0[k])
            for used, weight in states.items():
                nxt[used] = nxt.get(used, 0.0) + weight * miss
                for bit, w in options[k]:
                    if not used & bit:
                        nxt[used | bit] = nxt.get(used | bit, 0.0) + weight * w
            states = nxt
        used = np.fromiter(states.keys(), dtype=np.int64, count=len(states))
        total = np.fromiter(states.values(), dtype=float, count=len(states))
        free = ((used[:, None] >> np.arange(m)) & 1) == 0  # (states, m): plot j not taken
        beta[i, 0] = w0[i] * total.sum()
        beta[i, 1:] = W[i] * (total @ free)
        beta[i] /= beta[i].sum()
    return beta


def best_permutation_marginals(w0: np.ndarray, W: np.ndarray) -> np.ndarray:
    """Marginals of JPDA* (Blom and Bloem, 2000): of the joint events that detect the same
    tracks with the same plots — permutations of one another — only the likeliest is
    kept; same arguments and result as :func:`exact_marginals`.

    Two tracks close together share their plots; JPDA weights both pairings of their two
    plots, so each track is pulled toward the other's plot and the pair coalesces.
    JPDA* keeps one pairing of the pair, the likelier: the tracks stay apart. A track
    alone in its cluster has no permutation: its marginals are JPDA's.

    The maxima are a dynamic programme over the tracks whose state is (tracks detected,
    plots taken) so far: a class's likeliest event extends the likeliest prefix of each
    state, so merging events that reach one state by keeping the heavier is exact.
    """
    w0, W = _rows_scaled(w0, W)
    n, m = W.shape
    options = [[(j, 1 << j, float(W[i, j])) for j in np.flatnonzero(W[i] > 0.0)] for i in range(n)]
    states: dict[tuple[int, int], tuple[float, tuple[int, ...]]] = {(0, 0): (1.0, ())}
    for k in range(n):
        nxt: dict[tuple[int, int], tuple[float, tuple[int, ...]]] = {}
        miss = float(w0[k])
        for (det, used), (weight, event) in states.items():
            for key, w, j in [((det, used), weight * miss, -1)] + [
                    ((det | 1 << k, used | bit), weight * wj, j) for j, bit, wj in options[k] if not used & bit]:
                if w > nxt.get(key, (-1.0, ()))[0]:
                    nxt[key] = (w, event + (j,))
        states = nxt
    beta = np.zeros((n, m + 1))
    rows = np.arange(n)
    for weight, event in states.values():
        beta[rows, 1 + np.asarray(event)] += weight  # plot -1 (missed) lands in column 0
    return beta / beta.sum(axis=1, keepdims=True)


def lbp_marginals(w0: np.ndarray, W: np.ndarray, tol: float = LBP_TOL, max_iter: int = LBP_MAX_ITER) -> np.ndarray:
    """Marginal association probabilities by loopy belief propagation (Williams and Lau,
    2014), the approximation for clusters too large to sum; same arguments and result as
    :func:`exact_marginals`.

    Messages between tracks and plots, from ``ν = 1``::

        μᵢⱼ = Wᵢⱼ / (w0ᵢ + Σ_{j'≠j} Wᵢⱼ' νᵢⱼ')      (track → plot)
        νᵢⱼ = 1 / (1 + Σ_{i'≠i} μᵢ'ⱼ)               (plot → track)

    until no ``ν`` moves by more than ``tol``; then ``βᵢⱼ ∝ Wᵢⱼ νᵢⱼ``, ``βᵢ₀ ∝ w0ᵢ``. The
    iteration converges for this problem (Williams and Lau); its error against the
    exact sum is measured in docs/algorithms.md, "JIPDA: association with track existence".
    """
    w0, W = _rows_scaled(w0, W)
    nu = np.ones_like(W)
    for _ in range(int(max_iter)):
        wn = W * nu
        mu = W / (w0[:, None] + wn.sum(axis=1, keepdims=True) - wn)
        new = 1.0 / (1.0 + mu.sum(axis=0, keepdims=True) - mu)
        moved = float(np.max(np.abs(new - nu), initial=0.0))
        nu = new
        if moved <= tol:
            break
    beta = np.concatenate([w0[:, None], W * nu], axis=1)
    return beta / beta.sum(axis=1, keepdims=True)


def marginals(w0: np.ndarray, W: np.ndarray, exact_events: float = EXACT_EVENTS,
              jpda_star: bool = False) -> tuple[np.ndarray, bool]:
    """``(β, exact)``: :func:`exact_marginals` (:func:`best_permutation_marginals` with
    ``jpda_star``) if the cluster has at most ``exact_events`` joint events by
    :func:`n_events_bound`, else :func:`lbp_marginals`."""
    if n_events_bound(W) <= exact_events and np.shape(W)[1] <= 62:
        return (best_permutation_marginals if jpda_star else exact_marginals)(w0, W), True
    return lbp_marginals(w0, W), False


def joint_association(gated: Sequence[np.ndarray], ratios: Sequence[np.ndarray], r: np.ndarray, n_plots: int,
                      p_detect: float, gate_prob: float,
                      exact_events: float = EXACT_EVENTS, jpda_star: bool = False) -> tuple[np.ndarray, list[bool]]:
    """``(β, exact)``: the joint association probabilities of one scan (module docstring)
    and, per cluster, whether they were summed exactly (``jpda_star``: :func:`marginals`).

    ``gated[i]``: the plots in track i's gate (indices among ``n_plots``); ``ratios[i]``:
    their ``Nᵢⱼ/ρ``; ``r``: the tracks' existence. ``β (n, n_plots + 1)``: column 0
    "missed or does not exist", column ``1 + j`` plot j; rows sum to 1."""
    r = np.asarray(r, dtype=float)
    n = len(gated)
    w0 = 1.0 - p_detect * gate_prob * r
    beta = np.zeros((n, n_plots + 1))
    beta[:, 0] = 1.0
    exact = []
    for tracks, plots in clusters(gated, n_plots):
        col = np.full(n_plots, -1)
        col[plots] = np.arange(len(plots))
        Wc = np.zeros((len(tracks), len(plots)))
        for a, i in enumerate(tracks):
            Wc[a, col[gated[i]]] = np.asarray(ratios[i]) * (p_detect * r[i])  # P_D rᵢ Nᵢⱼ / ρ
        bc, is_exact = marginals(w0[tracks], Wc, exact_events, jpda_star)
        beta[tracks, 0] = bc[:, 0]
        beta[np.ix_(tracks, plots + 1)] = bc[:, 1:]
        exact.append(is_exact)
    return beta, exact


# The PDA update ------------------------------------------------------------------------
def pda_update(x: np.ndarray, P: np.ndarray, H: np.ndarray, R: np.ndarray, nu: np.ndarray, c0: float,
               c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(x⁺, P⁺)`` of the PDA update: innovations ``nu (g, n_z)`` with weights ``c (g,)``
    and the miss weight ``c0`` (``c0 + Σc = 1``), the EKF gain and Joseph-form ``Pᶜ`` at
    the prediction (module docstring)."""
    c = np.asarray(c, dtype=float)
    nu = np.asarray(nu, dtype=float).reshape(len(c), -1)
    nu_bar = c @ nu
    res = kalman.update(x, P, nu_bar, H, R)  # x + K ν̄, and Pᶜ
    spread = (nu * c[:, None]).T @ nu - np.outer(nu_bar, nu_bar)
    P_new = c0 * P + (1.0 - c0) * res.P + res.K @ spread @ res.K.T
    return res.x, kalman.symmetrise(P_new)


# One scan --------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class ScanUpdate:
    """What one scan did to the tracks (:func:`scan_update`).

    Attributes:
        x, P: the updated states, one per track.
        r: existence after the scan (n,).
        beta: joint association probabilities (n, m + 1): column 0 "missed or does not
            exist", column ``1 + j`` plot j; rows sum to 1.
        density: the clutter density used.
        exact: per cluster, whether its probabilities were summed exactly.
    """

    x: list[np.ndarray]
    P: list[np.ndarray]
    r: np.ndarray
    beta: np.ndarray
    density: float
    exact: list[bool]

    @property
    def plot_use(self) -> np.ndarray:
        """``Σᵢ βᵢⱼ`` per plot: the probability that some track made it (m,)."""
        return self.beta[:, 1:].sum(axis=0)


def scan_update(model, states: Sequence[tuple[np.ndarray, np.ndarray]], r: Sequence[float], Z: np.ndarray,
                p_detect: float, gate_prob: float, density: float | None = None,
                exact_events: float = EXACT_EVENTS, jpda_star: bool = False) -> ScanUpdate:
    """JIPDA update of every track with one sensor scan (module docstring).

    Args:
        model: the sensor's :class:`fusion.measurement.models.MeasurementModel`.
        states: each track's predicted ``(x, P)`` at the scan time.
        r: each track's predicted existence probability.
        Z: the scan's plots (m, n_z).
        p_detect, gate_prob: the sensor's P_D and the gate's P_G.
        density: the clutter density ρ; None estimates it from the scan
            (:func:`clutter_density`).
        exact_events: the cluster size up to which probabilities are summed exactly.
        jpda_star: keep only the likeliest of permuted events (:func:`best_permutation_marginals`).
    """
    r = np.asarray(r, dtype=float)
    Z = np.asarray(Z, dtype=float).reshape(-1, model.n_z)
    n, m = len(states), len(Z)
    hyps = [hypothesise(model, x, P, Z, gate_prob) for x, P in states]
    if density is None:
        density = clutter_density(Z, model.angles, p_detect * gate_prob * float(r.sum()),
                                  max((h.gate_volume for h in hyps), default=0.0)) if m else 1.0
    if not density > 0.0:
        raise ValueError(f"clutter density must be > 0, got {density}")
    ratios = [np.exp(h.log_lik) / density for h in hyps]  # Nᵢⱼ / ρ
    beta, exact = joint_association([h.plots for h in hyps], ratios, r, m, p_detect, gate_prob, exact_events,
                                    jpda_star)
    r_post, c0 = existence_update(r, beta[:, 0], p_detect, gate_prob, beta[:, 1:].sum(axis=1))
    xs, Ps = [], []
    for i, (x, P) in enumerate(states):
        h = hyps[i]
        if h.plots.size == 0 or r_post[i] <= 0.0:
            xs.append(np.asarray(x, dtype=float))
            Ps.append(np.asarray(P, dtype=float))
            continue
        x_new, P_new = pda_update(x, P, h.H, model.R, h.nu, float(c0[i]), beta[i, 1 + h.plots] / r_post[i])
        xs.append(x_new)
        Ps.append(P_new)
    return ScanUpdate(xs, Ps, r_post, beta, float(density), exact)


# The associator ------------------------------------------------------------------------
class JIPDA:
    """JIPDA as the many-target tracker's associator (module docstring): one scan's
    :class:`~fusion.tracking.hypotheses.Hypotheses` (``d²``, ``log_norm``, the rows'
    ``existence``; a row without existence is certain: JPDA) in, :class:`Weights` out —
    ``beta``/``miss`` the weights given existence ``(cⱼ, c₀)`` that the PDA update
    takes, ``existence`` the rows' ``r⁺``, ``claimed`` the probability that some track
    made each plot (``Σᵢ βᵢⱼ``), ``used`` the plots claimed with at least :data:`USED`
    (what a consumer that starts tracks at full existence leaves alone: the local nodes of
    the distributed topologies; the many-target tracker weighs each birth by
    ``1 − claimed`` instead, :meth:`born`).

    Every scan is the recursion's step with *its* sensor's numbers: that sensor's
    ``P_D`` (:meth:`detection`) in the miss weight ``1 − P_D P_G rᵢ`` and in ``aᵢ``, and
    that sensor's clutter density in ``Nᵢⱼ/ρ``, estimated from its last ``clutter_scans``
    scans (:class:`ClutterWindow`), the expected target plots ``Σ P_D P_G rᵢ`` taken off;
    so the associator keeps a window per sensor and must see every scan once. Over a
    frame's scans the existence odds ``r/(1 − r)`` are multiplied by each scan's
    ``1 − δ`` in turn (a lone track: ``δ = P_D P_G − P_D Σⱼ Nⱼ/ρ`` of that scan).

    *Rays.* Once a scan has fixed range (:attr:`ranged`: a radar's, or a position
    report's), a scan that fixes none (an angle sensor's rays) leaves unmoved the
    existence of a track whose gated plots all lie in another track's gate too: ``r⁺ ← r``.
    Such a plot is as likely from the other track's target on the ray as from one at
    this track's range, so its evidence ``P_D Nⱼ/ρ`` (10²–10⁴ for a track tight in
    angle) is no evidence that this track's target exists — a track at a false range on
    a real aircraft's ray would live on that aircraft's plots — nor, when the joint
    events give it to the other track, evidence against (two aircraft in formation).
    A track with a plot in its gate that no other track gates, or with an empty gate,
    takes the recursion's ``r⁺`` as it is; the weights update every track as they are.
    A network of angle sensors alone has nothing else: there every scan counts in full.

    Args:
        p_detect: the detection probability ``P_D`` of every sensor not in ``p_detect_by_sensor``.
        gate_prob: the gate's ``P_G`` (the hypotheses' gates must be ``χ²⁻¹(P_G; n_z)``).
        clutter_scans: the scans of a sensor its clutter density is estimated from.
        exact_events: the cluster size up to which probabilities are summed exactly.
        p_detect_by_sensor: ``P_D`` of named sensors (sensor id → P_D).
        jpda_star: of the joint events that permute plots among tracks keep only the
            likeliest (:func:`best_permutation_marginals`): tracks close together do
            not coalesce.
    """

    def __init__(self, p_detect: float, gate_prob: float, clutter_scans: int = CLUTTER_SCANS,
                 exact_events: float = EXACT_EVENTS, p_detect_by_sensor: Mapping[str, float] | None = None,
                 jpda_star: bool = False):
        by_sensor = {str(k): float(v) for k, v in (p_detect_by_sensor or {}).items()}
        for name, pd in [("p_detect", p_detect), *((f"p_detect of {k!r}", v) for k, v in by_sensor.items())]:
            if not 0.0 < pd <= 1.0:
                raise ValueError(f"{name} must lie in (0, 1], got {pd}")
        self.p_detect, self.gate_prob = float(p_detect), float(gate_prob)
        self.p_detect_by_sensor = by_sensor
        self.clutter_scans, self.exact_events = int(clutter_scans), exact_events
        self.jpda_star = bool(jpda_star)
        self._clutter: dict[str, ClutterWindow] = {}
        self.density: dict[str, float] = {}  # the latest clutter density of each sensor
        self.ranged = False  # whether a scan has fixed range (then the rays rule applies)

    def counts_in_full(self, plot) -> bool:
        """Whether the scan of ``plot``'s sensor moves every track's existence in full (else
        *Rays*, above)."""
        return fixes(plot, RANGE) or not self.ranged

    def detection(self, sensor: str) -> float:
        """``P_D`` of ``sensor``: its own if named, else :attr:`p_detect`."""
        return self.p_detect_by_sensor.get(sensor, self.p_detect)

    def born(self, r: float, missed: Sequence[str], unclaimed: float = 1.0) -> float:
        """The existence of a track after its birth frame: ``r`` (``existence_birth``)
        times ``unclaimed``, the probability that no existing track made the plots it
        starts from (``∏ (1 − claimedⱼ)`` of :class:`Weights`: a new target exists only
        if its plots are its own), with the miss of each sensor of the frame that gave
        its group no plot, as the recursion charges it: odds × ``∏ (1 − P_D P_G)``."""
        r = r * unclaimed
        odds_factor = float(np.prod([1.0 - self.detection(s) * self.gate_prob for s in missed]))
        return r * odds_factor / (1.0 - r + r * odds_factor)

    def associate(self, hyp: Hypotheses) -> Weights:
        if hyp.log_norm is None or hyp.model is None:
            raise ValueError("JIPDA needs the plots' likelihoods: hypotheses of measurements with log_norm")
        n, m = hyp.d2.shape
        r = np.ones(n) if hyp.existence is None else np.asarray(hyp.existence, dtype=float)
        sensor = hyp.plots[0].sensor
        self.ranged = self.ranged or fixes(hyp.plots[0], RANGE)
        p_detect = self.detection(sensor)
        pdg = p_detect * self.gate_prob
        gated = [np.flatnonzero(g) for g in hyp.gated]
        volumes = gate_volume(hyp.model.n_z, hyp.gate, hyp.log_norm)
        window = self._clutter.setdefault(sensor, ClutterWindow(self.clutter_scans))
        Z = np.array([p.z for p in hyp.plots])
        if n == 0:  # no track: no density needed (one plot alone spans none), the scan still counts
            window.add(Z, 0.0)
            return Weights(np.zeros((0, m)), np.zeros(0), frozenset(), np.zeros(0), np.zeros(m))
        rho = window.update(Z, hyp.model.angles, pdg * float(r.sum()),
                            float(np.max(volumes[np.isfinite(volumes)], initial=0.0)))
        self.density[sensor] = rho
        ratios = [np.exp(hyp.log_norm[i] - 0.5 * hyp.d2[i, g]) / rho for i, g in enumerate(gated)]
        beta, _ = joint_association(gated, ratios, r, m, p_detect, self.gate_prob, self.exact_events,
                                    self.jpda_star)
        r_post, c0 = existence_update(r, beta[:, 0], p_detect, self.gate_prob, beta[:, 1:].sum(axis=1))
        alive = r_post > 0.0
        c = np.zeros((n, m))
        c[alive] = beta[alive, 1:] / r_post[alive, None]
        claimed = np.minimum(beta[:, 1:].sum(axis=0), 1.0)
        used = frozenset(int(j) for j in np.flatnonzero(claimed >= USED))
        if not self.counts_in_full(hyp.plots[0]):  # a ray scan (Rays)
            g = hyp.gated
            own = (g & (g.sum(axis=0) == 1)).any(axis=1)
            r_post = np.where(g.any(axis=1) & ~own, r, r_post)
        return Weights(c, np.where(alive, c0, 1.0), used, r_post, claimed)
