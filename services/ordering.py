"""Time ordering of many sources by watermarks, and the input gate in front of it.

Each source stamps its measurements with their time of validity and then publishes a
watermark "everything up to and including t has been sent". :class:`WatermarkMerger`
holds measurements until every *live* source's watermark has passed them, then releases
them in ``(t, sensor, seq)`` order — the total order the in-process evaluation uses, so
a distributed run feeds the estimator the same sequence at any speed. A source silent
for longer than its timeout is declared dead and no longer waited for; it rejoins when
it speaks again. A consumer that joins the streams mid-way (a restarted fuser) starts from
the first scan it has heard whole (:meth:`WatermarkMerger.join`).

Input it cannot order (``unknown-source``, ``out-of-order``, ``duplicate``, ``late``,
``stale``; a time outside the session is the intake's, :mod:`services.intake`) is
dropped and counted by cause and leaves the released sequence as if it had never arrived; duplicates are judged by ``seq`` among the held data only, so a
forged huge ``seq`` cannot silence a source. Each source holds at most ``max_held``
measurements (:func:`hold_cap`); beyond that the latest is ``shed``. Live sessions wait
at most ``max_delay`` for a lagging source and hand data that then arrives for a
released time to the estimator to re-filter (:meth:`WatermarkMerger.take_oosm`,
:mod:`fusion.oosm`). The causes, the shedding policy and why: docs/reliability.md ("Bad
input", "Load"); live operation: docs/live.md.

Pure logic: the caller passes wall-clock ``now`` in; nothing here sleeps or reads a clock.
"""

from __future__ import annotations

import heapq
import math
from bisect import bisect_right, insort
from collections import deque
from dataclasses import dataclass, field
from typing import Any

# Held measurements per source when the caller gives no cap: 10× the largest built-in
# scenario's whole output per source (61 measurements), so no run at any speed sheds.
DEFAULT_MAX_HELD = 1024
LEAD_MAX = 4096  # rises of the leading watermark remembered for the bounded wait


def hold_cap(rate_hz: float, window_s: float, factor: float = 10.0) -> int:
    """``factor`` times the measurements a source sends at its nominal ``rate_hz``
    (measurements per second of scenario time) in ``window_s`` seconds of scenario time.

    The window is how far a source may legitimately run ahead of the slowest live one:
    ``speed × timeout`` for a paced run, the whole scenario at ``--speed max``.
    """
    if not (rate_hz > 0 and window_s > 0 and factor >= 1):
        raise ValueError(f"hold_cap needs rate_hz > 0, window_s > 0, factor >= 1 "
                         f"(got {rate_hz}, {window_s}, {factor})")
    return math.ceil(factor * rate_hz * window_s)


