"""Time ordering of many sources by watermarks, and the input gate in front of it.

Each source stamps its measurements with their time of validity and then publishes a
watermark "everything up to and including t has been sent". :class:`WatermarkMerger` holds
measurements until every *live* source's watermark has passed them, then releases them
in ``(t, sensor, seq)`` order — the same total order the in-process evaluation uses, so a
distributed run feeds the estimator the same sequence at any speed.

A source silent for longer than its timeout is declared dead and no longer waited for;
it rejoins when it speaks again. Late data (older than what was already released) is
dropped and counted, as are duplicates (a sequence number already seen), data from
unknown sources and data far in the future. Rejected input leaves the released
sequence exactly as if it had never arrived.

Pure logic: the caller passes wall-clock ``now`` in; nothing here sleeps or reads a clock.
"""

from __future__ import annotations

import heapq
import math
from dataclasses import dataclass, field
from typing import Any


@dataclass
class SourceState:
    watermark: float = -math.inf
    last_seq: int = -1
    final: bool = False
    dead: bool = False
    last_heard: float | None = None  # wall clock
    dead_since_t: float | None = None  # scenario time when declared dead
    dead_intervals: list[list[float | None]] = field(default_factory=list)


@dataclass(frozen=True)
class Rejection:
    src: str
    cause: str
    detail: str


class WatermarkMerger:
    """Merge per-source streams into one time-ordered stream.

    Args:
        sources: the expected source ids (anything else is rejected as unknown).
        timeout: seconds of wall-clock silence after which a source is declared dead.
        start_grace: extra seconds a source that has never been heard gets at start-up.
        horizon: measurements with ``t`` beyond this scenario time are rejected as
            "future" (a scenario's duration plus slack; ``inf`` disables).
    """

    def __init__(self, sources: list[str], timeout: float, start_grace: float = 30.0,
                 horizon: float = math.inf, now: float = 0.0):
        if not sources:
            raise ValueError("WatermarkMerger needs at least one source")
        self.sources = {s: SourceState() for s in sources}
        self.timeout = timeout
        self.horizon = horizon
        self._start = now
        self._start_grace = start_grace
        self._heap: list[tuple[float, str, int, Any]] = []
        self.released_until = -math.inf  # the merged watermark already passed downstream
        self.late = 0

    # -- input ------------------------------------------------------------------------------

    def _source(self, src: str) -> SourceState | Rejection:
        st = self.sources.get(src)
        if st is None:
            return Rejection(src, "unknown-source", f"source {src!r} is not part of this scenario")
        return st

    def _heard(self, src: str, st: SourceState, now: float, events: list[str]) -> None:
        st.last_heard = now
        if st.dead:
            st.dead = False
            st.dead_intervals[-1][1] = self.released_until if math.isfinite(self.released_until) else None
            events.append(f"source {src} rejoined")

    def add(self, src: str, t: float, seq: int, item: Any, now: float, events: list[str]) -> Rejection | None:
        """Offer one measurement; returns a :class:`Rejection` if it is dropped."""
        st = self._source(src)
        if isinstance(st, Rejection):
            return st
        if seq <= st.last_seq:
            return Rejection(src, "duplicate", f"seq {seq} already seen (last {st.last_seq})")
        if t > self.horizon:
            return Rejection(src, "future", f"t = {t:g} s is beyond the scenario's end ({self.horizon:g} s)")
        if t <= st.watermark:
            return Rejection(src, "out-of-order", f"t = {t:g} s is not after its own watermark {st.watermark:g} s")
        if t <= self.released_until:
            self.late += 1
            st.last_seq = seq
            self._heard(src, st, now, events)
            return Rejection(src, "late", f"t = {t:g} s arrived after the merged stream passed {self.released_until:g} s")
        st.last_seq = seq
        self._heard(src, st, now, events)
        heapq.heappush(self._heap, (t, src, seq, item))
        return None

    def watermark(self, src: str, t: float, final: bool, now: float, events: list[str]) -> Rejection | None:
        st = self._source(src)
        if isinstance(st, Rejection):
            return st
        if t < st.watermark:
            return Rejection(src, "out-of-order", f"watermark {t:g} s goes back from {st.watermark:g} s")
        st.watermark = t
        st.final = st.final or final
        self._heard(src, st, now, events)
        return None

    # -- liveness ---------------------------------------------------------------------------

    def check_timeouts(self, now: float, events: list[str]) -> None:
        for src, st in self.sources.items():
            if st.dead or st.final:
                continue
            since = st.last_heard if st.last_heard is not None else self._start + self._start_grace
            if now - since > self.timeout:
                self.declare_dead(src, events, f"silent for more than {self.timeout:g} s")

    def declare_dead(self, src: str, events: list[str], why: str) -> None:
        st = self.sources[src]
        if st.dead or st.final:
            return
        st.dead = True
        t = self.released_until if math.isfinite(self.released_until) else 0.0
        st.dead_intervals.append([t, None])
        events.append(f"source {src} declared dead ({why})")

    # -- output -------------------------------------------------------------------------------

    @property
    def merged_watermark(self) -> float:
        """Minimum watermark over live, unfinished sources (``inf`` when none is left)."""
        live = [st.watermark for st in self.sources.values() if not st.dead and not st.final]
        return min(live) if live else math.inf

    @property
    def done(self) -> bool:
        """Every source finished or dead, and nothing held."""
        return all(st.final or st.dead for st in self.sources.values()) and not self._heap

    @property
    def all_final(self) -> bool:
        return all(st.final for st in self.sources.values())

    def release(self) -> tuple[list[Any], float]:
        """Pop every held item the merged watermark has passed, in (t, src, seq) order.

        Returns the items and the watermark to hand to the estimator's ``advance``.
        """
        wm = self.merged_watermark
        out = []
        while self._heap and self._heap[0][0] <= wm:
            out.append(heapq.heappop(self._heap)[3])
        if wm == math.inf and not self._heap:
            wm = max([self.released_until] + [st.watermark for st in self.sources.values()])
        if wm > self.released_until:
            self.released_until = wm
        return out, self.released_until

    def held(self) -> int:
        return len(self._heap)
