r"""Regions of a site: the areas regional fusers hold, and the geometry they need.

A :class:`Region` is a simple polygon in the horizontal plane of the origin's ENU frame
(metres, ``[e, n]`` vertices in order, either sense), a margin, and the sensors that
feed it. A point ``p`` is *in the region* if it lies inside the polygon, and *held* by
it if it lies inside or within ``margin`` of the polygon's boundary:

    held(p)  ⇔  inside(p)  or  min_k dist(p, edge_k) ≤ margin

``inside`` is the even-odd rule (a horizontal ray from ``p`` crosses the boundary an odd
number of times), and the distance to an edge ``a→b`` is that to its nearest point
``a + clip(((p − a)·(b − a)) / |b − a|², 0, 1) (b − a)``. Both are vectorised over many
points (one NumPy pass per edge), so a regional fuser checks all its tracks at once.
Altitude is not part of a region: an aircraft belongs to the regions above which it
flies.

Regions overlap by their margins (and by their polygons, if a site wants that): an
aircraft crossing from one region into the next is held by both for the width of the
overlap, which is where the system fuser hands its track over (:mod:`fusion.regional`).
:class:`Crossings` counts those passages from truth, for the evaluation.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping

import numpy as np

__all__ = ["Crossings", "Region", "box_polygon", "boundary_distance", "inside_polygon", "polygon_area"]


def box_polygon(e_min: float, n_min: float, e_max: float, n_max: float) -> np.ndarray:
    """The rectangle ``[e_min, e_max] × [n_min, n_max]`` as a counter-clockwise polygon."""
    return np.array([[e_min, n_min], [e_max, n_min], [e_max, n_max], [e_min, n_max]], dtype=float)


def polygon_area(polygon: np.ndarray) -> float:
    """The signed area (shoelace formula): positive counter-clockwise."""
    e, n = np.asarray(polygon, dtype=float).T
    return 0.5 * float(np.dot(e, np.roll(n, -1)) - np.dot(n, np.roll(e, -1)))


def _edges(polygon: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    a = np.asarray(polygon, dtype=float)
    return a, np.roll(a, -1, axis=0)


def inside_polygon(points: np.ndarray, polygon: np.ndarray) -> np.ndarray:
    """``(m,)`` whether each of ``points`` ``(m, ≥2)`` lies inside ``polygon`` (even-odd
    rule; a point exactly on the boundary may fall either way)."""
    p = np.atleast_2d(np.asarray(points, dtype=float))[:, :2]
    x, y = p[:, 0:1], p[:, 1:2]
    a, b = _edges(polygon)
    ya, yb = a[:, 1][None, :], b[:, 1][None, :]
    straddles = (ya > y) != (yb > y)
    with np.errstate(divide="ignore", invalid="ignore"):
        x_cross = a[:, 0][None, :] + (y - ya) * (b[:, 0] - a[:, 0])[None, :] / (yb - ya)
    return np.count_nonzero(straddles & (x < x_cross), axis=1) % 2 == 1


def boundary_distance(points: np.ndarray, polygon: np.ndarray) -> np.ndarray:
    """``(m,)`` each point's distance to the polygon's boundary (m)."""
    p = np.atleast_2d(np.asarray(points, dtype=float))[:, None, :2]
    a, b = _edges(polygon)
    ab = b - a
    u = np.clip(np.sum((p - a) * ab, axis=-1) / np.sum(ab * ab, axis=-1), 0.0, 1.0)
    nearest = a + u[..., None] * ab
    return np.min(np.linalg.norm(p - nearest, axis=-1), axis=1)


@dataclass(frozen=True, eq=False)
class Region:
    """One region (module docstring).

    Attributes:
        name: its name (a key chunk: ``fused/<name>``, track ids ``<name>.T3``).
        polygon: ``(k, 2)`` vertices ``[e, n]`` in the origin's ENU frame (m), k ≥ 3.
        margin: how far beyond the polygon its fuser still holds tracks (m).
        sensors: the ids of the sensors that feed it.
    """

    name: str
    polygon: np.ndarray
    margin: float
    sensors: tuple[str, ...]

    def __post_init__(self):
        polygon = np.asarray(self.polygon, dtype=float)
        if polygon.ndim != 2 or polygon.shape[0] < 3 or polygon.shape[1] != 2:
            raise ValueError(f"region {self.name!r}: a polygon needs at least 3 points [e, n]")
        if not np.all(np.isfinite(polygon)) or abs(polygon_area(polygon)) <= 0.0:
            raise ValueError(f"region {self.name!r}: the polygon is degenerate (no area)")
        if not self.margin >= 0.0:
            raise ValueError(f"region {self.name!r}: margin must be >= 0, got {self.margin}")
        if not self.sensors:
            raise ValueError(f"region {self.name!r}: no sensor feeds it")
        polygon.setflags(write=False)
        object.__setattr__(self, "polygon", polygon)
        object.__setattr__(self, "sensors", tuple(self.sensors))

    def inside(self, points: np.ndarray) -> np.ndarray:
        """``(m,)`` whether each point (``[e, n, ...]``) lies inside the polygon."""
        return inside_polygon(points, self.polygon)

    def holds(self, points: np.ndarray, beyond: float = 0.0) -> np.ndarray:
        """``(m,)`` whether each point lies inside the polygon or within the margin of it
        (and ``beyond`` more)."""
        p = np.atleast_2d(np.asarray(points, dtype=float))
        if p.shape[0] == 0:
            return np.zeros(0, dtype=bool)
        held = self.inside(p)
        if self.margin + beyond > 0.0 and not held.all():
            held[~held] = boundary_distance(p[~held], self.polygon) <= self.margin + beyond
        return held


class Crossings:
    """Counts aircraft passing from one region into another, from their true positions
    step by step: an aircraft is *in* the first region (in the order given) whose
    polygon contains it, and a crossing is a step where it is in a region other than
    the last one it was in (time outside every region does not break a passage)."""

    def __init__(self, regions: Mapping[str, Region] | list[Region]):
        self.regions = list(regions.values()) if isinstance(regions, Mapping) else list(regions)
        self.count = 0
        self._last: dict[str, str] = {}  # aircraft -> the last region it was in

    def add(self, truths: Mapping[str, np.ndarray]) -> int:
        """One step's true positions (id -> ``[e, n, ...]``); returns its crossings."""
        if not truths:
            return 0
        ids = list(truths)
        P = np.array([np.asarray(truths[i], dtype=float)[:2] for i in ids])
        where: list[str | None] = [None] * len(ids)
        for region in reversed(self.regions):  # the first region listed wins
            for k in np.flatnonzero(region.inside(P)):
                where[k] = region.name
        n = 0
        for i, r in zip(ids, where):
            if r is None:
                continue
            before = self._last.get(i)
            n += int(before is not None and before != r)
            self._last[i] = r
        self.count += n
        return n
