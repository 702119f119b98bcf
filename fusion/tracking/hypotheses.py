r"""Hypotheses: which plots each track may have made, and at what cost.

*Gating.* A track predicted to ``(x, P)`` and a plot ``z`` of a sensor with model ``h``
give ``ν = z − h(x)`` (angles wrapped) and ``S = H P Hᵀ + R``; if the pair is right
``d² = νᵀ S⁻¹ ν`` is χ²(n_z), so the gate ``d² ≤ G = χ²⁻¹(P_G; n_z)`` keeps the true plot
with probability ``P_G``. ``H`` and ``S`` do not depend on ``z``, so :func:`mahalanobis2`
scores a whole scan against a track at once.

*Sequential gating.* The sensors of one frame are gated one after another: a track that
took a plot of one sensor is gated for the next at its state updated with that plot
(:func:`gating_update`). A track born or coasting with a broad covariance (an unknown
velocity spreads a second's prediction over hundreds of metres) is narrowed by its
first plot before the next sensor's plots compete for it, so a neighbour's plot that
fits the broad prediction no longer fits.

*Track-to-track distance* (:func:`track_distance2`): two estimates of one state differ by
``Δ = x₁ − x₂`` with covariance ``T = P₁ + P₂ − P₁₂ − P₁₂ᵀ`` (``P₁₂ = 0`` when unknown,
which only widens the gate); ``d² = Δᵀ T⁺ Δ`` with the rank of ``T`` as its degrees of
freedom (``T`` is singular when the two share a prior).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache
from typing import Any, Iterable, Sequence

import numpy as np
from scipy.linalg import cho_factor, cho_solve
from scipy.special import chdtri  # χ²⁻¹ without importing scipy.stats (0.3 s a process)

from .. import kalman
from ..angles import wrap_pi
from ..ekf import ekf_update_weighted
from ..measurement.kinds import model_of


# Gating --------------------------------------------------------------------------------
@lru_cache(maxsize=64)
def gate_threshold(dof: int, prob: float) -> float:
    """``G = χ²⁻¹(prob; dof)``: a true plot falls inside ``d² ≤ G`` with probability ``prob``."""
    if not 0.0 < prob < 1.0:
        raise ValueError(f"gate probability must lie in (0, 1), got {prob}")
    if dof < 1:
        raise ValueError(f"gate needs dof >= 1, got {dof}")
    return float(chdtri(dof, 1.0 - prob))


def mahalanobis2(model, x: np.ndarray, P: np.ndarray, Z: np.ndarray) -> np.ndarray:
    """``d²`` of each row of ``Z (n, n_z)`` (plots of one sensor) against the track ``(x, P)``.

    ``model`` is the sensor's :class:`~fusion.measurement.models.MeasurementModel`. Returns ``(n,)``;
    ``inf`` for every plot when the geometry is undefined (track over the site).
    """
    return distances(model, x, P, Z)[0]


def distances(model, x: np.ndarray, P: np.ndarray, Z: np.ndarray) -> tuple[np.ndarray, float]:
    """``(d², log c)``: :func:`mahalanobis2`, and the log of the normalising constant
    ``c = det(2πS)^(−½)`` of the innovation density, so that a plot's likelihood is
    ``N(ν; 0, S) = c · exp(−d²/2)`` (``log c = −inf`` where the geometry is undefined)."""
    Z = np.atleast_2d(np.asarray(Z, dtype=float))
    try:
        z_pred = model.h(x)
        H = model.jacobian(x)
    except ValueError:
        return np.full(len(Z), np.inf), -math.inf
    nu = Z - z_pred
    nu[:, model.angles] = wrap_pi(nu[:, model.angles])
    S = H @ P @ H.T + model.R
    c = cho_factor(0.5 * (S + S.T), lower=True, check_finite=False)
    log_c = -float(np.sum(np.log(np.abs(np.diag(c[0]))))) - 0.5 * model.n_z * math.log(2.0 * math.pi)
    return np.einsum("ij,ji->i", nu, cho_solve(c, nu.T, check_finite=False)), log_c


def gating_update(model, x: np.ndarray, P: np.ndarray, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(x, P)`` after the EKF update with one plot ``z`` of the sensor ``model``: the
    state a frame's next sensor is gated against (sequential gating, module docstring)."""
    nu, H = model.innovation_and_jacobian(np.asarray(z, dtype=float), x)
    res = kalman.update(x, P, nu, H, model.R)
    return res.x, res.P


