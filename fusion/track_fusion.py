r"""Track-to-track fusion rules, and the centre-side fuser that runs them.

Every rule fuses N ≥ 1 estimates ``(x_i, P_i)`` of one state at one time:

- ``naive``, the patent's rule, exact for independent estimates only:
  ``P_f = (Σ P_i⁻¹)⁻¹``, ``x_f = P_f Σ P_i⁻¹ x_i``;
- ``bar-shalom-campo``, best linear unbiased given the cross-covariances ``P_ij``
  (``x_f = x_1 − C D⁺ d``, ``P_f = P_11 − C D⁺ Cᵀ``), which follow
  ``P_ij ← A_i (F P_ij Fᵀ + Q) A_jᵀ`` with ``A_i = I − K_i H_i`` of each local update;
- ``ci``, covariance intersection, consistent for any correlation:
  ``P_f⁻¹ = Σ ω_i P_i⁻¹`` with ω on the simplex minimising ``tr P_f`` or ``det P_f``;
- ``info``, subtracting the information each track shares with the centre's prior:
  ``P_f⁻¹ = P_c⁻¹ + Σ (P_i⁻¹ − P̄_i⁻¹)`` (and the same for information vectors), exact
  for linear(ised) updates from one prior; with local IMMs applied per model, the
  centre rebuilding the centralised model likelihood from the locals' ones.

:class:`TrackFuser` keeps the centre's state between scans (its prediction, the
cross-covariances, the IMM's per-model estimates) and fuses local reports
(:class:`fusion.links.LocalReport`, :class:`~fusion.links.PredictionReport`): ``info``
reads their ``prior``, ``bar-shalom-campo`` their ``KH`` and ``feedback_t``, per-model
``info`` their ``models``. The N-track and per-model formulas, how ω is found and the
numerics (equilibrated inverses, information vectors about a reference point):
docs/algorithms.md, "Track-to-track fusion rules".
"""

from __future__ import annotations

from typing import Sequence

import numpy as np
from scipy.linalg import eigh
from scipy.optimize import brentq, minimize

from . import linalg
from .imm import ModelSet, mixed_predictions
from .kalman import gaussian_loglikelihood, gaussian_mixture, symmetrise
from .links import ModelStates, Report
from .topology import FUSION_RULES
from .types import Estimate

CI_CRITERIA = ("trace", "det")
_PINV_RTOL = 1e-10  # eigenvalues of an equilibrated PSD matrix below this count as zero


# Linear-algebra helpers ------------------------------------------------------------
def _inv_spd_many(Ps: Sequence[np.ndarray], what: str = "covariance") -> list[np.ndarray]:
    """Inverses of SPD matrices via equilibration + Cholesky (one batched call)."""
    A = np.asarray(Ps, dtype=float)
    d = np.diagonal(A, axis1=-2, axis2=-1)
    if not d.min() > 0.0:  # also catches NaN
        raise ValueError(f"{what} is not positive definite (diagonal {d})")
    s = 1.0 / np.sqrt(d)
    ss = s[:, :, None] * s[:, None, :]
    try:
        L = linalg.cholesky(A * ss)
    except np.linalg.LinAlgError:
        raise ValueError(f"{what} is not positive definite") from None
    Linv = linalg.inv(L)  # triangular, condition number √cond of the equilibrated matrix
    return list(np.swapaxes(Linv, -1, -2) @ Linv * ss)


def _inv_spd(P: np.ndarray, what: str = "covariance") -> np.ndarray:
    """Inverse of one SPD matrix; see :func:`_inv_spd_many`."""
    return _inv_spd_many([P], what)[0]


def _pinv_psd(D: np.ndarray) -> np.ndarray:
    """A generalised inverse of a PSD matrix: pseudo-inverse of its equilibrated form."""
    d = np.sqrt(np.clip(np.diag(D), 0.0, None))
    scale = np.where(d > 1e-300, d, 1.0)
    Ds = D / scale[:, None] / scale[None, :]
    w, V = np.linalg.eigh(symmetrise(Ds))
    keep = w > _PINV_RTOL * max(float(w.max(initial=0.0)), 1e-300)
    Dp = (V[:, keep] / w[keep]) @ V[:, keep].T
    return Dp / scale[:, None] / scale[None, :]


