r"""Interacting Multiple Model filter of one 3D track (Blom & Bar-Shalom 1988), ``motion = "imm"``.

Models (:class:`ModelSet`) on one common state, the CA layout ``[p v a]`` (9 states), so
that mixing adds like quantities: ``cv`` (:class:`fusion.motion.PaddedConstantVelocity`,
acceleration held at zero), ``ct`` (:class:`fusion.motion.ConstantTurn`, ``ȧ = −ω² v``
at a fixed rate ω, any direction and plane; one per rate of a grid), ``turn``
(:class:`fusion.motion.CoordinatedTurn`, a coordinated turn at the rate the state's own
``v`` and ``a`` imply, straight flight at ``a = 0``) and ``ca``. Each model-matched
filter is an ordinary track filter (EKF or UKF, ``filter``) and the IMM adds only the
cycle below, which predicts each model itself (:func:`fusion.ekf.motion_predict`:
``F x``, or a state-dependent model's ``f(x)`` with its Jacobian, as an EKF).
``Π[i, j] = P(model j at k | model i at k − 1)``: a fixed matrix, or from each model's expected sojourn time τᵢ the
continuous-time Markov chain ``Π(dt) = exp(G dt)``, ``Gᵢᵢ = −1/τᵢ``, ``Gᵢⱼ = 1/(τᵢ (m − 1))``
(a model is left at rate 1/τᵢ, to any other alike), so irregular updates switch alike.

Predict to ``t`` (posterior mode probabilities μ, model states ``(xᵢ, Pᵢ)``)::

    c̄ⱼ = Σᵢ Π[i, j] μᵢ,        μᵢ|ⱼ = Π[i, j] μᵢ / c̄ⱼ                      (mixing)
    x₀ⱼ = Σᵢ μᵢ|ⱼ xᵢ,         P₀ⱼ = Σᵢ μᵢ|ⱼ (Pᵢ + (xᵢ − x₀ⱼ)(xᵢ − x₀ⱼ)ᵀ)
    xⱼ⁻ = fⱼ(x₀ⱼ),            Pⱼ⁻ = Fⱼ P₀ⱼ Fⱼᵀ + Qⱼ,   Fⱼ = ∂fⱼ/∂x(x₀ⱼ)     (model j)

and ``μ ← c̄``. Update with a measurement: each model's own update gives ``νⱼ, Sⱼ``
and the likelihood ``Λⱼ = N(νⱼ; 0, Sⱼ)``; ``μⱼ ∝ Λⱼ c̄ⱼ``, in the log domain
(``ℓⱼ = log Λⱼ + log c̄ⱼ``, ``μⱼ = exp(ℓⱼ − max ℓ) / Σ``). The track's Gaussian, for
predictions as for updates, is the moment-matched mixture::

    x = Σⱼ μⱼ xⱼ,             P = Σⱼ μⱼ (Pⱼ + (xⱼ − x)(xⱼ − x)ᵀ)

Several updates at one time (no predict between them) are sequential Bayes: each
multiplies μ by its likelihoods. ``K·H`` for the track-fusion rules is the one that
gives ``P⁺ = (I − K H) P⁻`` for the mixtures, ``K H = I − (P⁻⁻¹ P⁺)ᵀ``; the update's
ν, S are the mixture's (``ν = Σ c̄ⱼ νⱼ``, ``S = Σ c̄ⱼ (Sⱼ + (νⱼ − ν)(νⱼ − ν)ᵀ)``).
A Gaussian without mode probabilities (a track-fusion centre's fused estimate) is
predicted with the set's ``prediction_model`` (its CA model, the widest).
"""

from __future__ import annotations

from typing import Callable, Sequence

import numpy as np
from scipy.linalg import expm

from . import kalman
from .links import ModelTerms
from .pda import WeightedUpdate, check_weights
from .motion import ConstantAcceleration, ConstantTurn, CoordinatedTurn, KinematicModel, PaddedConstantVelocity
from .ekf import motion_predict

IMM_MODELS = ("cv", "ct", "turn", "ca")


