r"""Out-of-sequence measurements by re-filtering from a short buffer.

A live fuser releases a lagging source's peers after a bounded wait, so the laggard's
measurement may arrive for a time the estimator has passed (an *out-of-sequence
measurement*, OOSM). :class:`Refiltering` applies it exactly. It keeps checkpoints of
the estimator (deep copies of the method: filters, scans being grouped, track tables;
the measurements it holds are values, shared with the log, not copied) and the
measurements since the oldest one; on an OOSM at time ``τ`` it

1. restores the latest checkpoint taken at a release time ``t_c < τ``;
2. replays, in ``(t, sensor, seq)`` order, every measurement with ``t > t_c`` together
   with the OOSM, calling ``advance(t_k)`` at each later checkpoint time (and re-taking
   that checkpoint), then ``advance(t_now)``.

Every method's estimates depend only on the measurement sequence, not on when
``advance`` is called, so the estimator ends exactly where the in-order run would be:
no approximation of the process-noise cross-covariance between ``τ`` and ``t_now``, which
one-step retrodiction (Bar-Shalom's A1) approximates for one filter only. The cost is a
replay of ``W`` = ``window`` seconds per OOSM and ``W·rate`` checkpoints; anything older
than :attr:`oldest` is *stale*. The replay's estimates, from ``τ`` on, are the corrected
history the caller re-publishes (docs/live.md).
"""

from __future__ import annotations

import copy
import math
from bisect import bisect_left, insort
from dataclasses import dataclass
from typing import Any, Iterable


@dataclass
class _Checkpoint:
    t: float  # every measurement with t <= this is in ``method``, and advance(t) was called
    method: Any


class Refiltering:
    """A streaming method (``process`` / ``advance``) that also takes late measurements.

    Args:
        method: the estimator, an object with ``process(m) -> list`` and
            ``advance(t) -> list``; copied with :func:`copy.deepcopy`, except for the
            measurements of the log (immutable values: the copy shares them).
        window: buffer length ``W`` (s of the data's time base).
        shared: objects the method refers to that must not be copied (e.g. a
            rejection log it reports to).

    Example::

        rf = Refiltering(make_method("SS", config), window=10.0)
        out = rf.step([m1, m2], t=12.0)      # in order, up to the released time
        out += rf.insert([late], t=12.5)     # late.t <= 12.0: re-filtered
    """

    def __init__(self, method: Any, window: float, shared: Iterable[Any] = ()):
        if not window > 0:
            raise ValueError(f"Refiltering needs a window > 0 s, got {window}")
        self.method = method
        self.window = float(window)
        self._shared = tuple(shared)
        self._log: list[tuple[tuple, Any]] = []  # (order_key, item) with t > oldest checkpoint, sorted
        self._checkpoints: list[_Checkpoint] = [_Checkpoint(-math.inf, self._copy(method))]
        self.t = -math.inf  # the latest released time
        self.replays = 0

    def _copy(self, method: Any) -> Any:
        """A checkpoint of ``method``: everything it holds copied but the ``shared``
        objects and the measurements it was given (a frame it still groups holds them;
        copying them was most of a checkpoint's cost, docs/design.md)."""
        memo = {id(o): o for o in self._shared}
        memo.update((id(m), m) for _, m in self._log)
        return copy.deepcopy(method, memo)

    @property
    def oldest(self) -> float:
        """A measurement at or before this time can no longer be applied (stale)."""
        return self._checkpoints[0].t

    def step(self, items: list, t: float) -> list:
        """Process ``items`` (in order, all after the previous ``t``) and ``advance(t)``.
        Items may be later than ``t`` (a live release forced past a lagging source's
        watermark): the checkpoint is then at the latest item's time, never before what
        it has processed, so that a late measurement is replayed from a state that has
        not seen the items after it."""
        out: list = []
        for m in items:
            out.extend(self.method.process(m))
            insort(self._log, (m.order_key, m), key=lambda e: e[0])
        if math.isfinite(t):
            out.extend(self.method.advance(t))
        t = max([t, *(m.t for m in items)])
        if t > self.t:
            self.t = t
        if items or out:  # the state changed: a new checkpoint (else the last one still holds)
            self._checkpoints.append(_Checkpoint(self.t, self._copy(self.method)))
            self._prune()
        return out

    def insert(self, late: list, t: float | None = None) -> list:
        """Apply measurements whose times were already released (each after
        :attr:`oldest`); returns the replay's estimates, in time order: the corrected
        history from the late data's time on, ending with the current picture."""
        if not late:
            return []
        t_now = self.t if t is None else max(self.t, t)
        tau = min(m.t for m in late)
        if tau <= self.oldest:
            raise ValueError(f"measurement at t = {tau} is older than the re-filtering buffer "
                             f"(oldest checkpoint t = {self.oldest})")
        i = bisect_left([c.t for c in self._checkpoints], tau) - 1  # latest checkpoint with t_c < tau
        for m in late:
            insort(self._log, (m.order_key, m), key=lambda e: e[0])
        start = self._checkpoints[i]
        self.method = self._copy(start.method)
        keys = [k for k, _ in self._log]
        lo = bisect_left(keys, (start.t, "\uffff"))  # first item with t > t_c
        out: list = []
        for c in self._checkpoints[i + 1:]:
            hi = bisect_left(keys, (c.t, "\uffff"))
            out.extend(self._replay(self._log[lo:hi], c.t))
            c.method = self._copy(self.method)
            lo = hi
        out.extend(self._replay(self._log[lo:], t_now))
        self.t = t_now
        self.replays += 1
        if self._checkpoints[-1].t < t_now:
            self._checkpoints.append(_Checkpoint(t_now, self._copy(self.method)))
        self._prune()
        return out

    def _replay(self, entries: list, t: float) -> list:
        out: list = []
        for _, m in entries:
            out.extend(self.method.process(m))
        if math.isfinite(t):
            out.extend(self.method.advance(t))
        return out

    def _prune(self) -> None:
        """Keep the latest checkpoint at or before ``t − W`` and everything after it."""
        horizon = self.t - self.window
        n = 0
        while n + 1 < len(self._checkpoints) and self._checkpoints[n + 1].t <= horizon:
            n += 1
        if n:
            del self._checkpoints[:n]
            keys = [k for k, _ in self._log]
            del self._log[:bisect_left(keys, (self.oldest, "\uffff"))]

    def __len__(self) -> int:
        """Checkpoints held (bounded by ``W`` times the release rate, plus one)."""
        return len(self._checkpoints)
