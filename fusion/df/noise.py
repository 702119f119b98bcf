r"""Bearing-noise samplers (documents 001, 003). Every function draws from the numpy
Generator it is given, and nothing else.

* :func:`gaussian` — zero-mean Gaussian, one std per site (sites may differ: instrument,
  distance, frequency, propagation, ionosphere).
* :func:`contaminated` — the jamming mixture: each sample is, with probability ``p``,
  an outlier of std ``σ₂``, otherwise Gaussian with std ``σ₁``. Outliers are Laplacian
  (scale ``b = σ₂/√2``, so the std is ``σ₂``) or uniform on ``±√3·σ₂`` (std ``σ₂``; the
  maximum-entropy law under a peak-power constraint).
"""

from __future__ import annotations

import numpy as np

OUTLIER_LAWS = ("laplacian", "uniform")


def _shape(size) -> tuple[int, ...]:
    return (size,) if np.isscalar(size) else tuple(size)


def gaussian(rng: np.random.Generator, sigma, size) -> np.ndarray:
    """Gaussian noise of shape ``size``; ``sigma`` broadcasts against it (e.g. one std
    per site along the last axis)."""
    sigma = np.asarray(sigma, dtype=float)
    if np.any(sigma < 0) or not np.all(np.isfinite(sigma)):
        raise ValueError("gaussian: sigma must be finite and >= 0")
    return rng.standard_normal(_shape(size)) * sigma


def contaminated(rng: np.random.Generator, sigma1, sigma2, p: float, size, law: str = "laplacian",
                 return_mask: bool = False):
    """Gaussian(σ₁) noise where each sample is replaced with probability ``p`` by an
    outlier of std σ₂ (Laplacian or uniform). ``sigma1``/``sigma2`` broadcast against
    ``size``. With ``return_mask`` also returns the boolean outlier mask."""
    if law not in OUTLIER_LAWS:
        raise ValueError(f"unknown outlier law {law!r}; expected one of {OUTLIER_LAWS}")
    if not 0.0 <= p <= 1.0:
        raise ValueError(f"outlier probability p must be in [0, 1], got {p}")
    shape = _shape(size)
    s2 = np.broadcast_to(np.asarray(sigma2, dtype=float), shape)
    if np.any(s2 < 0) or not np.all(np.isfinite(s2)):
        raise ValueError("contaminated: sigma2 must be finite and >= 0")
    n = gaussian(rng, sigma1, shape)
    mask = rng.random(shape) < p
    if law == "laplacian":
        out = rng.laplace(0.0, 1.0, shape) * (s2 / np.sqrt(2.0))
    else:
        out = rng.uniform(-1.0, 1.0, shape) * (np.sqrt(3.0) * s2)
    n = np.where(mask, out, n)
    return (n, mask) if return_mask else n


def mixture_variance(sigma1: float, sigma2: float, p: float) -> float:
    """Variance of the contaminated noise: ``(1−p)σ₁² + pσ₂²``."""
    return (1.0 - p) * sigma1 ** 2 + p * sigma2 ** 2


def snr_db(sigma1: float, sigma2: float, p: float) -> float:
    """The IMM thesis's abscissa ``SNR = 10·log10(1/((1−p)σ₁² + pσ₂²))`` dB (rad⁻²).

    (Its code has ``2pσ₂²``; the text has ``pσ₂²``, which is the variance.)
    """
    return float(10.0 * np.log10(1.0 / mixture_variance(sigma1, sigma2, p)))
