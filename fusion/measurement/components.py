r"""The components of a measurement vector, one frozen record each.

A measurement kind (:mod:`.kinds`) is an ordered tuple of components, and ``Measurement.z``
holds their values in that order. What the rest of the system asks of a component is
here and nowhere else:

* ``name`` — the row's name, and the field that carries its value on the wire;
* ``unit`` — ``"rad"`` or ``"m"`` (SI; edges that show degrees convert);
* ``angle`` — whether differences wrap to (−π, π] (residuals, circular means);
* ``std_field`` — the wire field of its stated standard deviation;
* ``lo``, ``hi``, ``lo_open``, ``hi_open`` — the interval a reported value lies in
  (the wire refuses others); ``periodic``: an angle whose values wrap into [0, 2π)
  instead of being clipped (azimuth).

Azimuth is compass azimuth (clockwise from north) in [0, 2π), elevation above the local
horizontal in [−π/2, π/2], range the slant range in metres (> 0); :mod:`fusion.angles`.
``east``, ``north``, ``up`` are a reported position in the origin's ENU frame (metres).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

TWO_PI = 2.0 * math.pi


@dataclass(frozen=True)
class Component:
    """One component of a measurement vector (module docstring)."""

    name: str
    unit: str
    angle: bool
    std_field: str
    lo: float = -math.inf
    hi: float = math.inf
    lo_open: bool = False
    hi_open: bool = False
    periodic: bool = False

    def __post_init__(self):
        if self.unit not in ("rad", "m"):
            raise ValueError(f"component {self.name!r}: unit must be 'rad' or 'm', got {self.unit!r}")
        if self.angle and self.unit != "rad":
            raise ValueError(f"component {self.name!r}: an angle is in radians")
        if self.periodic and not (self.angle and (self.lo, self.hi, self.lo_open, self.hi_open) == (0.0, TWO_PI, False, True)):
            raise ValueError(f"component {self.name!r}: a periodic component is an angle in [0, 2π)")

    def contains(self, value: float) -> bool:
        """Whether ``value`` lies in the component's interval."""
        lo_ok = self.lo < value if self.lo_open else self.lo <= value
        hi_ok = value < self.hi if self.hi_open else value <= self.hi
        return lo_ok and hi_ok


AZ = Component("az", "rad", angle=True, std_field="std_az", lo=0.0, hi=TWO_PI, hi_open=True, periodic=True)
EL = Component("el", "rad", angle=True, std_field="std_el", lo=-math.pi / 2, hi=math.pi / 2)
RANGE = Component("range", "m", angle=False, std_field="std_range", lo=0.0, lo_open=True)

EAST = Component("east", "m", angle=False, std_field="std_east")
NORTH = Component("north", "m", angle=False, std_field="std_north")
UP = Component("up", "m", angle=False, std_field="std_up")

#: every component, by name
COMPONENTS: dict[str, Component] = {c.name: c for c in (AZ, EL, RANGE, EAST, NORTH, UP)}
