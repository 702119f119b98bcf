"""Estimates in the session's ENU frame, as geographic shapes: points, confidence rings,
lines and the error figures map and TAK users expect.

The map view of a recording, the GeoJSON export and the Cursor-on-Target export all
draw the same things; this module is the one place that says how. Pure numpy and
pymap3d (through :class:`fusion.geodetic.LocalFrame`, in degrees), no I/O.

Confidence region: for a Gaussian position error with horizontal covariance ``P2``
(2×2), the ``p`` region is the ellipse ``d' P2⁻¹ d = k²`` with ``k² = χ²₂(p) = −2 ln(1 − p)``
(``p = 0.95``: ``k = 2.448``). With ``P2 = V diag(λ) V'`` its points are
``c + V diag(k √λ) (cos θ, sin θ)'``. The ring is built in ENU metres (exact around
its centre) and each vertex converted to WGS-84 (exact, ellipsoidal), then ordered
counter-clockwise in (lon, lat) and closed, as RFC 7946 asks of a polygon's exterior.

Error figures (Cursor-on-Target ``ce``/``le``, both 1σ, metres): ``ce`` is the semi-major
axis of the 1σ horizontal ellipse, ``√λmax(P2)`` — a circle of that radius holds the 1σ
ellipse, so it never understates the error in any direction; ``le`` is the vertical
std ``√P_uu``. A 2D emitter fix has no vertical estimate: its ``le`` is unknown.

A map-plane state ``[e, n]`` (an emitter fix) lies on the frame's plane ``u = 0``.
"""

from __future__ import annotations

import math

import numpy as np

from fusion.geodetic import LocalFrame

CONFIDENCE = 0.95  # the region drawn and exported around every estimate
RING_POINTS = 64  # vertices of a ring, before closing it
LINE_POINTS = 16  # vertices of a long straight ENU line, so it curves on the map as it should


def frame_of(origin: tuple[float, float, float]) -> LocalFrame:
    """The ENU frame of a scenario's or site's ``(lat °, lon °, alt m)`` origin."""
    lat, lon, alt = origin
    return LocalFrame(float(lat), float(lon), float(alt), deg=True)


def k_sigma(p: float = CONFIDENCE) -> float:
    """Mahalanobis radius of the ``p`` region of a 2D Gaussian: ``√(−2 ln(1 − p))``."""
    return math.sqrt(-2.0 * math.log1p(-p))


def enu3(x: np.ndarray) -> np.ndarray:
    """ENU position of a state: ``[e n]`` (emitter fix, ``u = 0``) or ``x[:3]``."""
    x = np.asarray(x, dtype=float)
    return np.array([x[0], x[1], 0.0]) if x.size in (2, 4) else x[:3].copy()


def lat_lon_alt(frame: LocalFrame, enu: np.ndarray) -> np.ndarray:
    """(…, 3) ENU metres -> (…, 3) ``[lat °, lon °, alt m]``."""
    lat, lon, alt = frame.to_geodetic(np.asarray(enu, dtype=float))
    return np.stack([lat, lon, alt], axis=-1)


def ring_enu(center: np.ndarray, P2: np.ndarray, p: float = CONFIDENCE, n: int = RING_POINTS) -> np.ndarray:
    """(n, 3) ENU vertices of the ``p`` ellipse of a 2×2 covariance around ``center`` (open)."""
    w, V = np.linalg.eigh(0.5 * (P2 + P2.T))
    th = np.linspace(0.0, 2.0 * math.pi, n, endpoint=False)
    axes = k_sigma(p) * np.sqrt(np.clip(w, 0.0, None))
    pts = (V @ (axes[:, None] * np.stack([np.cos(th), np.sin(th)]))).T
    c = np.asarray(center, dtype=float)
    return np.column_stack([pts + c[:2], np.full(n, c[2] if c.size > 2 else 0.0)])


def ring(frame: LocalFrame, center: np.ndarray, P2: np.ndarray, p: float = CONFIDENCE,
         n: int = RING_POINTS) -> np.ndarray:
    """(n + 1, 3) ``[lat, lon, alt]`` of the ``p`` ellipse: closed, counter-clockwise in (lon, lat)."""
    return closed_ring(lat_lon_alt(frame, ring_enu(center, P2, p, n)))


def closed_ring(g: np.ndarray) -> np.ndarray:
    """The vertices ``g`` (``[lat, lon, ...]`` rows) of a ring, closed and counter-clockwise in (lon, lat)."""
    lon, lat = g[:, 1], g[:, 0]
    if np.dot(lon, np.roll(lat, -1)) - np.dot(np.roll(lon, -1), lat) < 0:  # shoelace: twice the signed area
        g = g[::-1]
    return np.vstack([g, g[:1]])


def line(frame: LocalFrame, a: np.ndarray, b: np.ndarray, n: int = LINE_POINTS) -> np.ndarray:
    """(n, 3) ``[lat, lon, alt]`` along the straight ENU segment a -> b."""
    s = np.linspace(0.0, 1.0, n)[:, None]
    return lat_lon_alt(frame, (1.0 - s) * np.asarray(a, float) + s * np.asarray(b, float))


def horizontal_cov(P: np.ndarray) -> np.ndarray:
    return np.asarray(P, dtype=float)[:2, :2]


def ce_le(x: np.ndarray, P: np.ndarray) -> tuple[float, float | None]:
    """1σ circular and linear error (m) of a state's position (module docstring);
    ``le`` is None when the state has no height."""
    ce = math.sqrt(max(float(np.linalg.eigvalsh(horizontal_cov(P))[-1]), 0.0))
    le = None if np.asarray(x).size in (2, 4) else math.sqrt(max(float(P[2, 2]), 0.0))
    return ce, le


def position_std(x: np.ndarray, P: np.ndarray) -> float:
    """Root of the trace of the position covariance (m): the RMS position error it states."""
    d = 2 if np.asarray(x).size in (2, 4) else 3
    return math.sqrt(max(float(np.trace(np.asarray(P)[:d, :d])), 0.0))


def velocity(x: np.ndarray) -> np.ndarray | None:
    """ENU velocity of a state that has one (``[e n ve vn]`` or ``[p v (a)]``)."""
    x = np.asarray(x, dtype=float)
    if x.size == 4:
        return np.array([x[2], x[3], 0.0])
    if x.size >= 6:
        return x[3:6].copy()
    return None