# Track-to-track association ---------------------------------------------------------------
_PINV_RTOL = 1e-10  # eigenvalues of an equilibrated PSD matrix below this count as zero


def track_distance2(x1, P1, x2, P2, P12=None, dims=None) -> tuple[float, int]:
    """``(d², rank)`` of the difference of two estimates of one state (module docstring).

    ``dims`` selects the compared components (default: all); ``P12 = Cov(e₁, e₂)`` or None.
    ``rank`` is 0 (and ``d² = 0``) when ``T`` vanishes: identical tracks."""
    idx = np.arange(len(x1)) if dims is None else np.asarray(dims)
    d = (np.asarray(x1, float) - np.asarray(x2, float))[idx]
    T = np.asarray(P1, float) + np.asarray(P2, float)
    if P12 is not None:
        C = np.asarray(P12, float)
        T = T - C - C.T
    T = T[np.ix_(idx, idx)]
    # Pseudo-inverse of the equilibrated T (components of ~10⁴ m next to ~1 m/s).
    s = np.sqrt(np.clip(np.diag(T), 0.0, None))
    s = np.where(s > 1e-300, s, 1.0)
    w, V = np.linalg.eigh(0.5 * (T + T.T) / s[:, None] / s[None, :])
    keep = w > _PINV_RTOL * max(float(w.max(initial=0.0)), 1e-300)
    y = V[:, keep].T @ (d / s)
    return float(np.sum(y * y / w[keep])), int(keep.sum())




# One scan's hypotheses ----------------------------------------------------------------------
@dataclass(frozen=True)
class Hypotheses:
    """The gated costs of one scan: which plot each track may have made, and how well
    it fits. Built once per scan; an associator reads nothing else.

    Attributes:
        plots: the scan's plots (the columns), of one sensor.
        rows: the tracks (their places in the frame's list), in priority order.
        d2: ``(rows, plots)`` costs ``d²``; ``inf`` where a pair was not evaluated.
        gate: ``(rows,)`` each row's gate ``G``: a pair with ``d² ≤ G`` is in the gate,
            and a row that takes no plot costs ``G``.
        confirmed: ``(rows,)`` which rows are confirmed tracks.
        model: the scan's measurement model (None where the plots are not measurements).
        log_norm: ``(rows,)`` each row's ``log det(2πS)^(−½)``, so that a pair's
            likelihood is ``exp(log_norm − d²/2)`` (None where the costs are no χ² of
            plots: a probabilistic associator needs it).
        existence: ``(rows,)`` each row's probability that its target exists, at the
            scan (None: the tracks hold none; an associator takes them as certain).
    """

    plots: Sequence
    rows: Sequence[int]
    d2: np.ndarray
    gate: np.ndarray
    confirmed: np.ndarray
    model: Any = None
    log_norm: np.ndarray | None = None
    existence: np.ndarray | None = None

    @property
    def gated(self) -> np.ndarray:
        """``(rows, plots)``: the pairs inside their row's gate."""
        return self.d2 <= self.gate[:, None]


