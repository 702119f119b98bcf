"""What every consumer does first with a sample off the wire, in one order: split the
key, decode, check that the message may come on that key from that sender, check its
time, drop a repeat. The fuser, the local trackers, the recorder, the exporters and
the launcher call :meth:`Intake.offer`; what it refuses is counted by cause
(:class:`~services.node.RejectLog`, rate-limited) and dropped, and never raises.

1. ``key``: the key is not of this deployment (or not a family the consumer takes).
2. the schema's causes (``malformed``, ``version``, ``range``, ...: :mod:`schemas`).
3. ``kind``: a kind that never travels on that family (:data:`ROUTES`);
   ``spoofed-src``: a sender other than the one the key names (a measurement's sensor,
   a status's process, a truth's target; the fuser, for what a consumer takes only from it).
4. ``future``: beyond the session's end (a scenario's duration plus
   :data:`HORIZON_SLACK_S`) or, live, more than ``--max-skew`` ahead of this host's clock
   (:class:`services.live.ClockGuard`); ``past``: before the scenario's start. A status
   is stamped with its process's time, or 0: never judged by time; a watermark just
   below 0 (a node holding a plot at t = 0 promises nothing earlier) is no error.
5. ``duplicate``: the same message again (the same sender, seq and bytes on one
   stream). A restarted process numbers its messages from 1 again: a reused seq with
   other bytes is a new message. :data:`SEQ_WINDOW` recent seqs per stream, at most
   :data:`STREAMS_MAX` streams.

What is left is the consumer's: the order of the fuser's input (:mod:`services.ordering`,
which also refuses what arrives out of order or late), what a message must say to be
fused (its sensor's kind and noise, :mod:`services.fuser`).
"""

from __future__ import annotations

import math
from collections import OrderedDict
from dataclasses import dataclass
from typing import Iterable, Mapping

from schemas import MEASUREMENT_KINDS, KeySpace, Message, SchemaError, decode
from schemas.messages import DOWN_KINDS, UP_KINDS

HORIZON_SLACK_S = 1.0  # data beyond a scenario's end + this is "future"
SEQ_WINDOW = 4096  # recent sequence numbers remembered per stream (duplicate detection)
STREAMS_MAX = 4096  # streams remembered for duplicate detection, least recent forgotten first


@dataclass(frozen=True)
class Route:
    """What may travel on a key family, and what the key's id names.

    Attributes:
        family: the key's family (``zf/<deployment>/<family>/<id>``).
        kinds: the message kinds it carries.
        names: what the key's id is: ``"src"`` the sender (a measurement's sensor, a
            fuser), ``"target"`` a truth's target, ``"receiver"`` the node a downlink is
            for.
    """

    family: str
    kinds: frozenset[str]
    names: str | None


ROUTES: dict[str, Route] = {r.family: r for r in (
    Route("meas", frozenset(MEASUREMENT_KINDS) | {"watermark"}, "src"),
    Route("local", frozenset(UP_KINDS) | {"watermark"}, "src"),
    Route("feedback", frozenset(DOWN_KINDS) | {"watermark"}, "receiver"),
    Route("fused", frozenset({"track"}), "src"),
    Route("regional", frozenset({"regional_frame", "watermark"}), "src"),
    Route("truth", frozenset({"truth"}), "target"),
    Route("jam", frozenset({"jam_state"}), "src"),
    Route("status", frozenset({"status"}), "src"),
)}


@dataclass(frozen=True)
class Sample:
    """A sample the intake let through: its key's family and id, the message, its bytes."""

    family: str
    ident: str | None
    msg: Message
    data: bytes


