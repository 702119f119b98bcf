"""WGS-84 geodetic coordinates ↔ the local ENU frame of a scenario.

The frame is east-north-up, tangent to the WGS-84 ellipsoid at the scenario's origin
``(lat0, lon0, alt0)``. Conversions are pymap3d's (exact ellipsoidal formulas, no
flat-earth shortcut). Latitude/longitude are radians by default (SI, like the rest of
``fusion``); pass ``deg=True`` for degrees. Altitudes are metres above the ellipsoid.
Inputs broadcast (scalars or arrays).

The ENU axes at a point turn with it: ``enu_rotation(φ, λ)`` has for rows the east,
north and up unit vectors in ECEF::

    [ −sin λ          cos λ          0     ]
    [ −sin φ cos λ   −sin φ sin λ    cos φ ]
    [  cos φ cos λ    cos φ sin λ    sin φ ]

so a displacement (or a covariance) stated in the ENU axes at a point ``p`` is, in the
frame's axes at the origin ``o``, ``T d`` (``T C Tᵀ``) with ``T = R(o) R(p)ᵀ``
(:meth:`LocalFrame.rotation_from`). ENU and ECEF are affine in each other, so this is
exact for any displacement, not a linearisation.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pymap3d

WGS84 = pymap3d.Ellipsoid.from_name("wgs84")


def _check_latitude(lat, deg: bool, what: str) -> None:
    lim = 90.0 if deg else np.pi / 2
    lat = np.asarray(lat, dtype=float)
    if not np.all(np.isfinite(lat)) or np.any(np.abs(lat) > lim):
        raise ValueError(f"{what} must be finite and within ±{lim} ({'degrees' if deg else 'radians'})")


def geodetic_to_enu(lat, lon, alt, lat0, lon0, alt0, *, deg: bool = False):
    """``(e, n, u)`` in metres of geodetic points in the ENU frame at ``(lat0, lon0, alt0)``."""
    _check_latitude(lat, deg, "lat")
    _check_latitude(lat0, deg, "lat0")
    e, n, u = pymap3d.geodetic2enu(lat, lon, alt, lat0, lon0, alt0, ell=WGS84, deg=deg)
    return np.asarray(e, dtype=float), np.asarray(n, dtype=float), np.asarray(u, dtype=float)


def enu_to_geodetic(e, n, u, lat0, lon0, alt0, *, deg: bool = False):
    """``(lat, lon, alt)`` of ENU points (m) in the frame at ``(lat0, lon0, alt0)``."""
    _check_latitude(lat0, deg, "lat0")
    lat, lon, alt = pymap3d.enu2geodetic(e, n, u, lat0, lon0, alt0, ell=WGS84, deg=deg)
    return np.asarray(lat, dtype=float), np.asarray(lon, dtype=float), np.asarray(alt, dtype=float)


def enu_rotation(lat, lon, *, deg: bool = False) -> np.ndarray:
    """The 3 × 3 rotation from ECEF axes to the ENU axes at ``(lat, lon)`` (module docstring)."""
    _check_latitude(lat, deg, "lat")
    phi, lam = (np.radians(lat), np.radians(lon)) if deg else (float(lat), float(lon))
    sp, cp, sl, cl = np.sin(phi), np.cos(phi), np.sin(lam), np.cos(lam)
    return np.array([[-sl, cl, 0.0], [-sp * cl, -sp * sl, cp], [cp * cl, cp * sl, sp]])


@dataclass(frozen=True)
class LocalFrame:
    """A scenario's ENU frame: origin latitude, longitude (radians unless ``deg``) and
    altitude (m). ``to_enu``/``to_geodetic`` use the same angle unit as the origin."""

    lat0: float
    lon0: float
    alt0: float = 0.0
    deg: bool = False

    def __post_init__(self):
        _check_latitude(self.lat0, self.deg, "origin latitude")

    def to_enu(self, lat, lon, alt) -> np.ndarray:
        """ENU position(s), shape ``(..., 3)``."""
        return np.stack(geodetic_to_enu(lat, lon, alt, self.lat0, self.lon0, self.alt0, deg=self.deg), axis=-1)

    def rotation_from(self, lat, lon) -> np.ndarray:
        """``T = R(origin) R(lat, lon)ᵀ``: a vector in the ENU axes at ``(lat, lon)`` (this
        frame's angle unit) in this frame's axes (module docstring)."""
        return enu_rotation(self.lat0, self.lon0, deg=self.deg) @ enu_rotation(lat, lon, deg=self.deg).T

    def to_geodetic(self, enu) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        enu = np.asarray(enu, dtype=float)
        return enu_to_geodetic(enu[..., 0], enu[..., 1], enu[..., 2], self.lat0, self.lon0, self.alt0, deg=self.deg)