class PlotHypothesiser:
    """3D plots against 3D tracks: one :class:`Hypotheses` per sensor of a frame, the
    sensors in stream order, each gated against the tracks' gating states — their
    predictions, conditioned with sequential gating on what they took from the sensors
    before (module docstring). A track's ``filter`` is anything with
    ``predicted(t) -> (x, P)`` (a :class:`~fusion.filters.Filter`, a track fuser).

    Args:
        n_x: the state size of the tracks.
        gate_prob: ``P_G``.
        sequential: sequential gating (else every sensor is gated at the predictions).
    """

    def __init__(self, n_x: int, gate_prob: float, sequential: bool = True):
        self.n_x = n_x
        self.gate_prob = gate_prob
        self.sequential = sequential

    def predict(self, tracks: Sequence, frame) -> list[tuple[np.ndarray, np.ndarray]]:
        """The gating states: every track predicted to the frame's time."""
        return [tr.filter.predicted(frame.t) for tr in tracks]

    def scans(self, frame) -> list[list]:
        """The frame's plots grouped by sensor, sensors in order of first appearance."""
        return by_sensor(frame.plots)

    def hypothesise(self, states: Sequence[tuple[np.ndarray, np.ndarray]], tracks: Sequence, scan: Sequence) -> Hypotheses:
        """The scan's hypotheses against the tracks at their gating ``states``, with the
        tracks' existence where their logic holds one (:attr:`Track.existence
        <fusion.tracking.table.Track.existence>`)."""
        existence = [tr.existence for tr in tracks]
        return self.hypotheses(states, scan, [tr.confirmed for tr in tracks],
                               None if None in existence else np.array(existence, dtype=float))

    def hypotheses(self, states: Sequence[tuple[np.ndarray, np.ndarray]], scan: Sequence,
                   confirmed: Sequence[bool], existence: np.ndarray | None = None) -> Hypotheses:
        """The scan's hypotheses against tracks at ``states`` (``confirmed``: which are;
        ``existence``: their existence probabilities, if any)."""
        model = model_of(scan[0], self.n_x)
        gate = gate_threshold(model.n_z, self.gate_prob)
        Z = np.array([m.z for m in scan])
        d2 = np.full((len(states), len(scan)), np.inf)
        log_norm = np.full(len(states), -np.inf)
        for r, cols in self.candidates(model, gate, states, Z):
            d2[r, cols], log_norm[r] = distances(model, *states[r], Z[cols])
        return Hypotheses(scan, range(len(states)), d2, np.full(len(states), gate), np.array(confirmed, dtype=bool),
                          model, log_norm, existence)

    def candidates(self, model, gate: float, states: Sequence[tuple[np.ndarray, np.ndarray]],
                   Z: np.ndarray) -> Iterable[tuple[int, Any]]:
        """``(row, columns)``: the plots (rows of ``Z``, of the sensor ``model``) whose
        ``d²`` against each track is worth computing. Today every plot for every track.
        A spatial index goes here — a grid of the cells a track's gate ``G`` can reach,
        or a k-d tree of the plots — so that thousands of tracks do not cost tracks ×
        plots distances; a pair it leaves out must lie outside the gate (it stays at
        ``d² = inf``)."""
        every = slice(None)
        return ((r, every) for r in range(len(states)))

    def condition(self, states: list, hyp: Hypotheses, association) -> None:
        """Sequential gating: the gating state of each track that took a plot of the
        scan, updated with it (``association``: the scan's, see
        :mod:`fusion.tracking.associators`); with weights, the EKF's weighted update."""
        if not self.sequential:
            return
        for r, cols, beta, miss in association.per_row():
            i = hyp.rows[r]
            if len(cols) == 1 and miss == 0.0:
                states[i] = gating_update(hyp.model, *states[i], hyp.plots[cols[0]].z)
            else:  # weighted: the PDA mixture of the plots (fusion.pda)
                Z = np.array([hyp.plots[c].z for c in cols])
                res, _ = ekf_update_weighted(hyp.model, *states[i], Z, beta, miss)
                states[i] = res.x, res.P

    @staticmethod
    def unclaimed(hyp: Hypotheses, columns: Sequence[int]) -> list:
        """The plots no track took: left for initiation."""
        return [hyp.plots[c] for c in columns]


def by_sensor(plots: Iterable) -> list[list]:
    """The plots grouped by sensor, sensors in order of first appearance."""
    out: dict[str, list] = {}
    for m in plots:
        out.setdefault(m.sensor, []).append(m)
    return list(out.values())