class Intake:
    """The ordered intake of one consumer (module docstring).

    Args:
        keys: the deployment's key space.
        reject: where refusals are counted (a :class:`~services.node.RejectLog`).
        families: the key families it takes (others: ``key``).
        horizon: the session's end (scenario time; ``inf``: none, e.g. live).
        earliest: a measurement or estimate before this is ``past`` (scenario runs: 0).
        clock: live: a :class:`~services.live.ClockGuard` (:meth:`offer` then takes ``utc``).
        senders: per family whose key does not name its sender, the one sender taken
            (e.g. ``{"feedback": "fuser"}`` for a local tracker).
        dedup: drop repeats (the recorder, the exporters; the fuser's ordering does its own).
        only: per family, the one key id taken (e.g. ``{"fused": "fuser"}``: one fuser's
            tracks; None: no id, the family is heard but not this consumer's): another
            id's samples are passed over uncounted (:attr:`passed`) — another fuser
            publishing beside it is no error.
    """

    def __init__(self, keys: KeySpace, reject, families: Iterable[str], *, horizon: float = math.inf,
                 earliest: float = -math.inf, clock=None, senders: Mapping[str, str] | None = None,
                 dedup: bool = False, only: Mapping[str, str] | None = None):
        self.keys = keys
        self.reject = reject
        self.routes = {f: ROUTES[f] for f in families}
        self.horizon = horizon
        self.earliest = earliest
        self.clock = clock
        self.senders = dict(senders or {})
        self.only = dict(only or {})
        self.passed = 0  # samples of another key id than the one taken (``only``)
        self.events: list[str] = []  # what the clock guard says about sources' clocks
        self._seen: OrderedDict[tuple, OrderedDict[int, int]] | None = OrderedDict() if dedup else None

    @classmethod
    def of_scenario(cls, keys: KeySpace, reject, families: Iterable[str], duration: float | None, **kw) -> "Intake":
        """For a scenario run of ``duration`` s (None: a live session, no end and no start)."""
        if duration is None:
            return cls(keys, reject, families, **kw)
        return cls(keys, reject, families, horizon=float(duration) + HORIZON_SLACK_S, earliest=0.0, **kw)

    def offer(self, key: str, data: bytes, utc: float | None = None) -> Sample | None:
        """One sample off the wire (``utc``: this host's clock, live); None if refused."""
        try:
            family, ident = self.keys.family_and_id(key)
        except ValueError as e:
            self.reject("?", "key", str(e))
            return None
        if family in self.only and ident != self.only[family]:
            self.passed += 1
            return None
        route = self.routes.get(family)
        if route is None:
            self.reject(ident or "?", "key", f"{key!r}: this process takes nothing on {family}/")
            return None
        try:
            msg = decode(data)
        except SchemaError as e:
            self.reject(ident or family, e.cause, str(e))
            return None
        who = ident if route.names == "src" else msg.src
        why = self._route(route, ident, msg)
        if why is None:
            why = self._time(msg, utc)
        if why is None and self._seen is not None and self._repeated(family, ident, msg, hash(data)):
            why = "duplicate", f"{msg.kind} seq {msg.seq} from {msg.src} already taken"
        if why is not None:
            self.reject(who, *why)
            return None
        return Sample(family, ident, msg, data)

    def _route(self, route: Route, ident: str | None, msg: Message) -> tuple[str, str] | None:
        where = f"{route.family}/{ident or ''}"
        if msg.kind not in route.kinds:
            return "kind", f"{msg.kind!r} is not expected on {where}"
        if route.names == "src":
            claimed = msg.body.get("sensor", msg.src) if msg.kind in MEASUREMENT_KINDS else msg.src
            if msg.src != ident or claimed != ident:
                return "spoofed-src", f"{msg.kind} of {claimed!r} from {msg.src!r} came on {where}"
        elif route.names == "target" and msg.body["target"] != ident:
            return "spoofed-src", f"{msg.kind} of {msg.body['target']!r} came on {where}"
        sender = self.senders.get(route.family)
        if sender is not None and msg.src != sender:
            return "spoofed-src", f"{msg.kind} on {where} from {msg.src!r}, not {sender!r}"
        return None

    def _time(self, msg: Message, utc: float | None) -> tuple[str, str] | None:
        if msg.kind == "status":
            return None
        if msg.t > self.horizon:
            return "future", f"t = {msg.t:g} s is beyond the session's end ({self.horizon:g} s)"
        if msg.t < self.earliest and msg.kind != "watermark":
            return "past", f"t = {msg.t:g} s is before the scenario's start ({self.earliest:g} s)"
        if self.clock is not None and utc is not None:
            rej = self.clock.check(msg.src, msg.t, utc, self.events)
            if rej is not None:
                return rej.cause, rej.detail
        return None

    def _repeated(self, family: str, ident: str | None, msg: Message, digest: int) -> bool:
        """Whether this message (its seq on its stream, ``digest`` the hash of its bytes) was
        taken already. Watermarks and statuses are not data: never repeats. Measurements
        and estimates of one sender are separate streams (a process may count them apart)."""
        if msg.kind in ("watermark", "status"):
            return False
        stream = (family, ident or "", msg.src, "meas" if msg.kind in MEASUREMENT_KINDS else msg.kind)
        seen = self._seen.get(stream)
        if seen is None:
            seen = self._seen[stream] = OrderedDict()
            while len(self._seen) > STREAMS_MAX:
                self._seen.popitem(last=False)
        self._seen.move_to_end(stream)
        if seen.get(msg.seq) == digest:
            return True
        seen[msg.seq] = digest
        seen.move_to_end(msg.seq)
        if len(seen) > SEQ_WINDOW:
            seen.popitem(last=False)
        return False

    def forget(self, family: str, ident: str) -> None:
        """Forget the streams of one key (a target that has left)."""
        if self._seen is not None:
            for stream in [s for s in self._seen if s[0] == family and s[1] == ident]:
                del self._seen[stream]
