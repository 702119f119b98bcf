"""fusion.binning: a bounded series holds consecutive blocks of a power-of-two size,
the smallest that fits, each summing exactly its samples."""

from __future__ import annotations

import pytest

from fusion.binning import BinnedSeries


@pytest.mark.parametrize("max_points", [1, 2, 5, 8, 9])
@pytest.mark.parametrize("n", [1, 7, 8, 9, 100, 257])
def test_points_are_the_blocks_of_the_smallest_power_of_two_that_fits(n, max_points):
    s: BinnedSeries[list] = BinnedSeries(max_points, lambda: [0], lambda a, b: a.__setitem__(0, a[0] + b[0]))
    for k in range(n):
        s.sample(10.0 + k)[0] += k * k
    k = 1
    while -(-n // k) > max_points:  # the least power of two whose ⌈n / k⌉ blocks fit
        k *= 2
    assert s.bin == k and len(s) == -(-n // k) <= max_points
    blocks = [range(i, min(i + k, n)) for i in range(0, n, k)]
    assert [p[0] for p in s] == [10.0 + b[-1] for b in blocks]  # stamped with its last sample
    assert [p[1] for p in s] == [len(b) for b in blocks]
    assert [p[2][0] for p in s] == [sum(j * j for j in b) for b in blocks]
    assert s.last_t == 10.0 + n - 1
