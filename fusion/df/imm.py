r"""Interacting Multiple Model estimator (Bar-Shalom), as used against jamming (document 003).

Two bearing EKFs (EKFT) with the same emitter model (:mod:`fusion.df.models`: the
theses' ``Φ = I``, ``+Q``, or constant velocity), model 1 with ``R₁ = σ₁²``
(clean) and model 2 with ``R₂ = σ₂²`` (outlier), and a Markov transition matrix
``Π[i, j] = P(model j now | model i before)``. One cycle per bearing:

1. predicted mode probabilities  ``c̄ⱼ = Σᵢ Π[i,j] μᵢ``
2. mixing  ``μᵢ|ⱼ = Π[i,j] μᵢ / c̄ⱼ``,  ``x₀ⱼ = Σᵢ μᵢ|ⱼ xᵢ``,
   ``P₀ⱼ = Σᵢ μᵢ|ⱼ (Pᵢ + (xᵢ − x₀ⱼ)(xᵢ − x₀ⱼ)ᵀ)``
3. model-matched updates from ``(x₀ⱼ, P₀ⱼ)``, likelihoods ``Λⱼ = N(νⱼ; 0, Sⱼ)``
4. mode update with the *predicted* probabilities, ``μⱼ ∝ Λⱼ c̄ⱼ`` (as Bar-Shalom and
   the thesis's code; its text multiplies by the previous ``μⱼ``)
5. output ``x = Σ μⱼ xⱼ``, ``P = Σ μⱼ (Pⱼ + (xⱼ − x)(xⱼ − x)ᵀ)``.

Step 4 is done in the log domain, ``μⱼ = exp(ℓⱼ − max ℓ)/Σ`` with
``ℓⱼ = log c̄ⱼ + log Λⱼ``: a wild outlier that underflows ``Λⱼ`` under every model would
make the linear-domain normalisation 0/0. Transition forms: ``"symmetric"``
``[[1−p, p], [p, 1−p]]`` (modes persist, as in the source documents) and ``"iid"``
``[[1−p, p], [1−p, p]]`` (each bearing an outlier independently; then ``c̄ = [1−p, p]``).
The estimator takes initial states, covariances and mode probabilities; choosing them
(``ipu`` or :mod:`fusion.df.init`) is :mod:`fusion.df.methods`' business.
"""

from __future__ import annotations

from typing import Callable, Sequence

import numpy as np

from ..kalman import UpdateResult, gaussian_loglikelihood, gaussian_mixture
from .filters import bearing_step
from .models import emitter_model

TRANSITIONS = ("symmetric", "iid")


def transition_matrix(p: float, form: str = "symmetric") -> np.ndarray:
    """Two-mode Markov matrix (rows: from, columns: to) for outlier probability ``p``."""
    if not 0.0 < p < 1.0:
        raise ValueError(f"IMM transition probability p must be in (0, 1), got {p}")
    if form == "symmetric":
        return np.array([[1.0 - p, p], [p, 1.0 - p]])
    if form == "iid":
        return np.array([[1.0 - p, p], [1.0 - p, p]])
    raise ValueError(f"unknown IMM transition form {form!r}; expected one of {TRANSITIONS}")


def log_likelihood(res: UpdateResult) -> float:
    """``log N(ν; 0, S)`` of an update: the model likelihood, in the log domain."""
    return gaussian_loglikelihood(res.nu, res.S)


class IMM:
    """Generic IMM over model-matched filter steps.

    Args:
        x0s, P0s: initial state and covariance of each model.
        Pi: transition matrix (rows sum to 1).
        mu0: initial mode probabilities.
    The filters are supplied per step as callables ``(x, P) -> UpdateResult`` (one
    predict + update each, see :meth:`step`), so the IMM itself knows no measurement.
    """

    def __init__(self, x0s: Sequence[np.ndarray], P0s: Sequence[np.ndarray], Pi: np.ndarray, mu0: Sequence[float]):
        self.xs = np.array(x0s, dtype=float)
        self.Ps = np.array(P0s, dtype=float)
        self.Pi = np.asarray(Pi, dtype=float)
        self.mu = np.asarray(mu0, dtype=float)
        m = len(self.mu)
        if self.xs.shape[0] != m or self.Ps.shape[0] != m or self.Pi.shape != (m, m):
            raise ValueError("IMM: models, covariances, transition matrix and mode probabilities disagree in size")
        if np.any(self.mu <= 0) or abs(self.mu.sum() - 1.0) > 1e-12:
            raise ValueError(f"IMM: initial mode probabilities must be > 0 and sum to 1, got {self.mu}")
        if np.any(self.Pi < 0) or np.any(np.abs(self.Pi.sum(axis=1) - 1.0) > 1e-12):
            raise ValueError("IMM: transition matrix rows must be probabilities summing to 1")
        self.x, self.P = gaussian_mixture(self.mu, self.xs, self.Ps)

    def step(self, model_steps: Sequence[Callable[[np.ndarray, np.ndarray], UpdateResult]]) -> list[UpdateResult]:
        """One IMM cycle; returns the model-matched update results."""
        cbar = self.mu @ self.Pi
        mix = self.Pi * self.mu[:, None] / cbar[None, :]  # mix[i, j] = μ_{i|j}
        results = []
        for j, f in enumerate(model_steps):
            x0, P0 = gaussian_mixture(mix[:, j], self.xs, self.Ps)
            results.append(f(x0, P0))
        logw = np.log(cbar) + np.array([log_likelihood(r) for r in results])
        w = np.exp(logw - logw.max())
        self.mu = w / w.sum()
        self.xs = np.array([r.x for r in results])
        self.Ps = np.array([r.P for r in results])
        self.x, self.P = gaussian_mixture(self.mu, self.xs, self.Ps)
        return results


class BearingIMM(IMM):
    """IMM of two (or more) EKFT bearing filters differing only in bearing noise.

    ``model``: the emitter model both filters predict with (or a 2×2 ``Q``: the static
    emitter). ``step(site, beta, sigmas, dt)`` runs one cycle ``dt`` seconds after the
    last, model ``j`` assuming std ``sigmas[j]``; the mixing is done at the previous
    time and each mixed prior predicted over ``dt`` (the models share ``F``, so mixing
    before or after the prediction is the same).
    """

    def __init__(self, x0s, P0s, model, Pi: np.ndarray, mu0: Sequence[float]):
        super().__init__(x0s, P0s, Pi, mu0)
        self.model = emitter_model(model)

    def step(self, site: np.ndarray, beta: float, sigmas: Sequence[float],  # type: ignore[override]
             dt: float = 0.0) -> list[UpdateResult]:
        return super().step([
            (lambda x, P, s=s: bearing_step(x, P, site, beta, s, self.model, "EKFT", dt)) for s in sigmas
        ])
