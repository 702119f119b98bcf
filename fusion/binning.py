"""A series in bounded memory: at most ``max_points`` points however many samples.

An open-ended run (a live session scored for days) cannot keep a point per output
time. :class:`BinnedSeries` keeps points of ``bin`` consecutive samples each, ``bin`` a
power of two: while the points fit, one sample a point; when one more point would make
``max_points + 1``, neighbours are merged in pairs (``2i`` with ``2i + 1``, the last alone
when odd) and ``bin`` doubles. A point is ``[t, n, value]``: the time of its last sample,
how many samples it holds, and what they sum to. The value is the caller's (a running sum
of its own kind): ``new()`` makes an empty one, ``merge(a, b)`` adds ``b`` into ``a``.

Merging adds the later point into the earlier, so a point's value is its samples summed
in time order, pairwise over the doublings: the same sums whoever uses it.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from typing import Generic, TypeVar

V = TypeVar("V")


class BinnedSeries(Generic[V]):
    """At most ``max_points`` points ``[t, n, value]`` of ``bin`` samples each (the last
    point may hold fewer)."""

    def __init__(self, max_points: int, new: Callable[[], V], merge: Callable[[V, V], None]):
        self.max_points = max_points
        self.new, self.merge = new, merge
        self.points: list[list] = []
        self.bin = 1

    def sample(self, t: float) -> V:
        """A new sample at time ``t`` (after the last one): the value to add it into."""
        pts = self.points
        if pts and pts[-1][1] < self.bin:
            pts[-1][0] = t
            pts[-1][1] += 1
            return pts[-1][2]
        pts.append([t, 1, self.new()])
        if len(pts) > self.max_points:
            merged = []
            for i in range(0, len(pts), 2):
                a = pts[i]
                for b in pts[i + 1:i + 2]:
                    a[0], a[1] = b[0], a[1] + b[1]
                    self.merge(a[2], b[2])
                merged.append(a)
            self.points = merged
            self.bin *= 2
        return self.points[-1][2]

    @property
    def last_t(self) -> float | None:
        return self.points[-1][0] if self.points else None

    @property
    def last(self) -> V:
        """The value of the latest point (there must be one)."""
        return self.points[-1][2]

    def __iter__(self) -> Iterator[list]:
        return iter(self.points)

    def __len__(self) -> int:
        return len(self.points)
