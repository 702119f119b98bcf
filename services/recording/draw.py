"""Geometry and styling for the recorder: pure numpy, no Rerun and no I/O.

Conventions are the project's: ENU metres, compass azimuth (clockwise from north),
elevation above the horizontal. State layouts (docs/design.md, Conventions): a 3D target is
``[px py pz vx vy vz (ax ay az)]``, an emitter fix ``[px py]``. The recorder also meets
a few layouts other processes may publish as local tracks; :func:`state_layout` names
what it knows how to draw (what is scored, and how: :mod:`services.scoring`).
"""

from __future__ import annotations

import math
import zlib

import numpy as np

N_SIGMA = 3.0
MIN_RAY_M = 1_000.0
MAX_RAY_M = 2_000_000.0


def state_layout(n: int) -> str | None:
    """``"3d"`` (position in x[:3]), ``"2d"`` (map-plane position in x[:2]), ``"bearing"``
    (a smoothed azimuth, x[0]) or None (nothing drawable)."""
    if n == 1:
        return "bearing"
    if n in (2, 4):
        return "2d"
    if n == 3 or n >= 6:
        return "3d"
    return None


def position3(x: np.ndarray) -> np.ndarray:
    """ENU position of a state; map-plane states sit at z = 0."""
    x = np.asarray(x, dtype=float)
    if state_layout(x.size) == "2d":
        return np.array([x[0], x[1], 0.0])
    return x[:3].copy()


def unit(az: float, el: float = 0.0) -> np.ndarray:
    """ENU unit vector of a compass azimuth and an elevation."""
    return np.array([math.sin(az) * math.cos(el), math.cos(az) * math.cos(el), math.sin(el)])


def ellipsoid(P: np.ndarray, n_sigma: float = N_SIGMA) -> tuple[np.ndarray, np.ndarray]:
    """Half-sizes and rotation quaternion (x, y, z, w) of the n-σ ellipsoid of a 3×3 covariance."""
    w, V = np.linalg.eigh(0.5 * (P + P.T))
    if np.linalg.det(V) < 0:
        V[:, 0] = -V[:, 0]
    half = n_sigma * np.sqrt(np.clip(w, 0.0, None))
    return half, quaternion(V)


def quaternion(R: np.ndarray) -> np.ndarray:
    """Unit quaternion (x, y, z, w) of a rotation matrix, by Shepperd's method (the largest
    of the four candidate terms is the divisor, so it stays accurate for any rotation).
    What ``scipy``'s ``Rotation.from_matrix(R).as_quat()`` gives, up to sign, in a tenth of
    the time: the recorder draws an ellipsoid per fused track."""
    (a, b, c), (d, e, f), (g, h, i) = R.tolist()
    tr = a + e + i
    if tr >= a and tr >= e and tr >= i:
        w = 0.5 * math.sqrt(1.0 + tr)
        q = ((h - f) / (4 * w), (c - g) / (4 * w), (d - b) / (4 * w), w)
    elif a >= e and a >= i:
        x = 0.5 * math.sqrt(1.0 + a - e - i)
        q = (x, (b + d) / (4 * x), (c + g) / (4 * x), (h - f) / (4 * x))
    elif e >= i:
        y = 0.5 * math.sqrt(1.0 - a + e - i)
        q = ((b + d) / (4 * y), y, (f + h) / (4 * y), (c - g) / (4 * y))
    else:
        z = 0.5 * math.sqrt(1.0 - a - e + i)
        q = ((c + g) / (4 * z), (f + h) / (4 * z), z, (d - b) / (4 * z))
    q = np.array(q)
    return q / np.linalg.norm(q)


def ellipse(center: np.ndarray, P2: np.ndarray, n_sigma: float = N_SIGMA, n: int = 64,
            z: float = 0.0) -> np.ndarray:
    """Closed line strip ((n+1)×3) of the n-σ ellipse of a 2×2 covariance, at height z."""
    w, V = np.linalg.eigh(0.5 * (P2 + P2.T))
    th = np.linspace(0.0, 2.0 * math.pi, n + 1)
    circle = np.stack([np.cos(th), np.sin(th)])
    pts = (V @ (n_sigma * np.sqrt(np.clip(w, 0.0, None))[:, None] * circle)).T + np.asarray(center[:2], float)
    return np.column_stack([pts, np.full(n + 1, z)])


def vertical_arc(site: np.ndarray, az: float, rng: float, n: int = 12) -> np.ndarray:
    """Where a 2D radar's (azimuth, slant range) report may be: elevations 0..90°."""
    return np.array([site + rng * unit(az, el) for el in np.linspace(0.0, math.pi / 2, n + 1)])


