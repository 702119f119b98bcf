"""Time grouping: a time-ordered measurement stream cut into groups by time of validity.

Every method family works on groups: a one-target 3D method on *scans* (at most one
measurement per sensor), a many-target method on *frames* (any number of plots per
sensor), a DF method on *epochs* (the bearings of one scan of the DF network). All three
are cut by one rule, here:

- a group opens at its first measurement, time ``t₀``, and takes every later measurement
  with ``t − t₀ ≤ tol``;
- it closes (a) when a measurement arrives that cannot join it (``t − t₀ > tol``, or,
  for scans, a second one from the same sensor), (b) at a watermark ``w`` with
  ``w − t₀ ≥ tol`` (everything up to ``w`` has been sent, so nothing can still join),
  (c) for scans after the first, once it holds a measurement of every sensor seen so
  far, or (d) at :meth:`TimeGrouper.finish`.

Each rule depends on the measurement sequence alone, so the groups — and every estimate
made from them — never depend on when watermarks arrive: only how early a group is
released does. The grouper also guards the order the methods rely on: measurements in
strictly increasing ``(t, sensor, seq)``, none at or before a watermark already given.
"""

from __future__ import annotations

import math

from .types import Measurement


class TimeGrouper:
    """The groups of a time-ordered stream (module docstring).

    Args:
        tol: the group's time window ``tol`` (s, ≥ 0; the methods' ``pair_tol``).
        one_per_sensor: scans (at most one measurement per sensor, rule (c)) rather
            than frames or epochs (any number per sensor; a group closes on time alone).
    """

    def __init__(self, tol: float, one_per_sensor: bool = False):
        if not tol >= 0.0:
            raise ValueError(f"pair_tol must be >= 0, got {tol}")
        self.tol = float(tol)
        self.one_per_sensor = one_per_sensor
        self._open: list[Measurement] = []
        self._seen: set[str] = set()
        self._closed = 0
        self._last_key: tuple | None = None
        self._watermark = -math.inf

    def push(self, m: Measurement) -> list[list[Measurement]]:
        """Take ``m``; the groups it closes (none or one)."""
        key = m.order_key
        if self._last_key is not None and key <= self._last_key:
            raise ValueError(f"measurement {key} out of order (after {self._last_key})")
        if m.t <= self._watermark:
            raise ValueError(f"late measurement at t={m.t} from {m.sensor!r}: arrived after watermark {self._watermark}")
        self._last_key = key
        out = []
        if self._open and (m.t - self._open[0].t > self.tol
                           or (self.one_per_sensor and any(o.sensor == m.sensor for o in self._open))):
            out += self._close()
        self._open.append(m)
        if self.one_per_sensor:
            self._seen.add(m.sensor)
            if self._closed and self._seen <= {o.sensor for o in self._open}:
                out += self._close()
        return out

    def advance(self, t: float) -> list[list[Measurement]]:
        """Watermark ``t``: nothing at or before it will come. The group it closes, if any."""
        self._watermark = max(self._watermark, float(t))
        if self._open and self._watermark - self._open[0].t >= self.tol:
            return self._close()
        return []

    def finish(self) -> list[list[Measurement]]:
        """End of stream: the open group, if any."""
        return self._close()

    def held_since(self) -> float | None:
        """Time of the open group's first member (None when no group is open)."""
        return self._open[0].t if self._open else None

    def _close(self) -> list[list[Measurement]]:
        if not self._open:
            return []
        group, self._open = self._open, []
        self._closed += 1
        return [group]