class ModelSet:
    """The IMM's motion models, transition matrix and initial mode probabilities.

    Args:
        models: motion models on one state (``F(dt)``, ``Q(dt)``, ``n_x``, ``name``).
        Pi: Markov transition matrix per update, rows "from", columns "to" (rows sum to 1);
            or None with ``sojourn``.
        mu0: initial mode probabilities (default equal).
        sojourn: expected time in each model (s, > 0): ``Π(dt) = exp(G dt)`` (module docstring).
    """

    def __init__(self, models: Sequence[KinematicModel], Pi=None, mu0=None, sojourn=None):
        self.models = tuple(models)
        m = len(self.models)
        if m == 0 or len({md.n_x for md in self.models}) != 1:
            raise ValueError("an IMM needs at least one model, all on one state")
        self.n_x = self.models[0].n_x
        self.G = None
        self._transitions: dict[float, np.ndarray] = {}
        if (Pi is None) == (sojourn is None):
            raise ValueError("an IMM needs a transition matrix or sojourn times, not both")
        if sojourn is not None:
            tau = np.array(sojourn, dtype=float)
            if tau.shape != (m,) or not np.all(np.isfinite(tau) & (tau > 0.0)):
                raise ValueError(f"IMM sojourn times must be {m} values > 0 s, got {sojourn}")
            self.G = np.zeros((m, m)) if m == 1 else np.outer(1.0 / (tau * (m - 1)), np.ones(m))
            np.fill_diagonal(self.G, -1.0 / tau if m > 1 else 0.0)
            Pi = np.eye(m)
        self.Pi = np.array(Pi, dtype=float)
        self.mu0 = np.full(m, 1.0 / m) if mu0 is None else np.array(mu0, dtype=float)
        if self.Pi.shape != (m, m) or np.any(self.Pi < 0) or np.any(np.abs(self.Pi.sum(axis=1) - 1.0) > 1e-12):
            raise ValueError(f"IMM transition matrix must be {m}×{m} with rows of probabilities summing to 1")
        if self.mu0.shape != (m,) or np.any(self.mu0 < 0) or abs(self.mu0.sum() - 1.0) > 1e-12:
            raise ValueError(f"IMM initial mode probabilities must be {m} values >= 0 summing to 1")
        self.names = tuple(md.name for md in self.models)
        self.prediction_model = next((md for md in self.models if md.name == "ca"), self.models[-1])
        self.name = "imm"

    def __repr__(self) -> str:
        return f"ModelSet({list(self.models)!r})"

    def transition(self, dt: float) -> np.ndarray:
        """``Π`` for an update ``dt`` after the previous one (the fixed matrix, or ``exp(G dt)``)."""
        if self.G is None:
            return self.Pi
        Pi = self._transitions.get(float(dt))
        if Pi is None:  # updates repeat a few intervals: cache them (bounded, read-only)
            Pi = np.clip(expm(self.G * float(dt)), 0.0, None)
            Pi /= Pi.sum(axis=1, keepdims=True)
            Pi.setflags(write=False)
            if len(self._transitions) >= 64:
                self._transitions.clear()
            self._transitions[float(dt)] = Pi
        return Pi

    def F(self, dt: float) -> np.ndarray:
        return self.prediction_model.F(dt)

    def Q(self, dt: float) -> np.ndarray:
        return self.prediction_model.Q(dt)

    def check_state(self, x: np.ndarray) -> np.ndarray:
        return self.models[0].check_state(x)


