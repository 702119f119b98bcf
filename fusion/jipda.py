r"""JIPDA: joint integrated probabilistic data association of one sensor scan (Mušicki and
Evans), with the existence probability of each track.

Tracks ``i`` predicted to ``(xᵢ, Pᵢ)`` with existence ``rᵢ``; plots ``zⱼ`` of one sensor
(model ``h``, Jacobian ``Hᵢ`` at ``xᵢ``, noise ``R``); ``νᵢⱼ = zⱼ − h(xᵢ)`` (angles
wrapped), ``Sᵢ = HᵢPᵢHᵢᵀ + R``, gate ``νᵀS⁻¹ν ≤ G = χ²⁻¹(P_G; n_z)``; clutter density ρ.
A joint event ``ε`` gives each track at most one gated plot and each plot at most one
track (the rest are clutter). With ``Nᵢⱼ = N(νᵢⱼ; 0, Sᵢ)``::

    P(ε) ∝ ∏_{i missed} (1 − P_D P_G rᵢ) · ∏_{i ← j} P_D rᵢ Nᵢⱼ / ρ

(``1 − P_D P_G rᵢ``: the track does not exist, or exists and was not detected in the
gate). Marginals ``βᵢⱼ = Σ_{ε ∋ (i←j)} P(ε)``, ``βᵢ₀ = 1 − Σⱼ βᵢⱼ``; with every ``rᵢ = 1`` this
is JPDA. Tracks that share no gated plot are independent: the sum runs per *cluster*
(connected tracks and plots), exactly where the cluster is small (:data:`EXACT_EVENTS`),
by loopy belief propagation where it is not (:func:`lbp_marginals`). Then per track::

    rᵢ⁺ = 1 − βᵢ₀ + βᵢ₀ aᵢ,    aᵢ = (1 − P_D P_G) rᵢ / (1 − P_D P_G rᵢ)
    c₀ = βᵢ₀ aᵢ / rᵢ⁺,  cⱼ = βᵢⱼ / rᵢ⁺            (association weights given existence)
    ν̄ = Σ cⱼ νⱼ,  x⁺ = x + K ν̄,  P⁺ = c₀ P + (1 − c₀) Pᶜ + K (Σ cⱼ νⱼνⱼᵀ − ν̄ν̄ᵀ) Kᵀ

with ``K``, ``Pᶜ`` the EKF gain and updated covariance at the prediction (Joseph form).
Between scans ``r⁻ = p_S^Δt r`` (Markov chain one). One track alone gives the IPDA's
closed form ``r⁺ = (1 − δ) r / (1 − δ r)``, ``δ = P_D P_G − P_D Σⱼ Nⱼ/ρ``. ρ is estimated
from the sensor's recent plots (:class:`ClutterWindow`). The maths, choices and
measurements: docs/algorithms.md, "JIPDA: association with track existence".
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass
from typing import Sequence

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.special import gammaln

from . import kalman
from .angles import TWO_PI
from .tracking.hypotheses import gate_threshold

EXACT_EVENTS = 10_000  # a cluster is summed exactly when ∏ᵢ (1 + gᵢ) ≤ this (gᵢ: track i's gated plots)
LBP_TOL = 1e-12  # loopy belief propagation stops when no message moves by more than this
LBP_MAX_ITER = 1000
FULL_CIRCLE_TEST = 0.01  # an angle row's plots span the full circle unless their widest gap is this unlikely


# Existence -------------------------------------------------------------------------------
@dataclass(frozen=True)
class ExistenceRule:
    """The existence side of JIPDA: survival, the existence of a new track, and the
    thresholds that confirm and delete a track.

    Args:
        p_survive: probability that a target exists one second later (Markov chain one:
            ``r⁻ = p_survive^Δt · r``).
        birth: existence probability of a track at its first plots.
        confirm: a track is confirmed once its existence reaches this.
        delete: a track is deleted once its existence falls below this.
    """

    p_survive: float = 0.98
    birth: float = 0.1
    confirm: float = 0.9
    delete: float = 0.01

    def __post_init__(self):
        if not 0.0 < self.p_survive <= 1.0:
            raise ValueError(f"p_survive must lie in (0, 1], got {self.p_survive}")
        if not 0.0 <= self.delete < self.birth < self.confirm <= 1.0:
            raise ValueError(f"existence thresholds need 0 <= delete < birth < confirm <= 1, got "
                             f"delete={self.delete}, birth={self.birth}, confirm={self.confirm}")

    def predict(self, r, dt: float):
        """Existence after ``dt`` seconds without a scan: ``p_survive^dt · r``."""
        if dt < 0.0:
            raise ValueError(f"cannot predict existence backwards (dt = {dt})")
        return r * self.p_survive ** dt


def existence_update(r, beta0, p_detect: float, gate_prob: float):
    """``(r⁺, c₀)``: existence after a scan whose joint association left the track
    unassigned with probability ``beta0``, and the weight of "missed" among the
    association hypotheses given that the target exists (module docstring)."""
    r = np.asarray(r, dtype=float)
    beta0 = np.asarray(beta0, dtype=float)
    pdg = p_detect * gate_prob
    a = (1.0 - pdg) * r / (1.0 - pdg * r)  # P(exists | unassigned)
    r_post = 1.0 - beta0 + beta0 * a
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
    half_log_det = -float(np.sum(np.log(np.diag(L_inv))))  # ½ log det S
    volume = math.exp(0.5 * n * math.log(math.pi) - gammaln(0.5 * n + 1.0) + 0.5 * n * math.log(gate) + half_log_det)
    log_lik = -0.5 * (d2[inside] + n * math.log(TWO_PI)) - half_log_det
    return TrackHypotheses(inside, nu[inside], log_lik, H, volume)


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
    holding them; ``V̂`` at least ``min_volume`` (the largest gate: a scan of one plot
    spans no box). docs/algorithms.md, "JIPDA: association with track existence".
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
    volume = max(volume, float(min_volume))
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

    def update(self, Z: np.ndarray, angles: np.ndarray, expected_targets: float, min_volume: float = 0.0) -> float:
        """Add a scan's plots (and the target plots expected in it); the density now."""
        self._scans.append((np.atleast_2d(np.asarray(Z, dtype=float)), float(expected_targets)))
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