def _check(xs, Ps):
    xs = [np.asarray(x, dtype=float) for x in xs]
    Ps = [np.asarray(P, dtype=float) for P in Ps]
    if not xs or len(xs) != len(Ps):
        raise ValueError(f"need one or more estimates with one covariance each, got {len(xs)} and {len(Ps)}")
    n = xs[0].size
    for x, P in zip(xs, Ps):
        if x.shape != (n,) or P.shape != (n, n):
            raise ValueError(f"estimates must all be ({n},) with ({n}, {n}) covariances, got {x.shape}, {P.shape}")
    return xs, Ps


# The rules ---------------------------------------------------------------------------
def fuse_naive(xs: Sequence[np.ndarray], Ps: Sequence[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Independent-estimates (the patent's "MMSE") fusion."""
    xs, Ps = _check(xs, Ps)
    if len(xs) == 1:
        return xs[0], Ps[0]
    ref = xs[0]
    Ys = _inv_spd_many(Ps)
    Pf = _inv_spd(sum(Ys), "fused information")
    xf = ref + Pf @ sum(Y @ (x - ref) for Y, x in zip(Ys, xs))
    return xf, Pf


def fuse_bar_shalom_campo(xs, Ps, cross) -> tuple[np.ndarray, np.ndarray, list[np.ndarray]]:
    """Best linear unbiased fusion with cross-covariances ``cross[i][j] = Cov(e_i, e_j)``.

    ``cross`` is any object indexable as ``cross[i][j]`` for i ≠ j (a nested list, or
    a dict of dicts). Returns ``x_f``, ``P_f`` and the weights ``W_i`` (``x_f = Σ W_i x_i``,
    ``Σ W_i = I``).
    """
    xs, Ps = _check(xs, Ps)
    N, n = len(xs), xs[0].size
    if N == 1:
        return xs[0], Ps[0], [np.eye(n)]

    def Pij(i, j):
        return Ps[i] if i == j else np.asarray(cross[i][j], dtype=float)

    m = N - 1
    C = np.hstack([Pij(0, j) - Ps[0] for j in range(1, N)])  # Cov(e_1, d)
    D = np.empty((m * n, m * n))
    for a, j in enumerate(range(1, N)):
        for b, k in enumerate(range(1, N)):
            D[a * n : (a + 1) * n, b * n : (b + 1) * n] = Pij(j, k) - Pij(j, 0) - Pij(0, k) + Ps[0]
    d = np.concatenate([xs[j] - xs[0] for j in range(1, N)])
    G = -C @ _pinv_psd(symmetrise(D))  # x_f = x_1 + G d
    xf = xs[0] + G @ d
    Pf = symmetrise(Ps[0] + G @ C.T)
    Gs = [G[:, a * n : (a + 1) * n] for a in range(m)]
    return xf, Pf, [np.eye(n) - sum(Gs)] + Gs


def ci_weights(Ps: Sequence[np.ndarray], criterion: str = "trace") -> np.ndarray:
    """The covariance-intersection weights ω minimising ``tr P_f`` or ``det P_f``."""
    return _ci_weights(_inv_spd_many(Ps), criterion)


def _ci_weights(Ys: Sequence[np.ndarray], criterion: str) -> np.ndarray:
    if criterion not in CI_CRITERIA:
        raise ValueError(f"ci criterion must be one of {CI_CRITERIA}, got {criterion!r}")
    N = len(Ys)
    if N == 1:
        return np.ones(1)
    if N == 2:
        # Y1 v = λ Y2 v with Vᵀ Y2 V = I: ω Y1 + (1−ω) Y2 = V⁻ᵀ diag(1 + ω(λ−1)) V⁻¹.
        lam, V = eigh(Ys[0], Ys[1])
        a = lam - 1.0
        if criterion == "det":  # minimise −Σ log(1 + ω a)
            def grad(w):
                return -np.sum(a / (1.0 + w * a))
        else:  # minimise Σ c/(1 + ω a), c = |v|²
            c = np.sum(V * V, axis=0)

            def grad(w):
                return -np.sum(c * a / (1.0 + w * a) ** 2)
        g0, g1 = grad(0.0), grad(1.0)
        if g0 >= 0.0:
            w = 0.0
        elif g1 <= 0.0:
            w = 1.0
        else:
            w = brentq(grad, 0.0, 1.0, xtol=1e-14, rtol=4 * np.finfo(float).eps)
        return np.array([w, 1.0 - w])

    def objective(w):
        M = sum(wi * Y for wi, Y in zip(w, Ys))
        if criterion == "det":
            return -np.linalg.slogdet(M)[1]
        return float(np.trace(np.linalg.inv(M)))

    res = minimize(
        objective,
        np.full(N, 1.0 / N),
        method="SLSQP",
        bounds=[(0.0, 1.0)] * N,
        constraints=[{"type": "eq", "fun": lambda w: np.sum(w) - 1.0}],
        options={"ftol": 1e-12, "maxiter": 200},
    )
    w = np.clip(res.x, 0.0, 1.0)
    return w / w.sum()


def fuse_ci(xs, Ps, criterion: str = "trace") -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Covariance intersection; returns ``x_f``, ``P_f`` and ω."""
    xs, Ps = _check(xs, Ps)
    if all(np.array_equal(P, Ps[0]) for P in Ps[1:]):
        # Equal covariances: every ω gives P_f = P; take equal weights.
        if criterion not in CI_CRITERIA:
            raise ValueError(f"ci criterion must be one of {CI_CRITERIA}, got {criterion!r}")
        return sum(xs) / len(xs), Ps[0], np.full(len(xs), 1.0 / len(xs))
    Ys = _inv_spd_many(Ps)
    w = _ci_weights(Ys, criterion)
    ref = xs[0]
    Pf = _inv_spd(sum(wi * Y for wi, Y in zip(w, Ys)), "CI information")
    xf = ref + Pf @ sum(wi * (Y @ (x - ref)) for wi, Y, x in zip(w, Ys, xs))
    return xf, Pf, w


def fuse_info(xs, Ps, prior_xs, prior_Ps, x_c, P_c) -> tuple[np.ndarray, np.ndarray]:
    """Information fusion subtracting each track's prior ``(x̄ᵢ, P̄ᵢ)`` from its estimate
    and adding the centre's prior ``(x_c, P_c)`` once:
    ``P_f⁻¹ = P_c⁻¹ + Σ (Pᵢ⁻¹ − P̄ᵢ⁻¹)``, and the same for the information vectors."""
    xs, Ps = _check(xs, Ps)
    prior_xs, prior_Ps = _check(prior_xs, prior_Ps)
    if len(prior_xs) != len(xs):
        raise ValueError(f"info fusion needs one prior per track, got {len(prior_xs)} for {len(xs)}")
    x_c = np.asarray(x_c, dtype=float)
    P_c = np.asarray(P_c, dtype=float)
    # Prediction-only reports carry no new information; priors equal to the centre's
    # (feedback, two-stage) share its inverse. Invert each distinct matrix once.
    used = [
        (x, P, xb, Pb)
        for x, P, xb, Pb in zip(xs, Ps, prior_xs, prior_Ps)
        if not (np.array_equal(xb, x) and np.array_equal(Pb, P))
    ]
    mats = [P_c] + [P for _, P, _, _ in used]
    prior_idx = []
    for _, _, _, Pb in used:
        prior_idx.append(0 if np.array_equal(Pb, P_c) else len(mats))
        if prior_idx[-1]:
            mats.append(Pb)
    inv = _inv_spd_many(mats)
    Y = inv[0]
    y = np.zeros_like(x_c)  # information vector about x_c
    for k, ((x, _, xb, _), j) in enumerate(zip(used, prior_idx)):
        Yi, Ybi = inv[1 + k], inv[j]
        Y = Y + (Yi - Ybi)
        y = y + Yi @ (x - x_c) - Ybi @ (xb - x_c)
    Pf = _inv_spd(symmetrise(Y), "info-fused information (prior subtracted more than it was counted?)")
    return x_c + Pf @ y, Pf


def fuse_info_model(xs, Ps, prior_xs, prior_Ps, logliks, x_c, P_c) -> tuple[np.ndarray, np.ndarray, float]:
    """One model of the per-model information fusion of local IMMs (module docstring):
    ``x_f``, ``P_f`` (:func:`fuse_info` on the coordinates where ``P_c`` has variance)
    and the centralised log-likelihood ``log Λ_j`` of the model."""
    x_c = np.asarray(x_c, dtype=float)
    P_c = np.asarray(P_c, dtype=float)
    keep = np.diag(P_c) > 0.0
    sub = np.ix_(keep, keep)
    xs, Ps = _check(xs, Ps)
    prior_xs, prior_Ps = _check(prior_xs, prior_Ps)
    for P in (*Ps, *prior_Ps):
        if np.any(P[~keep, :]) or np.any(P[:, ~keep]):
            raise ValueError("per-model info fusion: a local covariance has variance where the centre's prior has none")
    xf_s, Pf_s = fuse_info([x[keep] for x in xs], [P[sub] for P in Ps], [x[keep] for x in prior_xs],
                           [P[sub] for P in prior_Ps], x_c[keep], P_c[sub])
    x_f = x_c.copy()
    x_f[keep] = xf_s
    P_f = np.zeros_like(P_c)
    P_f[sub] = Pf_s

    def log_n(mean, P):  # log N(x_f; mean, P) on the kept coordinates
        return gaussian_loglikelihood(x_f[keep] - np.asarray(mean, float)[keep], P[sub])

    ll = sum(float(l) + log_n(x, P) - log_n(xb, Pb) for l, x, P, xb, Pb in zip(logliks, xs, Ps, prior_xs, prior_Ps))
    return x_f, P_f, ll + log_n(x_c, P_c) - log_n(x_f, P_f)


# The centre-side fuser --------------------------------------------------------------
class TrackFuser:
    """Centre-side fusion of local tracks with the bookkeeping each rule needs.

    Keeps the last fused estimate ``(x, P, t)`` (the ``info`` rule's centre prior,
    predicted with ``motion``) and, for ``bar-shalom-campo``, the cross-covariances
    between every pair of local nodes and between the fused track and each node, so
    that tracks re-started from the fused estimate (feedback, two-stage) are handled
    exactly. Local tracks are reports (:data:`fusion.links.Report`), all at the fusion
    time.

    Every known node is assumed to report at every fusion time (a node with no
    measurement reports its prediction); a node that does not is propagated as a pure
    prediction (``A = I``) in the cross-covariance bookkeeping.

    With ``info`` and an IMM's :class:`~fusion.imm.ModelSet` as ``motion`` the fuser is
    an IMM centre: it keeps per-model estimates and mode probabilities, predicts them
    with the IMM cycle and fuses per model (module docstring); :meth:`model_states` is
    what a fed-back node restarts from.
    """

    def __init__(self, rule: str, motion, ci_criterion: str = "trace", method: str = "HNV", track: str = "T1"):
        if rule not in FUSION_RULES:
            raise ValueError(f"fusion rule must be one of {FUSION_RULES}, got {rule!r}")
        if ci_criterion not in CI_CRITERIA:
            raise ValueError(f"ci criterion must be one of {CI_CRITERIA}, got {ci_criterion!r}")
        if rule == "bar-shalom-campo" and isinstance(motion, ModelSet):
            raise ValueError("fusion rule 'bar-shalom-campo' needs local tracks of one linear(ised) model (its "
                             "cross-covariances come from each update's K·H); with motion = \"imm\" use 'info' "
                             "(exact, per model) or 'ci'")
        self.rule = rule
        self.motion = motion
        self.ci_criterion = ci_criterion
        self.method = method
        self.track = track
        self.x = self.P = self.t = None
        self._P_nodes: dict[str, np.ndarray] = {}  # Cov(e_a, e_a) at self.t
        self._cross: dict[tuple[str, str], np.ndarray] = {}  # Cov(e_a, e_b), a < b, at self.t
        self._cross_fused: dict[str, np.ndarray] = {}  # Cov(e_f, e_a) at self.t
        self.per_model = rule == "info" and isinstance(motion, ModelSet)
        self.model_xs = self.model_Ps = self.mu = None  # the IMM centre's state at self.t

    @property
    def initialised(self) -> bool:
        return self.t is not None

    def initialise(self, x: np.ndarray, P: np.ndarray, t: float) -> None:
        """Start from a shared initial estimate (every local tracker starts from it too)."""
        self.x, self.P, self.t = np.asarray(x, float), np.asarray(P, float), float(t)
        if self.per_model:
            m = len(self.motion.models)
            self.model_xs, self.model_Ps = np.array([self.x] * m), np.array([self.P] * m)
            self.mu = np.array(self.motion.mu0, dtype=float)
        self._P_nodes.clear()
        self._cross.clear()
        self._cross_fused.clear()

    def add_node(self, node: str) -> None:
        """Register a node that starts from the current fused estimate (its
        initialisation): its error is the fused error, so its covariances are known
        and a node that does not report at the next fusion is still accounted for."""
        if not self.initialised:
            raise ValueError("fuser not initialised")
        for a, C in self._cross_fused.items():  # Cov(e_node, e_a) = Cov(e_f, e_a)
            if a != node:
                self._cross[(node, a) if node < a else (a, node)] = C if node < a else C.T
        self._P_nodes[node] = self.P
        self._cross_fused[node] = self.P

    def predicted(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """The last fused estimate predicted to ``t`` (the centre prior)."""
        if not self.initialised:
            raise ValueError("fuser not initialised")
        dt = float(t) - self.t
        if dt < 0.0:
            raise ValueError(f"cannot fuse at t={t}: the fuser is already at t={self.t}")
        if dt == 0.0:
            return self.x, self.P
        if self.per_model:
            xs, Ps, cbar = mixed_predictions(self.motion, self.mu, self.model_xs, self.model_Ps, dt)
            return gaussian_mixture(cbar, xs, Ps)
        F = self.motion.F(dt)
        return F @ self.x, symmetrise(F @ self.P @ F.T + self.motion.Q(dt))

    def model_states(self) -> ModelStates | None:
        """The IMM centre's per-model estimates and mode probabilities at its time; None
        when the fuser does not fuse per model."""
        if not self.per_model:
            return None
        return ModelStates(self.model_xs, self.model_Ps, self.mu)

    def cross_covariance(self, t: float, r: Report) -> np.ndarray | None:
        """``Cov(e_c, e_i)`` of the centre prior at ``t`` (:meth:`predicted`) and the local
        report ``r`` (at ``t``), where it is known: ``P_c Aᵀ`` for a track restarted from
        this fuser's latest estimate (they share the prediction), ``(F P_fi Fᵀ + Q) Aᵀ``
        with the ``bar-shalom-campo`` bookkeeping; ``A = I − K H`` of the local update.
        None otherwise (another rule, unknown node)."""
        fb = r.feedback_t
        restarted = fb is not None and abs(float(fb) - self.t) <= 1e-9
        if not (restarted or (self.rule == "bar-shalom-campo" and r.node in self._cross_fused)):
            return None
        x_c, P_c = self.predicted(t)
        if restarted:
            C = P_c
        else:
            dt = float(t) - self.t
            F = self.motion.F(dt)
            C = F @ self._cross_fused[r.node] @ F.T + self.motion.Q(dt)
        return C @ (np.eye(x_c.size) - np.asarray(r.KH, float)).T

    def fuse(self, t: float, reports: Sequence[Report]) -> Estimate:
        """Fuse the local reports (all at time ``t``) into the centre's estimate at ``t``."""
        if not reports:
            raise ValueError("nothing to fuse")
        t = float(t)
        nodes = [r.node for r in reports]
        if len(set(nodes)) != len(nodes):
            raise ValueError(f"two tracks from one node in one fusion: {nodes}")
        for r in reports:
            if abs(r.estimate.t - t) > 1e-9:
                raise ValueError(f"track from node {r.node!r} is at t={r.estimate.t}, fusion time is {t}")
        x_c, P_c = self.predicted(t)
        xs = [np.asarray(r.estimate.x, float) for r in reports]
        Ps = [np.asarray(r.estimate.P, float) for r in reports]
        extra: dict = {"rule": self.rule, "nodes": nodes}
        if self.rule == "naive":
            xf, Pf = fuse_naive(xs, Ps)
        elif self.rule == "ci":
            xf, Pf, w = fuse_ci(xs, Ps, self.ci_criterion)
            extra["omega"] = w
        elif self.per_model:
            xf, Pf = self._fuse_info_models(t, reports)
        elif self.rule == "info":
            priors = [r.prior for r in reports]
            xf, Pf = fuse_info(xs, Ps, [p.x for p in priors], [p.P for p in priors], x_c, P_c)
        else:
            xf, Pf = self._fuse_bsc(t, reports, xs, Ps, P_c)
        self.x, self.P, self.t = xf, Pf, t
        return Estimate(t=t, x=xf, P=Pf, method=self.method, node="centre", track=self.track, extra=extra)

    def _fuse_info_models(self, t, reports):
        dt = t - self.t
        if dt == 0.0:  # a second fusion at one time (DDHNV's second stage): no switching
            cxs, cPs, cbar = self.model_xs, self.model_Ps, self.mu
        else:
            cxs, cPs, cbar = mixed_predictions(self.motion, self.mu, self.model_xs, self.model_Ps, dt)
        m, n = cxs.shape
        rep = [r.models for r in reports]
        if any(terms is None or terms.xs.shape != (m, n) for terms in rep):
            raise ValueError(f"info fusion with motion = imm needs every local report's per-model terms ({m} models "
                             f"of {n} states)")
        xs, Ps, ll = [], [], np.empty(m)
        for j in range(m):
            x, P, ll[j] = fuse_info_model([r.xs[j] for r in rep], [r.Ps[j] for r in rep], [r.prior_xs[j] for r in rep],
                                          [r.prior_Ps[j] for r in rep], [r.loglik[j] for r in rep], cxs[j], cPs[j])
            xs.append(x)
            Ps.append(P)
        with np.errstate(divide="ignore"):
            ell = np.log(cbar) + ll
        w = np.exp(ell - ell.max())
        self.model_xs, self.model_Ps, self.mu = np.array(xs), np.array(Ps), w / w.sum()
        return gaussian_mixture(self.mu, self.model_xs, self.model_Ps)

    def _fuse_bsc(self, t, reports, xs, Ps, P_c):
        dt = t - self.t
        F, Q = self.motion.F(dt), self.motion.Q(dt)
        n = xs[0].size
        A, fb = {}, {}
        for r in reports:
            A[r.node] = np.eye(n) - np.asarray(r.KH, float)
            fb[r.node] = r.feedback_t is not None and abs(float(r.feedback_t) - self.t) <= 1e-9
            if not fb[r.node] and r.node not in self._P_nodes:
                raise ValueError(
                    f"bar-shalom-campo: no cross-covariance for node {r.node!r}; a local track must start "
                    "from the centre's fused estimate (initialisation or feedback)"
                )
        reported = {r.node: P for r, P in zip(reports, Ps)}
        nodes = sorted(set(self._P_nodes) | set(reported))
        for a in nodes:
            A.setdefault(a, np.eye(n))
            fb.setdefault(a, False)

        def prior_cross(a, b):  # Cov(e_a, e_b) of the priors at t (before the updates at t)
            if fb[a] and fb[b]:
                return P_c
            if fb[a]:
                return F @ self._cross_fused[b] @ F.T + Q
            if fb[b]:
                return (F @ self._cross_fused[a] @ F.T + Q).T
            C = self._cross[(a, b)] if a < b else self._cross[(b, a)].T
            return F @ C @ F.T + Q

        P_nodes = {a: reported.get(a) if a in reported else symmetrise(F @ self._P_nodes[a] @ F.T + Q) for a in nodes}
        cross = {}
        for i, a in enumerate(nodes):
            for b in nodes[i + 1 :]:
                cross[(a, b)] = A[a] @ prior_cross(a, b) @ A[b].T

        def Pab(a, b):
            if a == b:
                return P_nodes[a]
            return cross[(a, b)] if a < b else cross[(b, a)].T

        rep = [r.node for r in reports]
        xf, Pf, W = fuse_bar_shalom_campo(xs, Ps, [[Pab(a, b) for b in rep] for a in rep])
        self._P_nodes = P_nodes
        self._cross = cross
        self._cross_fused = {b: sum(Wi @ Pab(a, b) for Wi, a in zip(W, rep)) for b in nodes}
        return xf, Pf
