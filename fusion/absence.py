r"""How long a process's loss leaves aircraft out of the picture: the absences across a
loss, from the times each aircraft was seen (issue 28, "Losing a region").

An aircraft is *seen* at a time when the picture holds it then: a scored step at which a
track is on it (GOSPA's assignment within the cut-off, :mod:`fusion.mtt_metrics`), or,
for a benchmark, the arrival of an estimate near it. Around a loss at time ``at``:

* its **absence** is the gap across the loss, from its last sighting at or before ``at``
  to its first after it — or, not seen again, to ``end`` (the end of what was watched:
  a lower bound, the aircraft is *not back*). An aircraft held at every step has an
  absence of one step;
* the aircraft counted are those seen at or before the loss (since ``since``): one
  never seen is nobody's loss.

Over the aircraft of a loss (:func:`loss_counts`, the keys of a run's summary):
``aircraft`` (how many), ``longest_absence_s`` (the longest absence), ``absent_over_2_periods``
(the aircraft whose absence exceeds two of ``period_s``) and ``not_back``.

:class:`LossWatch` follows one loss through a run's scored steps, as a live run folds
them in, holding only the aircraft it watches: those of the lost process's region (an
area; None: the whole picture) held at a step in the period before the loss (``since``;
a run's summary: one ``period_s``, so that an aircraft whose last frames before the kill
died with the process still counts). An aircraft lost earlier is not counted (its
absence began before: a tracker's break, not the loss), nor one never held. Pure: no
clock, no I/O.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable, Collection, Mapping, Sequence

import numpy as np

__all__ = ["Absence", "LossWatch", "absences", "loss_counts"]


@dataclass(frozen=True)
class Absence:
    """One aircraft's absence across a loss: ``last`` seen at or before it, ``back``
    seen again after it (None: not by the end), ``s`` the absence (s)."""

    last: float
    back: float | None
    s: float


def absences(seen: Mapping[str, Sequence[float]], at: float, end: float | Mapping[str, float],
             since: float = -math.inf) -> dict[str, Absence]:
    """Per aircraft seen in ``[since, at]``, its absence across ``at`` (module docstring).
    ``seen``: each aircraft's sighting times (any order); ``end``: where watching ended,
    for all or per aircraft (an aircraft that left earlier: its last step)."""
    out = {}
    for a, times in seen.items():
        t = np.sort(np.asarray(times, dtype=float))
        before, after = t[(t >= since) & (t <= at)], t[t > at]
        if not before.size:
            continue
        last = float(before[-1])
        back = float(after[0]) if after.size else None
        stop = back if back is not None else (end[a] if isinstance(end, Mapping) else end)
        out[a] = Absence(last, back, max(0.0, float(stop) - last))
    return out


def loss_counts(gone: Mapping[str, Absence], period_s: float) -> dict:
    """The summary's keys for one loss: ``aircraft``, ``longest_absence_s``,
    ``absent_over_2_periods`` (absence > 2 × ``period_s``), ``not_back``, ``period_s``."""
    s = [g.s for g in gone.values()]
    return {"aircraft": len(s), "longest_absence_s": round(max(s), 3) if s else None,
            "absent_over_2_periods": sum(x > 2.0 * period_s for x in s),
            "not_back": sum(g.back is None for g in gone.values()), "period_s": period_s}


class LossWatch:
    """One loss at ``at``, followed through a run's steps in time order (:meth:`step`):
    the aircraft held at a step in ``[since, at]`` whose true position then ``area``
    accepts (None: every one), each one's last such step, its first step held after the
    loss, and where it was last present (an aircraft that leaves the picture's truth ends
    its absence there). ``area``: points ``(m, ≥2)`` -> ``(m,)`` bool (a region's
    ``holds``)."""

    def __init__(self, at: float, area: Callable[[np.ndarray], np.ndarray] | None = None,
                 since: float = -math.inf):
        self.at, self.area, self.since = at, area, since
        self._last: dict[str, float] = {}  # before the loss: aircraft held in [since, at] -> its last step held
        self.seen: dict[str, list[float]] | None = None  # watched aircraft -> [last held <= at, first held > at]
        self.present: dict[str, float] = {}  # watched aircraft not back -> its last step present

    def step(self, t: float, truths: Mapping[str, np.ndarray], held: Collection[str]) -> None:
        """One scored step: the true positions of the aircraft present, those held."""
        if t <= self.at:
            if t >= self.since:
                ids = [a for a in held if a in truths]
                if ids and self.area is not None:
                    inside = self.area(np.array([np.asarray(truths[a], dtype=float)[:2] for a in ids]))
                    ids = [a for a, keep in zip(ids, inside) if keep]
                self._last.update(dict.fromkeys(ids, t))
            return
        if self.seen is None:
            self.seen = {a: [t0] for a, t0 in self._last.items()}
            self.present = dict(self._last)
        for a in list(self.present):
            if a in held:
                self.seen[a].append(t)
                del self.present[a]
            elif a in truths:
                self.present[a] = t

    def absences(self) -> dict[str, Absence]:
        """The watched aircraft's absences so far (none before a step after the loss)."""
        return absences(self.seen or {}, self.at, self.present)
