r"""What a sensor at ``site`` sees of a point ``p`` (ENU): the measurement function h.

With ``d = p − site = (e, n, u)``::

    az    = atan2(e, n)                 compass azimuth, in [0, 2π)
    el    = atan2(u, √(e² + n²))        above the local horizontal
    range = ‖d‖                         slant range

(the patent's ``θ = atan(y/x)`` is the math angle; compass ``az = π/2 − θ``). A
measurement kind picks its components in its order (:mod:`fusion.measurement.kinds`);
:data:`VALUES` holds each component's value as a function of ``d`` and ``p``. This is
the emulators' own h, on Python floats, independent of the trackers' models.
"""

from __future__ import annotations

import math
from typing import Callable

import numpy as np

from fusion.angles import TWO_PI, wrap_2pi
from fusion.measurement.kinds import KINDS

from .spec import SensorSpec


def az_el_range(d: np.ndarray) -> dict[str, float]:
    """Compass azimuth, elevation and slant range of the ENU offset ``d``."""
    e, n, u = (float(c) for c in d)
    horizontal = math.hypot(e, n)
    return {"az": wrap_2pi(math.atan2(e, n)), "el": math.atan2(u, horizontal), "range": math.hypot(horizontal, u)}


#: component -> its noise-free value, ``value(d, p)`` of the offset ``d = p − site`` and the position ``p``
VALUES: dict[str, Callable[[np.ndarray, np.ndarray], float]] = {
    "az": lambda d, p: az_el_range(d)["az"],
    "el": lambda d, p: az_el_range(d)["el"],
    "range": lambda d, p: az_el_range(d)["range"],
    "east": lambda d, p: float(p[0]),
    "north": lambda d, p: float(p[1]),
    "up": lambda d, p: float(p[2]),
}


_SPHERICAL = frozenset(("az", "el", "range"))


def observe(kind: str, position: np.ndarray, site: np.ndarray) -> np.ndarray:
    """Noise-free measurement of kind ``kind`` of a target at ``position`` seen from ``site``."""
    p = np.asarray(position, dtype=float)
    d = p - np.asarray(site, dtype=float)
    names = KINDS[kind].names
    if set(names) <= _SPHERICAL:  # the geometry once, not once per component
        aer = az_el_range(d)
        return np.array([aer[c] for c in names])
    return np.array([VALUES[c](d, p) for c in names])


def in_coverage(sensor: SensorSpec, d: np.ndarray) -> bool:
    """Whether the point at offset ``d`` is inside the sensor's azimuth sector,
    elevation limits and instrumented range."""
    aer = az_el_range(d)
    first, width = sensor.fov_az
    in_sector = width >= TWO_PI or wrap_2pi(aer["az"] - first) <= width
    lo, hi = sensor.fov_el
    return in_sector and lo <= aer["el"] <= hi and aer["range"] <= sensor.max_range


def coverage_span(sensor: SensorSpec, component: str) -> tuple[float, float]:
    """``(origin, extent)`` of a component's values over the sensor's coverage (azimuth
    sector, elevation limits, instrumented range), what false alarms spread over; the
    extent is infinite for a component no coverage bounds."""
    first, width = sensor.fov_az
    lo, hi = sensor.fov_el
    spans = {"az": (first, width), "el": (lo, hi - lo), "range": (0.0, sensor.max_range)}
    return spans.get(component, (-math.inf, math.inf))


def finish_measurement(kind: str, z: np.ndarray) -> np.ndarray:
    """Put noisy values back in their components' intervals: a periodic one (azimuth)
    wrapped to [0, 2π), the others clipped (elevation to [−π/2, π/2], range at 0)."""
    out = np.array(z, dtype=float)
    for i, c in enumerate(KINDS[kind].components):
        out[i] = wrap_2pi(out[i]) if c.periodic else min(max(out[i], c.lo), c.hi)
    return out


def az_el_range_arrays(d: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`az_el_range` of many offsets ``d`` (N, 3) at once: (azimuth, elevation,
    slant range), each (N,)."""
    d = np.asarray(d, dtype=float)
    horizontal = np.hypot(d[:, 0], d[:, 1])
    return wrap_2pi(np.arctan2(d[:, 0], d[:, 1])), np.arctan2(d[:, 2], horizontal), np.hypot(horizontal, d[:, 2])


def coverage_mask(sensor: SensorSpec, d: np.ndarray, margin: float = 0.0) -> np.ndarray:
    """:func:`in_coverage` of many offsets ``d`` (N, 3) at once; ``margin`` widens every
    bound by that relative amount (and 1 m, 1 nrad), for a test that may include a few
    points outside but never leaves one inside out."""
    az, el, r = az_el_range_arrays(d)
    first, width = sensor.fov_az
    lo, hi = sensor.fov_el
    slack = margin * (1.0 + abs(hi) + abs(lo)) + (1e-9 if margin else 0.0)
    sector = np.full(len(az), True) if width >= TWO_PI else wrap_2pi(az - first + slack) <= width + 2.0 * slack
    return sector & (el >= lo - slack) & (el <= hi + slack) & (r <= sensor.max_range * (1.0 + margin) + (margin > 0))
