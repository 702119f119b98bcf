r"""Bearings-only emitter model (documents 000–003).

Geometry is the horizontal plane of the local ENU frame, in metres. The emitter is
stationary, state ``X = [x_e, y_e]``. Inside ``fusion.df`` a bearing ``β`` is a *math*
angle (counter-clockwise from east, radians), as in the theses::

    β = h(X) = atan2(y_e − y_k, x_e − x_k)

with ``(x_k, y_k)`` the observer's position at the time of the bearing (it moves for an
airborne DF). Measurements arrive as :class:`fusion.types.Measurement` of kind
``"bearing"`` whose ``z[0]`` is a *compass* azimuth; :func:`bearing_of` converts at the
edge. The site's height is ignored: a DF azimuth is a horizontal-plane angle.

Model (as in the theses): ``Φ = I₂``, ``Q = diag(q11, q22)`` added once per bearing
(not per second), ``R = σ²``.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from ..angles import compass_to_math, math_to_compass
from ..types import Measurement

#: The theses' bearing noise, radians (≈1°).
THESIS_SIGMA = 0.0175
#: The theses' ``q22 = 0.025² km²`` in m² ("cannot be zero"; added per bearing).
THESIS_Q22 = 625.0


def bearing(p, site):
    """Math bearing ``atan2(Δy, Δx)`` from ``site`` to ``p`` (broadcasts over leading axes)."""
    d = np.asarray(p, dtype=float)[..., :2] - np.asarray(site, dtype=float)[..., :2]
    return np.arctan2(d[..., 1], d[..., 0])


def bearing_jacobian(p, site):
    """``∂β/∂p = [−Δy, Δx] / r²`` (shape ``(..., 2)``).

    This is the source documents' ``[−u/((1+u²)Δx), 1/((1+u²)Δx)]`` with ``u = Δy/Δx`` multiplied
    out, so it has no singularity at ``Δx = 0``; only ``r = 0`` (emitter on the site) is
    singular, and that raises.
    """
    d = np.asarray(p, dtype=float)[..., :2] - np.asarray(site, dtype=float)[..., :2]
    r2 = np.sum(d * d, axis=-1)
    if np.any(r2 <= 0.0):
        raise ValueError("bearing_jacobian: the position coincides with the observer site")
    return np.stack([-d[..., 1], d[..., 0]], axis=-1) / r2[..., None]


def emitter_Q(q22: float, q11: float = 0.0) -> np.ndarray:
    """Process noise ``diag(q11, q22)`` in m², added before every bearing update."""
    if q11 < 0.0 or q22 < 0.0:
        raise ValueError(f"emitter_Q: q11={q11} and q22={q22} must be >= 0")
    return np.diag([float(q11), float(q22)])


def bearing_of(m: Measurement) -> tuple[np.ndarray, float]:
    """``(site_xy, β)`` of a bearing measurement: the edge conversion compass → math.

    Raises ValueError for another kind, non-finite values or a malformed site.
    """
    if m.kind != "bearing":
        raise ValueError(f"expected a 'bearing' measurement, got kind {m.kind!r} from {m.sensor!r}")
    z = np.atleast_1d(np.asarray(m.z, dtype=float))
    site = np.atleast_1d(np.asarray(m.site, dtype=float))
    if z.shape != (1,) or not np.isfinite(z[0]):
        raise ValueError(f"bearing from {m.sensor!r} at t={m.t}: z must be one finite azimuth, got {m.z!r}")
    if site.shape not in ((2,), (3,)) or not np.all(np.isfinite(site)):
        raise ValueError(f"bearing from {m.sensor!r} at t={m.t}: site must be a finite 2- or 3-vector, got {m.site!r}")
    return site[:2].copy(), float(compass_to_math(z[0]))


def stated_sigma(m: Measurement) -> float:
    """The sensor's stated bearing standard deviation (radians); must be finite and > 0."""
    s = np.atleast_1d(np.asarray(m.std, dtype=float))
    if s.shape != (1,) or not np.isfinite(s[0]) or s[0] <= 0.0:
        raise ValueError(f"bearing from {m.sensor!r} at t={m.t}: std must be one positive number, got {m.std!r}")
    return float(s[0])


def bearing_measurements(
    t: Sequence[float] | np.ndarray,
    sensors: Sequence[str],
    sites: np.ndarray,
    beta: np.ndarray,
    sigma: float | Sequence[float],
) -> list[Measurement]:
    """Build a bearing stream in ``(t, sensor, seq)`` order from math bearings.

    ``sites`` has shape ``(T, S, 2|3)`` (site of sensor ``s`` at epoch ``k``) or
    ``(S, 2|3)`` for fixed stations; ``beta`` has shape ``(T, S)``; ``sigma`` is the
    stated std, one per sensor or one for all. ``seq`` counts epochs. Used to feed
    synthetic bearings (tests, in-process studies) through the streaming methods.
    """
    t = np.asarray(t, dtype=float)
    beta = np.asarray(beta, dtype=float)
    T, S = beta.shape
    sites = np.asarray(sites, dtype=float)
    if sites.ndim == 2:
        sites = np.broadcast_to(sites, (T,) + sites.shape)
    if t.shape != (T,) or len(sensors) != S or sites.shape[:2] != (T, S):
        raise ValueError("bearing_measurements: t (T,), sensors (S), sites (T,S,·) and beta (T,S) disagree")
    sig = np.broadcast_to(np.asarray(sigma, dtype=float), (S,))
    az = math_to_compass(beta)
    order = np.argsort(np.asarray(sensors, dtype=object), kind="stable")
    site3 = np.zeros((T, S, 3))
    site3[..., : sites.shape[2]] = sites
    return [
        Measurement(t=float(t[k]), sensor=sensors[s], kind="bearing", z=np.array([az[k, s]]),
                    std=np.array([sig[s]]), site=site3[k, s].copy(), seq=k)
        for k in range(T)
        for s in order
    ]
