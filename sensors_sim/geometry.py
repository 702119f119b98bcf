r"""What a sensor at ``site`` sees of a point ``p`` (ENU): the measurement function h.

With ``d = p − site = (e, n, u)``::

    az    = atan2(e, n)                 compass azimuth, in [0, 2π)
    el    = atan2(u, √(e² + n²))        above the local horizontal
    range = ‖d‖                         slant range

(the patent's ``θ = atan(y/x)`` is the math angle; compass ``az = π/2 − θ``). A
measurement kind picks its components in the order of ``fusion.types.KIND_COMPONENTS``.
"""

from __future__ import annotations

import math

import numpy as np

from fusion.angles import TWO_PI, wrap_2pi
from fusion.types import KIND_COMPONENTS

from .spec import SensorSpec


def az_el_range(d: np.ndarray) -> dict[str, float]:
    """Compass azimuth, elevation and slant range of the ENU offset ``d``."""
    e, n, u = (float(c) for c in d)
    horizontal = math.hypot(e, n)
    return {"az": wrap_2pi(math.atan2(e, n)), "el": math.atan2(u, horizontal), "range": math.hypot(horizontal, u)}


def observe(kind: str, d: np.ndarray) -> np.ndarray:
    """Noise-free measurement of kind ``kind`` of the ENU offset ``d``."""
    aer = az_el_range(d)
    return np.array([aer[c] for c in KIND_COMPONENTS[kind]])


def in_coverage(sensor: SensorSpec, d: np.ndarray) -> bool:
    """Whether the point at offset ``d`` is inside the sensor's azimuth sector,
    elevation limits and instrumented range."""
    aer = az_el_range(d)
    first, width = sensor.fov_az
    in_sector = width >= TWO_PI or wrap_2pi(aer["az"] - first) <= width
    lo, hi = sensor.fov_el
    return in_sector and lo <= aer["el"] <= hi and aer["range"] <= sensor.max_range


def finish_measurement(kind: str, z: np.ndarray) -> np.ndarray:
    """Put noisy values back in their domains: azimuth wrapped to [0, 2π), elevation
    clipped to [−π/2, π/2], range clipped at 0."""
    out = np.array(z, dtype=float)
    for i, c in enumerate(KIND_COMPONENTS[kind]):
        if c == "az":
            out[i] = wrap_2pi(out[i])
        elif c == "el":
            out[i] = min(max(out[i], -math.pi / 2.0), math.pi / 2.0)
        else:
            out[i] = max(out[i], 0.0)
    return out