def exact_marginals(w0: np.ndarray, W: np.ndarray) -> np.ndarray:
    """Marginal association probabilities of a cluster by summing every joint event.

    ``w0 (n,)`` the tracks' miss weights, ``W (n, m)`` their plot weights (0: not gated);
    a joint event's weight is the product of its tracks' weights (module docstring).
    Returns ``β (n, m + 1)``: column 0 the miss, column ``1 + j`` plot j; rows sum to 1.

    The sum is a dynamic programme over the tracks whose state is the set of plots
    taken so far (events that reach the same set merge), once per track with that
    track left out: ``βᵢⱼ ∝ Wᵢⱼ · T₋ᵢ(j free)``, ``βᵢ₀ ∝ w0ᵢ · T₋ᵢ``.
    """
    w0 = np.asarray(w0, dtype=float)
    W = np.asarray(W, dtype=float)
    n, m = W.shape
    if m > 62:
        raise ValueError(f"exact marginals take at most 62 plots a cluster, got {m}")
    scale = np.maximum(w0, W.max(axis=1, initial=0.0))  # a row's scale cancels: keeps products in range
    w0, W = w0 / scale, W / scale[:, None]
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
    w0 = np.asarray(w0, dtype=float)
    W = np.asarray(W, dtype=float)
    scale = np.maximum(w0, W.max(axis=1, initial=0.0))
    w0, W = w0 / scale, W / scale[:, None]
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


def marginals(w0: np.ndarray, W: np.ndarray, exact_events: float = EXACT_EVENTS) -> tuple[np.ndarray, bool]:
    """``(β, exact)``: :func:`exact_marginals` if the cluster has at most ``exact_events``
    joint events by :func:`n_events_bound`, else :func:`lbp_marginals`."""
    if n_events_bound(W) <= exact_events and np.shape(W)[1] <= 62:
        return exact_marginals(w0, W), True
    return lbp_marginals(w0, W), False


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
                exact_events: float = EXACT_EVENTS) -> ScanUpdate:
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
    w0 = 1.0 - p_detect * gate_prob * r
    beta = np.zeros((n, m + 1))
    beta[:, 0] = 1.0
    exact = []
    for tracks, plots in clusters([h.plots for h in hyps], m):
        col = {int(j): k for k, j in enumerate(plots)}
        Wc = np.zeros((len(tracks), len(plots)))
        for a, i in enumerate(tracks):
            h = hyps[i]
            Wc[a, [col[int(j)] for j in h.plots]] = np.exp(h.log_lik) * (p_detect * r[i] / density)  # P_D rᵢ Nᵢⱼ / ρ
        bc, is_exact = marginals(w0[tracks], Wc, exact_events)
        beta[tracks, 0] = bc[:, 0]
        beta[np.ix_(tracks, plots + 1)] = bc[:, 1:]
        exact.append(is_exact)
    r_post, c0 = existence_update(r, beta[:, 0], p_detect, gate_prob)
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