def ray_hit(p1: np.ndarray, u1: np.ndarray, p2: np.ndarray, u2: np.ndarray, min_sin: float = 1e-3) -> float | None:
    """Distance along ray 1 (map plane) to where it crosses ray 2, if both point at it."""
    d = np.asarray(p2[:2], float) - np.asarray(p1[:2], float)
    cross = u1[0] * u2[1] - u1[1] * u2[0]
    if abs(cross) < min_sin or np.hypot(*d) < 100.0:
        return None
    s1 = (d[0] * u2[1] - d[1] * u2[0]) / cross
    s2 = (d[0] * u1[1] - d[1] * u1[0]) / cross
    return float(s1) if s1 > 0 and s2 > 0 else None


def clamp_ray(length: float) -> float:
    return float(min(max(length, MIN_RAY_M), MAX_RAY_M))


# -- colours -----------------------------------------------------------------------------------

PALETTE = [(31, 119, 180), (255, 127, 14), (44, 160, 44), (214, 39, 40), (148, 103, 189), (140, 86, 75),
           (227, 119, 194), (127, 127, 127), (188, 189, 34), (23, 190, 207)]
TRUTH_COLOR = (0, 170, 0)
CENTRE_COLOR = (255, 140, 0)
FEEDBACK_COLOR = (160, 60, 220)
JAM_ON_COLOR = (230, 0, 0)
JAM_OFF_COLOR = (130, 130, 130)
BOUND_COLOR = (150, 150, 150)


def color_of(name: str) -> tuple[int, int, int]:
    """A stable colour per sensor / node id (the same in every recording)."""
    return PALETTE[zlib.crc32(name.encode()) % len(PALETTE)]


def dim(c: tuple[int, int, int], f: float = 0.55) -> tuple[int, int, int]:
    return tuple(int(255 - (255 - v) * f) for v in c)  # type: ignore[return-value]


PATH_MAX = 600  # points kept in a drawn path (truth, track, airborne site): 5 min at TRAIL_STEP_S


# A truth or track path gets a point (and a row) at most this often in scenario time, so
# the bytes it sends do not grow with the update rate (module docstring, "Paths").
TRAIL_STEP_S = 0.5


class Trail:
    """A drawn path: the latest ``PATH_MAX`` points.

    :meth:`add` returns the path so far as a view that later points never change: rows
    hold it until they are sent. Points are appended after every earlier view's end, and
    a full buffer is replaced, not overwritten. :meth:`mapped` gives the same path through
    a conversion (the map's latitude and longitude), each point converted once: a path
    redrawn with every point it gains costs one conversion a point, not one a point per row.
    """

    def __init__(self) -> None:
        self._buf = np.empty((2 * PATH_MAX, 3))
        self._start = self._end = 0
        self._mapped: np.ndarray | None = None  # the conversion of _buf[_mapped_to - n:_mapped_to]
        self._mapped_from = self._mapped_to = 0
        self.t = -math.inf  # time of the latest point, for callers that space them out

    @property
    def points(self) -> np.ndarray:
        return self._buf[self._start:self._end]

    def add(self, pos: np.ndarray) -> np.ndarray:
        if self._end == len(self._buf):
            lo = self._end - PATH_MAX + 1
            kept = self._buf[lo:self._end]
            self._buf = np.empty_like(self._buf)
            self._buf[:len(kept)] = kept
            if self._mapped is not None:  # the converted points kept move with them
                a, b = max(self._mapped_from, lo), self._mapped_to
                mapped = np.empty_like(self._mapped)
                if b > a:
                    mapped[a - lo:b - lo] = self._mapped[a:b]
                self._mapped = mapped
                self._mapped_from, self._mapped_to = (a - lo, b - lo) if b > a else (0, 0)
            self._start, self._end = 0, len(kept)
        self._buf[self._end] = pos
        self._end += 1
        self._start = max(self._start, self._end - PATH_MAX)
        return self._buf[self._start:self._end]

    def mapped(self, convert) -> np.ndarray:
        """The path so far through ``convert`` (``(n, 3)`` points to ``(n, k)``, point by
        point), a view that later points never change, like :meth:`add`'s. Only the points
        not converted yet go through ``convert``; ``convert`` must be the same every call."""
        if not self._mapped_from <= self._start <= self._mapped_to:
            self._mapped_from = self._mapped_to = self._start
        if self._mapped_to < self._end:
            new = np.asarray(convert(self._buf[self._mapped_to:self._end]), dtype=float)
            if self._mapped is None:
                self._mapped = np.empty((len(self._buf), new.shape[1]))
            self._mapped[self._mapped_to:self._end] = new
            self._mapped_to = self._end
        if self._mapped is None:
            return np.empty((0, 0))
        return self._mapped[self._start:self._end]