def model_set(names: Sequence[str], q: dict[str, float], turn_rates: Sequence[float],
              sojourn: dict[str, float], noise: str = "continuous") -> ModelSet:
    """The ``[tracker]`` IMM: models by name (of :data:`IMM_MODELS`, each once; ``ct`` is
    one CT model per rate of ``turn_rates``), process noise ``q[name]`` and expected
    sojourn time ``sojourn[name]`` (s; every CT model has the ``ct`` one)."""
    names = tuple(names)
    if not names or len(set(names)) != len(names) or not set(names) <= set(IMM_MODELS):
        raise ValueError(f"IMM models must be distinct names among {IMM_MODELS}, got {names}")
    rates = tuple(float(w) for w in turn_rates)
    if "ct" in names and not rates:
        raise ValueError("an IMM with a ct model needs at least one turn rate")
    build: dict[str, Callable[[], list[KinematicModel]]] = {
        "cv": lambda: [PaddedConstantVelocity(q["cv"], noise)],
        "ct": lambda: [ConstantTurn(q["ct"], w, noise) for w in rates],
        "turn": lambda: [CoordinatedTurn(q["turn"], noise)],
        "ca": lambda: [ConstantAcceleration(q["ca"], noise)],
    }
    models = [md for n in names for md in build[n]()]
    return ModelSet(models, sojourn=[sojourn[md.name] for md in models])


def mixed_predictions(models: ModelSet, mu: np.ndarray, xs: np.ndarray, Ps: np.ndarray, dt: float):
    """The cycle's predict (module docstring): ``(xⱼ⁻, Pⱼ⁻)`` of every model and ``c̄``,
    from the posterior mode probabilities ``mu`` and model states ``xs``, ``Ps``."""
    Pi = models.transition(dt)
    cbar = mu @ Pi
    with np.errstate(divide="ignore", invalid="ignore"):
        mix = Pi * mu[:, None] / cbar[None, :]  # mix[i, j] = μᵢ|ⱼ
    out_x, out_P = [], []
    for j, md in enumerate(models.models):
        w = mix[:, j] if cbar[j] > 0.0 else mu  # a model of probability 0: any prior
        x0, P0 = kalman.gaussian_mixture(w, xs, Ps)
        xj, Pj = motion_predict(md, x0, P0, dt)
        out_x.append(xj)
        out_P.append(Pj)
    return np.array(out_x), np.array(out_P), cbar


