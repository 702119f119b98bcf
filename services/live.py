"""Live sessions: the UTC time base, and the guard against sources whose clocks are off.

In a scenario run ``t`` on the wire is scenario seconds from 0, the processes know the
scenario's end, and every source is a process of this machine. In a live session ``t``
is UTC POSIX seconds, nothing ends (a process runs until SIGINT/SIGTERM), and sources
stamp their data with their own clocks. So a live consumer

* refuses any ``t`` more than ``max_skew`` seconds ahead of its own clock (cause
  ``future``, counted and logged at a bounded rate): it cannot be data yet, and a
  watermark from the future would make every other source's data look late;
* says in its status, per source, how far behind its clock the source's latest
  stamps are (``lag_s``: link delay plus clock offset) and whether the clock looks
  skewed (``clock``: ``ahead`` once data was refused as from the future, ``behind``
  while even the source's freshest message of the last ``LAG_WINDOW`` is more than
  ``max_skew`` old, else ``ok``), with an event when that changes.

:class:`ClockGuard` is that logic without a clock: the caller passes ``utc`` in.
:class:`LiveOptions` carries the live knobs a fuser is started with.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field

from .ordering import Rejection

LAG_WINDOW = 32  # messages per source over which the freshest stamp is judged


@dataclass(frozen=True)
class LiveOptions:
    """What makes a process live (``--site``): the clock checks, the bounded wait for a
    lagging source and the out-of-sequence buffer (:mod:`fusion.oosm`)."""

    max_skew: float = 5.0
    max_delay: float = 1.0
    oosm_window: float = 10.0

    def __post_init__(self) -> None:
        if not (self.max_skew > 0 and self.max_delay >= 0 and self.oosm_window > 0):
            raise ValueError(f"live options need max_skew > 0, max_delay >= 0 and oosm_window > 0 "
                             f"(got {self.max_skew}, {self.max_delay}, {self.oosm_window})")


@dataclass
class _Clock:
    lags: deque = field(default_factory=lambda: deque(maxlen=LAG_WINDOW))
    state: str = "ok"
    ahead: int = 0  # messages refused as from the future


class ClockGuard:
    """Refuses timestamps from the future and judges each source's clock (module docstring).

    Args:
        max_skew: seconds a stamp may be ahead of this host's clock.
        max_sources: distinct sources judged (names come off the wire); the rest are
            checked but not reported.
    """

    def __init__(self, max_skew: float, max_sources: int = 256):
        self.max_skew = max_skew
        self.max_sources = max_sources
        self._clocks: dict[str, _Clock] = {}

    def check(self, src: str, t: float, utc: float, events: list[str], lookahead: float | None = None) -> Rejection | None:
        """Judge one stamp ``t`` of ``src`` received at ``utc``; a :class:`Rejection` if it is
        too far ahead. ``lookahead``: a watermark's, which may promise up to that much
        beyond the source's latest data (its nominal period); it is checked, not judged."""
        c = self._clocks.get(src)
        if c is None and len(self._clocks) < self.max_sources:
            c = self._clocks[src] = _Clock()
        lag = utc - t
        if lookahead is not None:
            lag += lookahead
        if lag < -self.max_skew:
            if c is not None:
                c.ahead += 1
                self._set(src, c, "ahead", events, f"its t is {-lag:.1f} s ahead of this host's clock")
            return Rejection(src, "future", f"t = {t:.3f} is {-lag:.1f} s ahead of this host's clock "
                                            f"(--max-skew {self.max_skew:g} s)")
        if c is not None and lookahead is None:
            c.lags.append(lag)
            if min(c.lags) > self.max_skew and len(c.lags) == c.lags.maxlen:
                self._set(src, c, "behind", events, f"its freshest stamps are {min(c.lags):.1f} s old")
            elif min(c.lags) <= self.max_skew:
                self._set(src, c, "ok", events, "its stamps agree with this host's clock again")
        return None

    def _set(self, src: str, c: _Clock, state: str, events: list[str], why: str) -> None:
        if c.state != state:
            c.state = state
            if state == "ok":
                events.append(f"source {src}: clock ok ({why})")
            else:
                events.append(f"source {src}: clock looks skewed ({state}: {why}; --max-skew {self.max_skew:g} s)")

    def report(self, src: str) -> dict:
        """``lag_s`` (the latest stamp's age, s), ``clock`` (ok | ahead | behind)."""
        c = self._clocks.get(src)
        if c is None:
            return {"lag_s": None, "clock": "ok"}
        lag = c.lags[-1] if c.lags else None
        return {"lag_s": None if lag is None or not math.isfinite(lag) else round(lag, 3), "clock": c.state}
