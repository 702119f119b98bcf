"""fusion/linalg.py: numpy.linalg's Cholesky, inverse and solve without its argument
handling give the very same bits and the same errors; other inputs go to numpy.linalg."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from fusion import linalg


def _spd(rng, n: int, *stack: int) -> np.ndarray:
    A = rng.normal(size=(*stack, n, n))
    return A @ np.swapaxes(A, -1, -2) + n * np.eye(n)


@pytest.mark.parametrize("n", [1, 2, 3, 6, 9, 12])
def test_bit_identical_to_numpy_linalg(n):
    rng = np.random.default_rng(n)
    for _ in range(50):
        S, Ss, b = _spd(rng, n), _spd(rng, n, 3), rng.normal(size=n)
        assert np.array_equal(linalg.cholesky(S), np.linalg.cholesky(S))
        assert np.array_equal(linalg.cholesky(Ss), np.linalg.cholesky(Ss))
        assert np.array_equal(linalg.inv(S), np.linalg.inv(S))
        assert np.array_equal(linalg.inv(Ss), np.linalg.inv(Ss))
        assert np.array_equal(linalg.solve(S, b), np.linalg.solve(S, b))


def test_the_same_errors_and_no_warning():
    not_pd = np.diag([1.0, -1.0, 2.0])
    singular = np.array([[1.0, 2.0], [2.0, 4.0]])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(np.linalg.LinAlgError):
            linalg.cholesky(not_pd)
        with pytest.raises(np.linalg.LinAlgError):
            linalg.cholesky(np.stack([np.eye(3), not_pd]))
        with pytest.raises(np.linalg.LinAlgError):
            linalg.inv(singular)
        with pytest.raises(np.linalg.LinAlgError):
            linalg.solve(singular, np.ones(2))


def test_other_inputs_go_to_numpy_linalg():
    """Lists, integers, a matrix right-hand side: numpy.linalg's own handling and results."""
    A = [[4, 2], [2, 3]]
    assert np.array_equal(linalg.cholesky(A), np.linalg.cholesky(A))
    assert np.array_equal(linalg.inv(np.array(A)), np.linalg.inv(np.array(A)))
    B = np.array([[1.0, 2.0], [3.0, 4.0]])
    assert np.array_equal(linalg.solve(np.array(A, float), B), np.linalg.solve(np.array(A, float), B))
    with pytest.raises(np.linalg.LinAlgError):
        linalg.inv(np.ones((2, 3)))