class TrackIMM:
    """IMM filter of one 3D track (module docstring): holds ``(x, P, t)``, the mode
    probabilities ``mu`` and one model-matched filter per model.

    Args:
        models: the :class:`ModelSet`.
        new_filters: one ``(x, P, t) -> Filter`` per model (:data:`fusion.filters.NewFilter`).
        x, P, t: the initial state, its covariance and its time (every model starts there).
        mu: initial mode probabilities (default the set's ``mu0``).
    """

    def __init__(self, models: ModelSet, new_filters: Sequence[Callable], x: np.ndarray, P: np.ndarray,
                 t: float, mu=None):
        if len(new_filters) != len(models.models):
            raise ValueError("an IMM needs one filter per model")
        self.models = models
        x = models.check_state(x)
        self.filters = [f(x, P, t) for f in new_filters]
        self.mu = np.array(models.mu0 if mu is None else mu, dtype=float)
        self.x, self.P, self.t = x, np.asarray(P, dtype=float), float(t)
        self._prior_P = self._post_P = None
        self.last_update: dict | None = None  # the per-model terms of an update at this time (:meth:`update`)

    def model_states(self) -> tuple[np.ndarray, np.ndarray]:
        """Every model's ``(xⱼ, Pⱼ)`` at the filter's time, stacked ``(m, n)``, ``(m, n, n)``."""
        return np.array([f.x for f in self.filters]), np.array([f.P for f in self.filters])

    def model_terms(self) -> ModelTerms:
        """What a local report of this filter carries for per-model fusion
        (:class:`fusion.links.ModelTerms`): every model's estimate and, after an
        :meth:`update` at this time, the prediction it started from and its
        log-likelihood ``log Λⱼ``; after a prediction or a restart, the estimate and 0."""
        xs, Ps = self.model_states()
        last = self.last_update
        if last is None:
            return ModelTerms(xs, Ps, xs, Ps, np.zeros(len(xs)))
        return ModelTerms(xs, Ps, last["prior_xs"], last["prior_Ps"], last["loglik"])

    def set_model_states(self, xs, Ps, mu, t: float) -> None:
        """Restart from per-model states and mode probabilities at ``t`` (a centre's
        per-model fused estimate fed back); the track's Gaussian is their mixture."""
        xs, Ps = np.asarray(xs, dtype=float), np.asarray(Ps, dtype=float)
        mu = np.asarray(mu, dtype=float)
        if xs.shape != (len(self.filters), self.models.n_x) or Ps.shape != xs.shape + (self.models.n_x,) \
                or mu.shape != (len(self.filters),):
            raise ValueError(f"IMM model states must be {len(self.filters)} states of {self.models.n_x} with their "
                             f"covariances and probabilities, got {xs.shape}, {Ps.shape}, {mu.shape}")
        for f, x, P in zip(self.filters, xs, Ps):
            f.x, f.P, f.t = x, P, float(t)
        self.mu = mu
        self.x, self.P = kalman.gaussian_mixture(mu, xs, Ps)
        self.t = float(t)
        self.last_update = None

    def set_state(self, x: np.ndarray, P: np.ndarray, t: float) -> None:
        """Restart every model from ``(x, P)`` at ``t`` (a fed-back prior), keeping ``mu``."""
        x = self.models.check_state(x)
        P = np.asarray(P, dtype=float)
        for f in self.filters:
            f.x, f.P, f.t = x, P, float(t)
        self.x, self.P, self.t = x, P, float(t)
        self.last_update = None

    def _mixed_predictions(self, t: float):
        return mixed_predictions(self.models, self.mu, np.array([f.x for f in self.filters]),
                                 np.array([f.P for f in self.filters]), float(t) - self.t)

    def predicted(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """The mixture predicted to ``t`` (>= the filter's time), without changing the filter."""
        if t < self.t:
            raise ValueError(f"cannot predict backwards from t={self.t} to t={t}")
        if t == self.t:
            return self.x, self.P
        xs, Ps, cbar = self._mixed_predictions(t)
        return kalman.gaussian_mixture(cbar, xs, Ps)

    def predict(self, t: float) -> None:
        if t < self.t:
            raise ValueError(f"cannot predict backwards from t={self.t} to t={t}")
        if t == self.t:
            return
        xs, Ps, cbar = self._mixed_predictions(t)
        for f, xj, Pj in zip(self.filters, xs, Ps):
            f.x, f.P, f.t = xj, Pj, float(t)
        self.mu = cbar
        self.x, self.P = kalman.gaussian_mixture(cbar, xs, Ps)
        self.t = float(t)
        self.last_update = None

    def update(self, model, z: np.ndarray) -> kalman.UpdateResult:
        """Update every model with ``z`` of ``model`` at the filter's time; returns the
        mixture's x, P and ν, S, NIS (module docstring) and ``K`` with ``K ν = x⁺ − x⁻``
        for the mixture's mean ν (a least-squares gain; what fusion needs is :attr:`KH`)."""
        prior = self.mu
        prior_xs, prior_Ps = self.model_states()
        results = [f.update(model, z) for f in self.filters]
        loglik = np.array([kalman.gaussian_loglikelihood(r.nu, r.S) for r in results])
        with np.errstate(divide="ignore"):
            ell = np.log(prior) + loglik
        w = np.exp(ell - ell.max())
        self.mu = w / w.sum()
        x_prior, self._prior_P = self.x, self.P
        self.x, self.P = kalman.gaussian_mixture(self.mu, np.array([f.x for f in self.filters]),
                                          np.array([f.P for f in self.filters]))
        self._post_P = self.P
        self.last_update = {"prior_mu": prior, "prior_xs": prior_xs, "prior_Ps": prior_Ps, "loglik": loglik}
        nu, S = kalman.gaussian_mixture(prior, np.array([r.nu for r in results]), np.array([r.S for r in results]))
        L_inv = kalman.inverse_cholesky_factor(S)
        v = L_inv @ nu
        K = np.outer(self.x - x_prior, L_inv.T @ v) / max(float(v @ v), np.finfo(float).tiny)
        return kalman.UpdateResult(self.x, self.P, nu, S, float(v @ v), K)

    def update_weighted(self, model, Z: np.ndarray, beta, beta0: float) -> WeightedUpdate:
        r"""The weighted (PDA) update at the filter's time with the plots ``Z`` of one
        scan, ``beta`` each and ``beta0`` for none (:mod:`fusion.pda`), per model.

        With ``Nᵢⱼ = N(νᵢⱼ; 0, Sⱼ)`` the likelihood of plot ``i`` under model ``j``
        (its own innovation and ``S``) and ``N̄ᵢ = Σⱼ c̄ⱼ Nᵢⱼ`` the mixture's::

            Λⱼ = β₀ + Σᵢ βᵢ Nᵢⱼ / N̄ᵢ,      μⱼ = c̄ⱼ Λⱼ                (Σⱼ μⱼ = 1)
            βᵢ|ⱼ = βᵢ Nᵢⱼ / (N̄ᵢ Λⱼ),       β₀|ⱼ = β₀ / Λⱼ

        and model ``j``'s filter takes the weighted update with ``βᵢ|ⱼ, β₀|ⱼ``. This is
        the joint posterior over (model, association) when ``β`` came from the IMM's
        own predicted likelihood of the plots, ``N̄ᵢ`` (IMM-PDA): the association
        probabilities ``βᵢ ∝ P_D N̄ᵢ / λ``, ``β₀ ∝ 1 − P_D P_G`` carry ``P_D`` and the
        clutter density ``λ``, and dividing by ``N̄ᵢ`` leaves what each model adds. From
        ``β`` computed on the moment-matched prediction it is an approximation. One
        sure plot (``β₁ = 1``) is :meth:`update`; ``β₀ = 1`` changes nothing. The
        track's Gaussian is the mixture; the returned ``νs``, ``S`` are the
        ``c̄``-weighted means of the models', ``K`` a least-squares gain as in
        :meth:`update`."""
        Z = np.atleast_2d(np.asarray(Z, dtype=float))
        beta = check_weights(beta, beta0, len(Z))
        prior = self.mu
        self._prior_P, x_prior = self.P, self.x
        stats = [f.innovations(model, Z) for f in self.filters]
        logn = np.array([[kalman.gaussian_loglikelihood(nu, S) for nu in nus] for nus, S in stats])  # (models, plots)
        with np.errstate(divide="ignore"):
            ell = np.log(prior)[:, None] + logn
        top = ell.max(axis=0)
        log_mix = top + np.log(np.exp(ell - top).sum(axis=0))  # log N̄ᵢ
        ratio = np.exp(logn - log_mix)  # Nᵢⱼ / N̄ᵢ
        lam = beta0 + ratio @ beta
        mu = prior * lam
        for f, r, l in zip(self.filters, ratio, lam):
            if l > 0.0:
                f.update_weighted(model, Z, beta * r / l, beta0 / l)
        self.mu = mu / mu.sum()
        self.x, self.P = kalman.gaussian_mixture(self.mu, np.array([f.x for f in self.filters]),
                                                 np.array([f.P for f in self.filters]))
        self._post_P = self.P
        nus = np.einsum("j,jia->ia", prior, np.array([n for n, _ in stats]))
        S = np.einsum("j,jab->ab", prior, np.array([S for _, S in stats]))
        nu = beta @ nus
        L_inv = kalman.inverse_cholesky_factor(S)
        v = L_inv @ nu
        K = np.outer(self.x - x_prior, L_inv.T @ v) / max(float(v @ v), np.finfo(float).tiny)
        return WeightedUpdate(self.x, self.P, nus, nu, S, K)

    @property
    def KH(self) -> np.ndarray:
        """``K·H = I − (P⁻⁻¹ P⁺)ᵀ`` of the last update (module docstring)."""
        Pm, Pp = self._prior_P, self._post_P
        try:
            return np.eye(Pm.shape[0]) - np.linalg.solve(Pm, Pp).T
        except np.linalg.LinAlgError:
            return np.eye(Pm.shape[0]) - (np.linalg.pinv(Pm) @ Pp).T