@dataclass
class SourceState:
    watermark: float = -math.inf
    final: bool = False
    dead: bool = False
    last_heard: float | None = None  # wall clock
    dead_since_t: float | None = None  # scenario time when declared dead
    dead_intervals: list[list[float | None]] = field(default_factory=list)
    held: list[tuple[float, int, Any]] = field(default_factory=list)  # (t, seq, item), sorted
    held_seqs: set[int] = field(default_factory=set)
    oosm: int = 0  # out-of-sequence measurements taken (live)
    stale: int = 0  # measurements too old to re-filter (live)
    oosm_seqs: dict[int, float] = field(default_factory=dict)  # seq -> t of OOSMs after its watermark
    recovery_until: float = -math.inf  # live: its data stamped up to this was sent while it was cut off
    recovered: int = 0  # live: measurements sent while it was cut off (dead), arrived after it came back
    missed: int = 0  # live: measurements its publisher could not give back (told by the fabric)


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
        start_grace: extra seconds a source that has never been heard gets at start-up,
            counted from the first source heard (before any input nothing waits on it,
            and sources started together can take long to come up on a loaded host).
        now: wall clock at start.
        max_held: measurements held per source before the latest is shed (see the
            module docstring and :func:`hold_cap`).
        max_delay: live: longest wall-clock wait (s) for a lagging source's watermark;
            ``inf`` (scenario runs): wait for every live source.
        oosm_window: live: how far back (in ``t``) a measurement for an already
            released time is still taken as out-of-sequence; 0: rejected as ``late``.
    """

    def __init__(self, sources: list[str], timeout: float, start_grace: float = 30.0,
                 now: float = 0.0, max_held: int = DEFAULT_MAX_HELD, max_delay: float = math.inf, oosm_window: float = 0.0):
        if not sources:
            raise ValueError("WatermarkMerger needs at least one source")
        if max_held < 1:
            raise ValueError(f"max_held must be at least 1, got {max_held}")
        self.sources = {s: SourceState() for s in sources}
        self.timeout = timeout
        self.max_held = max_held
        self._start = now
        self._first_heard: float | None = None  # wall clock of the first message of any source
        self._start_grace = start_grace
        self.released_until = -math.inf  # the merged watermark already passed downstream
        self.late = 0
        self.shed = 0
        self.joined_at = -math.inf  # measurements up to this time may be partial (:meth:`join`)
        self.partial = 0
        self.max_delay = max_delay
        self.oosm_window = oosm_window
        # (wall time, leading watermark) as the lead rose, for the bounded wait; at most one
        # entry per rise within max_delay seconds (watermarks rise at the sources' scan rate)
        self._lead: deque[tuple[float, float]] = deque(maxlen=LEAD_MAX)
        self._forced = -math.inf  # the front the bounded wait has reached
        self._oosm: list[tuple[float, str, int, Any]] = []  # (t, src, seq, item) not yet taken

    # -- input ------------------------------------------------------------------------------

    def _source(self, src: str) -> SourceState | Rejection:
        st = self.sources.get(src)
        if st is None:
            return Rejection(src, "unknown-source", f"source {src!r} is not part of this scenario")
        return st

    def _heard(self, src: str, st: SourceState, now: float, events: list[str]) -> None:
        if self._first_heard is None:
            self._first_heard = now
        st.last_heard = now
        if st.dead:
            st.dead = False
            # (before anything was released: dead over [0, 0], not "until the end")
            st.dead_intervals[-1][1] = self.released_until if math.isfinite(self.released_until) else 0.0
            events.append(f"source {src} rejoined")

    def add(self, src: str, t: float, seq: int, item: Any, now: float, events: list[str]) -> Rejection | None:
        """Offer one measurement; returns a :class:`Rejection` if it, or a held
        measurement it displaced, is dropped."""
        st = self._source(src)
        if isinstance(st, Rejection):
            return st
        if t <= st.watermark:
            return Rejection(src, "out-of-order", f"t = {t:g} s is not after its own watermark {st.watermark:g} s")
        if seq in st.held_seqs or seq in st.oosm_seqs:
            return Rejection(src, "duplicate", f"seq {seq} is already held")
        self._heard(src, st, now, events)
        if t <= st.recovery_until:  # sent while it was cut off, given back on reconnection (the caller says until when)
            st.recovered += 1
        if t <= self.joined_at:
            self.partial += 1
            return None
        if t <= self.released_until:
            if self.oosm_window <= 0:
                self.late += 1
                return Rejection(src, "late", f"t = {t:g} s arrived after the merged stream passed "
                                 f"{self.released_until:g} s")
            if t <= self.released_until - self.oosm_window:
                st.stale += 1
                return Rejection(src, "stale", f"t = {t:g} s is more than {self.oosm_window:g} s before the "
                                 f"released time {self.released_until:g} s (the re-filtering window)")
            if len(st.oosm_seqs) >= self.max_held:  # a flood of "late" data: bounded like held data
                self.shed += 1
                return Rejection(src, "shed", f"holds {self.max_held} out-of-sequence measurements; t = {t:g} s dropped")
            st.oosm += 1
            st.oosm_seqs[seq] = t
            self._oosm.append((t, src, seq, item))
            return None
        if len(st.held) < self.max_held:
            self._hold(st, t, seq, item)
            return None
        self.shed += 1
        latest = st.held[-1]
        if (t, seq) > latest[:2]:
            return Rejection(src, "shed", f"holds {self.max_held} measurements; t = {t:g} s is the latest, dropped")
        st.held.pop()
        st.held_seqs.discard(latest[1])
        self._hold(st, t, seq, item)
        return Rejection(src, "shed", f"holds {self.max_held} measurements; the latest (t = {latest[0]:g} s) dropped")

    @staticmethod
    def _hold(st: SourceState, t: float, seq: int, item: Any) -> None:
        insort(st.held, (t, seq, item))  # (t, seq) is unique per source, so items are never compared
        st.held_seqs.add(seq)

    def watermark(self, src: str, t: float, final: bool, now: float, events: list[str]) -> Rejection | None:
        st = self._source(src)
        if isinstance(st, Rejection):
            return st
        if t < st.watermark:
            return Rejection(src, "out-of-order", f"watermark {t:g} s goes back from {st.watermark:g} s")
        st.watermark = t
        st.final = st.final or final
        if st.oosm_seqs:  # its watermark now rejects repeats of these by time
            st.oosm_seqs = {q: tq for q, tq in st.oosm_seqs.items() if tq > t}
        self._heard(src, st, now, events)
        if math.isfinite(self.max_delay) and not st.final and (not self._lead or t > self._lead[-1][1]):
            self._lead.append((now, t))
        return None

    def join(self, t: float) -> int:
        """A source was first heard mid-stream, its first watermark heard at ``t``: a
        consumer that subscribed then may have heard only part of what any source sent up
        to ``t``. Held measurements stamped up to ``t``, and any that come later, are
        dropped (counted in ``partial``): the stream released starts with a whole scan.
        Returns how many held ones were dropped."""
        self.joined_at = max(self.joined_at, t)
        n = 0
        for st in self.sources.values():
            k = bisect_right(st.held, t, key=lambda h: h[0])
            st.held_seqs.difference_update(seq for _, seq, _ in st.held[:k])
            del st.held[:k]
            n += k
        self.partial += n
        return n

    # -- liveness ---------------------------------------------------------------------------

    def check_timeouts(self, now: float, events: list[str]) -> None:
        for src, st in self.sources.items():
            if st.dead or st.final:
                continue
            since = st.last_heard if st.last_heard is not None else \
                max(self._start, self._first_heard or self._start) + self._start_grace
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
        return all((st.final or st.dead) and not st.held for st in self.sources.values())

    @property
    def all_final(self) -> bool:
        return all(st.final for st in self.sources.values())

    def front(self, now: float | None = None) -> float:
        """What may be released at wall time ``now``: the merged watermark, or (live) the
        leading watermark of ``max_delay`` seconds ago if that is later."""
        wm = self.merged_watermark
        if now is None or not math.isfinite(self.max_delay):
            return wm
        while self._lead and self._lead[0][0] <= now - self.max_delay:
            self._forced = max(self._forced, self._lead.popleft()[1])
        return wm if wm == math.inf else max(wm, self._forced)

    def take_oosm(self) -> list[Any]:
        """The out-of-sequence measurements taken since the last call, in (t, src, seq) order."""
        out, self._oosm = sorted(self._oosm, key=lambda r: r[:3]), []
        return [r[3] for r in out]

    def release(self, now: float | None = None) -> tuple[list[Any], float]:
        """Pop every held item the release front (:meth:`front`) has passed, in
        (t, src, seq) order.

        Returns the items and the watermark to hand to the estimator's ``advance``.
        """
        wm = self.front(now)
        ready = []
        for src, st in self.sources.items():
            n = bisect_right(st.held, wm, key=lambda h: h[0])
            if n:
                ready.append([(t, src, seq, item) for t, seq, item in st.held[:n]])
                st.held_seqs.difference_update(seq for _, seq, _ in st.held[:n])
                del st.held[:n]
        out = [r[3] for r in heapq.merge(*ready, key=lambda r: r[:3])]
        if wm == math.inf and not self.held():
            wm = max([self.released_until] + [st.watermark for st in self.sources.values()])
        if wm > self.released_until:
            self.released_until = wm
            if self.oosm_window > 0:  # older than the window: stale by time, no need to remember
                old = self.released_until - self.oosm_window
                for st in self.sources.values():
                    if st.oosm_seqs:
                        st.oosm_seqs = {q: tq for q, tq in st.oosm_seqs.items() if tq > old}
        return out, self.released_until

    def held(self) -> int:
        return sum(len(st.held) for st in self.sources.values())
