r"""Out-of-sequence measurements by re-filtering from a short buffer.

A live fuser cannot wait for its slowest source forever: after a bounded wait it
releases the others, and a measurement of the laggard then arrives for a time the
estimator has already passed (an *out-of-sequence measurement*, OOSM). Dropping it
throws away the best sensor of a slow link; applying it as if it were new ("predict
backwards") is wrong for any nonlinear or multi-sensor method. :class:`Refiltering`
applies it exactly: it keeps checkpoints of the estimator and the measurements since
the oldest one, and on an OOSM at time ``τ``

1. restores the latest checkpoint taken at a release time ``t_c < τ`` (a deep copy
   of the method: its filters, scans being grouped, track tables);
2. replays, in ``(t, sensor, seq)`` order, every measurement with ``t > t_c``
   together with the OOSM, calling ``advance(t_k)`` at each later checkpoint time
   ``t_k`` (and re-taking that checkpoint), then ``advance(t_now)``.

Every method here emits estimates that depend only on the measurement sequence, not on
when ``advance`` is called, so after step 2 the estimator is in exactly the state it
would be in had the OOSM arrived in order: for the EKF, ``x̂_{k|k}`` and ``P_{k|k}``
are the in-order ones to round-off, with no approximation of the cross-covariance of
the process noise between ``τ`` and ``t_now`` (what one-step retrodiction, e.g.
Bar-Shalom's A1 algorithm, approximates). The cost is a replay of ``W`` seconds of
data per OOSM and ``W·rate`` checkpoints of memory, where ``W`` (``window``) is the
buffer length: a checkpoint is dropped once a later one is older than ``t_now − W``,
so an OOSM with ``τ > t_now − W`` can always be applied, and anything older is
*stale* (refused by the caller, which knows the bound from :attr:`oldest`).

What the caller publishes: the replay's estimates, in time order, from the late
data's time to the latest output time: the corrected history of the last ``t_now − τ``
seconds, ending with the corrected current picture. A consumer that keeps the latest
estimate per ``(track, t)`` then holds what an in-order run would have given.
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
            ``advance(t) -> list``; copied with :func:`copy.deepcopy`.
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
        self._checkpoints: list[_Checkpoint] = [_Checkpoint(-math.inf, self._copy(method))]
        self._log: list[tuple[tuple, Any]] = []  # (order_key, item) with t > oldest checkpoint, sorted
        self.t = -math.inf  # the latest released time
        self.replays = 0

    def _copy(self, method: Any) -> Any:
        return copy.deepcopy(method, {id(o): o for o in self._shared})

    @property
    def oldest(self) -> float:
        """A measurement at or before this time can no longer be applied (stale)."""
        return self._checkpoints[0].t

    def step(self, items: list, t: float) -> list:
        """Process ``items`` (in order, all after the previous ``t``) and ``advance(t)``."""
        out: list = []
        for m in items:
            out.extend(self.method.process(m))
            insort(self._log, (m.order_key, m), key=lambda e: e[0])
        if math.isfinite(t):
            out.extend(self.method.advance(t))
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
