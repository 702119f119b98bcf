"""fusion.tracking.associators: global nearest neighbour."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from fusion.tracking.associators import gnn


def brute_force_cost(d2, gate):
    """Least total cost over every partial matching: Σ assigned d² + G·(missed rows)."""
    n, m = d2.shape
    best = gate * n
    for k in range(1, min(n, m) + 1):
        for rows in itertools.combinations(range(n), k):
            for cols in itertools.permutations(range(m), k):
                c = d2[list(rows), list(cols)]
                if np.all(c <= gate):
                    best = min(best, float(c.sum()) + gate * (n - k))
    return best


@pytest.mark.parametrize("seed", range(40))
def test_gnn_is_the_least_cost_assignment(seed):
    rng = np.random.default_rng(seed)
    n, m = rng.integers(1, 5, size=2)
    d2 = rng.chisquare(2, size=(n, m)) * rng.choice([0.5, 3.0])
    gate = 9.21
    pairs = gnn(d2, gate)
    rows, cols = [p[0] for p in pairs], [p[1] for p in pairs]
    assert len(set(rows)) == len(rows) and len(set(cols)) == len(cols)
    assert all(d2[r, c] <= gate for r, c in pairs)  # never outside the gate
    cost = sum(d2[r, c] for r, c in pairs) + gate * (n - len(pairs))
    assert cost == pytest.approx(brute_force_cost(d2, gate), abs=1e-9)


def test_gnn_prefers_the_global_optimum_to_the_greedy_one():
    # greedy takes (0,0) = 1 and leaves row 1 with its gate; the optimum swaps
    d2 = np.array([[1.0, 2.0], [1.5, 20.0]])
    assert gnn(d2, gate=9.0) == [(0, 1), (1, 0)]
    assert gnn(np.empty((0, 3)), 9.0) == [] and gnn(np.full((2, 2), 50.0), 9.0) == []
