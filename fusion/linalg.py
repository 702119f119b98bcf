"""``numpy.linalg``'s Cholesky, inverse and solve without its per-call argument handling.

The filters factorise and invert many small matrices (a 9 × 9 covariance per guard, a
stack of three per fusion). ``numpy.linalg.cholesky``/``inv``/``solve`` spend 3–5 µs per
call checking, classifying and converting their arguments before the LAPACK kernel runs
for well under a microsecond. These functions call the very same kernels (numpy's
``_umath_linalg`` gufuncs, under the same floating-point error state), so the results
are bit-identical and the errors the same (``LinAlgError``), for float64 arrays of any
stack shape. Anything else (a numpy without those kernels) goes to ``numpy.linalg``.
"""

from __future__ import annotations

import numpy as np

try:  # numpy's own kernels behind numpy.linalg (numpy >= 1.26 and 2.x)
    from numpy.linalg import _umath_linalg as _kernels
except ImportError:  # pragma: no cover - a numpy without them
    _kernels = None
if not all(hasattr(_kernels, k) for k in ("cholesky_lo", "inv", "solve1")):  # a private module: names may change
    _kernels = None  # pragma: no cover

LinAlgError = np.linalg.LinAlgError

__all__ = ["cholesky", "inv", "solve"]


def _not_positive_definite(err, flag):
    raise LinAlgError("Matrix is not positive definite")


def _singular(err, flag):
    raise LinAlgError("Singular matrix")


def cholesky(a: np.ndarray) -> np.ndarray:
    """Lower Cholesky factor of a float64 (stack of) matrix: ``numpy.linalg.cholesky``."""
    if _kernels is None or not (type(a) is np.ndarray and a.dtype == np.float64 and a.ndim >= 2):
        return np.linalg.cholesky(a)
    with np.errstate(call=_not_positive_definite, invalid="call", over="ignore", divide="ignore", under="ignore"):
        return _kernels.cholesky_lo(a, signature="d->d")


def inv(a: np.ndarray) -> np.ndarray:
    """Inverse of a float64 (stack of) square matrix: ``numpy.linalg.inv``."""
    if _kernels is None or not (type(a) is np.ndarray and a.dtype == np.float64 and a.ndim >= 2
                                and a.shape[-1] == a.shape[-2]):
        return np.linalg.inv(a)
    with np.errstate(call=_singular, invalid="call", over="ignore", divide="ignore", under="ignore"):
        return _kernels.inv(a, signature="d->d")


def solve(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a⁻¹ b`` for one float64 square matrix and a vector: ``numpy.linalg.solve``
    (other shapes go to it)."""
    if _kernels is None or not (type(a) is np.ndarray and type(b) is np.ndarray and a.dtype == np.float64
                                and b.dtype == np.float64 and a.ndim == 2 and b.ndim == 1
                                and a.shape == (b.shape[0], b.shape[0])):
        return np.linalg.solve(a, b)
    with np.errstate(call=_singular, invalid="call", over="ignore", divide="ignore", under="ignore"):
        return _kernels.solve1(a, b, signature="dd->d")
