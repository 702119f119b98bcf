"""Angle conventions.

At the edges (wire, scenario files, recordings) azimuth is *compass* azimuth:
clockwise from north, in [0, 2π). Elevation is above the local horizontal, in
[-π/2, π/2]. The theses write bearings as *math* angles (counter-clockwise from +x =
east); :func:`compass_to_math` / :func:`math_to_compass` convert, and are used inside
``fusion/`` only. Every angle difference is wrapped to (-π, π].
"""

from __future__ import annotations

import numpy as np

TWO_PI = 2.0 * np.pi


# One angle (a float, np.float64 included) is wrapped with Python's float ``%``: the same
# fmod-based remainder as np.mod (bit for bit), without the cost of a 0-d array.
def wrap_pi(a):
    """Wrap an angle (or array of angles) to (-π, π]."""
    if isinstance(a, float):
        w = (a + np.pi) % TWO_PI - np.pi
        return np.pi if w == -np.pi else float(w)
    w = np.mod(np.asarray(a, dtype=float) + np.pi, TWO_PI) - np.pi
    # np.mod maps π to -π; (-π, π] keeps +π.
    w = np.where(w == -np.pi, np.pi, w)
    return float(w) if np.ndim(w) == 0 else w


def wrap_2pi(a):
    """Wrap an angle (or array of angles) to [0, 2π)."""
    if isinstance(a, float):
        w = a % TWO_PI
        return 0.0 if w >= TWO_PI else float(w)
    w = np.mod(np.asarray(a, dtype=float), TWO_PI)
    w = np.where(w >= TWO_PI, 0.0, w)  # np.mod can round up to 2π for tiny negatives
    return float(w) if np.ndim(w) == 0 else w


def compass_to_math(az):
    """Compass azimuth (cw from north) -> math angle (ccw from east), in (-π, π]."""
    return wrap_pi(np.pi / 2.0 - np.asarray(az, dtype=float))


def math_to_compass(beta):
    """Math angle (ccw from east) -> compass azimuth (cw from north), in [0, 2π)."""
    return wrap_2pi(np.pi / 2.0 - np.asarray(beta, dtype=float))
