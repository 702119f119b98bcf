"""Who publishes the fused output when a hot standby runs beside the fuser.

A standby (``zfusion fuser --standby``, ``zfusion run --standby``) is a second fuser on
the same inputs. The fuser's ordering is deterministic (:mod:`services.ordering`: the
merged stream is released by the sources' watermarks, not by arrival time), so both
hold the same tracks with the same ids; only the *leader* publishes (estimates,
downlinks, the horizon), under the fuser's identity, with the seq numbers it would have
used, so a consumer sees one stream.

The election is by age. Every process of one fuser identity, leading or not, holds a
Zenoh liveliness token ``<deployment>/leader/<fuser>/<born>-<zid>`` (:class:`Member`:
its start, UTC in ns, then its Zenoh id to break a tie): a total order that every peer
computes alike. The token lives as long as the process's session, kill -9 included (the
peers see the link drop and the token go: a DELETE). Leadership is a pure function of the
members a process knows: **the oldest live member leads**. A process that learns of an
older member while leading yields at once (it stops publishing); one whose older
members are all gone takes over. A process without ``--standby`` first waits for its
session's first link and then for its links to settle (no new one for ``quiet``
seconds: gossip connects it to the other peers one by one, and a peer not yet linked is a
member not yet seen); a standby that knows no other member leads once ``grace`` has
passed (no fuser to stand by for). A process that finds an older member at its start
*joins* (below). In peer-to-peer mode two processes not yet linked to each other both
lead; the younger yields as soon as the link is up (docs/reliability.md: the window).

A standby that joins a running leader (started late, or a killed fuser restarted) has
not heard the data the leader's tracks come from. It rebuilds them (:func:`rebuild`)
from the leader's picture (:mod:`services.picture`: each track's last estimate, its
``x``, ``P``, time and seq, and the picture's time ``t_p``): a one-target method's
track filter starts from that estimate, a GNN many-target tracker's table from the
confirmed tracks of the latest frame; the core drops every measurement up to the scan
of ``t_p`` (:meth:`services.ordering.WatermarkMerger.join`), and the subscriber takes
the sources' recovery caches first, which hold what was sent after ``t_p`` before it
subscribed. A Kalman filter's future depends on its ``(x, P, t)`` and the measurements
after ``t`` alone, so from then on the standby's estimates are the leader's, bit for
bit (many targets: those of the tracks confirmed at the join; a tentative one starts
again and converges). A method whose state is more than its published tracks (JIPDA,
DF filters, track-fusion centres) joins as before, from the first scan it hears
whole; docs/reliability.md says what is equal, what converges and how fast. A regional
fuser that finds no older member (restarted with no standby) has no leader to ask: it
rebuilds alike from its region's picture, which the system fuser keeps from the frames
it takes (:class:`services.picture.RegionPictures`), so the region's ids go on.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np
import zenoh

from fusion.mtt import MultiTargetMethod
from fusion.patent import CentralisedMethod
from fusion.regional import RegionalFuser, RegionalStage
from fusion.tracking.manager import MultiTargetTracker
from fusion.tracking.table import Track
from fusion.types import Estimate
from schemas import KeySpace


LINK_WAIT_S = 5.0  # how long the election waits for the session's first link (none: a process alone)
SETTLE_S = 0.25  # then until no new link has come for this long (gossip links the other peers one by one) ...
SETTLE_MAX_S = 2.0  # ... but no longer than this after the first link


def group_key(keys: KeySpace, fuser: str) -> str:
    """The key under which every process of ``fuser``'s identity holds its member token."""
    return f"{keys.prefix}/leader/{fuser}"


@dataclass(frozen=True, order=True)
class Member:
    """One process of a fuser identity, as its token's last chunk says: ``<born>-<zid>``.
    Ordered by age: the smaller leads."""

    born: int  # when the process started, UTC in ns
    zid: str  # its Zenoh session's id: two born in the same ns are ordered alike everywhere

    def __str__(self) -> str:
        return f"{self.born}-{self.zid}"

    @classmethod
    def parse(cls, chunk: str) -> "Member | None":
        born, _, zid = chunk.partition("-")
        return cls(int(born), zid) if born.isdigit() and zid else None


def settle(session: zenoh.Session, stopping: threading.Event, link_wait: float = LINK_WAIT_S,
           quiet: float = SETTLE_S, longest: float = SETTLE_MAX_S) -> tuple[int, float]:
    """Wait for ``session``'s first link (at most ``link_wait`` s), then until no new link
    has come for ``quiet`` s (at most ``longest`` s after the first). Returns the links
    then up and the seconds it waited."""
    def links() -> set[str]:
        return {str(z) for z in session.info.peers_zid()} | {str(z) for z in session.info.routers_zid()}
    started = time.monotonic()
    end = started + link_wait
    seen = links()
    while not seen and time.monotonic() < end and not stopping.is_set():
        time.sleep(0.02)
        seen = links()
    if not seen:
        return 0, time.monotonic() - started
    end = time.monotonic() + longest
    calm = time.monotonic() + quiet
    while time.monotonic() < min(calm, end) and not stopping.is_set():
        time.sleep(0.02)
        now = links()
        if now - seen:
            seen |= now
            calm = time.monotonic() + quiet
    return len(seen), time.monotonic() - started


class Leadership:
    """This process's part in the election of one fuser's leader (module docstring).

    ``leads`` is read by the fuser's loop before each publication; ``event`` is called
    (from Zenoh's thread or the loop's) with a line for the status events. ``born``
    (UTC ns; default: now) ranks this process among the members; ``link_wait`` and
    ``quiet``: :func:`settle`'s."""

    def __init__(self, session: zenoh.Session, keys: KeySpace, fuser: str, standby: bool, grace: float,
                 event: Callable[[str], None], stopping: threading.Event, born: int | None = None,
                 link_wait: float = LINK_WAIT_S, quiet: float = SETTLE_S):
        self._stopping = stopping  # a process being stopped takes nothing over
        self._group = group_key(keys, fuser)
        self.me = Member(time.time_ns() if born is None else born, str(session.zid()))
        self._event = event
        self._lock = threading.Lock()
        self._others: dict[str, Member] = {}  # the other live members this process knows, by token key
        self._eligible = False  # leads if it is the oldest: from the end of its start (a standby: below)
        self._deadline = time.monotonic() + grace if standby else None
        self._started = False  # until its links have settled, no process leads
        self.leads = False
        self.takeovers = 0  # times it began to lead (its start included)
        self.yielded = 0  # times it stopped leading for an older member
        self._token = session.liveliness().declare_token(f"{self._group}/{self.me}")
        self._sub = session.liveliness().declare_subscriber(f"{self._group}/*", self._on_member, history=True)
        links, waited = settle(session, stopping, link_wait, quiet)
        for reply in session.liveliness().get(f"{self._group}/*", timeout=1.0):  # every linked peer's, surely
            if reply.ok is not None:
                self._on_member(reply.ok)
        with self._lock:
            older = self._older()
            self.joins = older is not None  # a leader ran already: this process stands by, joining its stream
            self._eligible = not standby or bool(self._others)
            self._started = True
        if older is not None:
            self._event(f"an older member {older} of {fuser} runs: standing by ({links} links, settled in "
                        f"{waited:.2f} s)")
        self._decide(f"leading: no older member on {links} links, settled in {waited:.2f} s" if not standby
                     else "the oldest of the members known: leading")

    def members(self) -> list[Member]:
        """The live members this process knows, itself included, oldest first."""
        with self._lock:
            return sorted([self.me, *self._others.values()])

    def _older(self) -> Member | None:
        return min((m for m in self._others.values() if m < self.me), default=None)

    def _on_member(self, sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        member = Member.parse(key.rpartition("/")[2])
        if member is None or member == self.me:
            return
        with self._lock:
            if sample.kind == zenoh.SampleKind.PUT:
                self._others[key] = member
                self._eligible |= self._started  # a standby that knows another member knows enough to rank itself
            elif self._others.pop(key, None) is None:
                return
        self._decide("the leader is gone: taking over" if sample.kind == zenoh.SampleKind.DELETE
                     else "the oldest of the members known: leading")

    def check(self) -> None:
        """A standby that has seen no other member within its grace leads (called by the loop)."""
        if self._deadline is not None and not self._eligible and time.monotonic() > self._deadline:
            with self._lock:
                self._eligible = True
            self._decide("no leader within the start grace: leading")

    def _decide(self, why: str) -> None:
        """Lead if this process is the oldest member it knows (and may lead), else not."""
        with self._lock:
            older = self._older()
            if older is not None and self.leads:
                self.leads = False
                self.yielded += 1
                why = f"yielded to {older}: an older member of the same fuser"
            elif older is None and not self.leads and self._eligible and not self._stopping.is_set():
                self.leads = True
                self.takeovers += 1
            else:
                return
        self._event(why)

    def undeclare(self) -> None:
        """Give up the watch and the member token (the node does, when it closes)."""
        self._sub.undeclare()
        self._token.undeclare()


@dataclass(frozen=True)
class Rebuilt:
    """What a joining standby took from its leader's picture (:func:`rebuild`)."""

    t: float  # the picture's time: every measurement up to its scan is in the state taken
    seq: int  # the seq of the leader's latest estimate: the standby numbers on from it
    tracks: tuple[str, ...]


def rebuild(method: Any, picture: dict | None) -> Rebuilt | None:
    """Start ``method`` from the leader's ``picture`` (:func:`services.picture.pictures`):
    a one-target method's track filter from its one track; a many-target method's table
    (GNN, frame by frame) from the tracks the picture's latest frame reports, confirmed,
    under their ids, the id counter after them; a regional fuser's
    (:class:`~fusion.regional.RegionalStage`) likewise from its region's picture, which
    the system fuser keeps (:class:`services.picture.RegionPictures`). None (and
    ``method`` untouched) for any other method, a method that holds a track already, or
    a picture without tracks."""
    if picture is None or not picture["tracks"]:
        return None
    if isinstance(method, RegionalStage):  # a region's picture holds the tracks of its latest frame alone
        latest = picture["tracks"]
        if not _seed_region(method.fuser, latest):
            return None
        method = method.fuser.method
    else:
        latest = [tr for tr in picture["tracks"] if tr["t"] == picture["t"]]  # (the others were no longer reported)
        if isinstance(method, CentralisedMethod):
            if len(latest) != 1 or latest[0]["id"] != method.track or method.filter is not None:
                return None
            track = latest[0]
            method.start(np.asarray(track["x"], dtype=float), np.asarray(track["P"], dtype=float), track["t"])
        elif not (isinstance(method, MultiTargetMethod) and _seed_table(method, latest)):
            return None
    return Rebuilt(picture["t"] + method.group_tol, max(tr["seq"] for tr in latest), tuple(tr["id"] for tr in latest))


def _seed_region(fuser: RegionalFuser, tracks: list[dict]) -> bool:
    """A regional fuser's table seeded (:func:`_seed_table`) with its region's tracks,
    each under its id in the region (``west.T3``: ``T3``), and the fuser told that its
    frames published them (:meth:`~fusion.regional.RegionalFuser.resume`)."""
    prefix = f"{fuser.region.name}."
    if not (isinstance(fuser.method, MultiTargetMethod) and all(tr["id"].startswith(prefix) for tr in tracks)
            and _seed_table(fuser.method, [{**tr, "id": tr["id"][len(prefix):]} for tr in tracks])):
        return False
    fuser.resume(tr["id"] for tr in tracks)
    return True


def _seed_table(method: MultiTargetMethod, tracks: list[dict]) -> bool:
    """A GNN frame-by-frame tracker's empty table filled with ``tracks``, confirmed."""
    tracker = method.tracker
    if not isinstance(tracker, MultiTargetTracker) or method.config.association != "gnn" or len(method.table):
        return False
    table = tracker.table
    numbers = {tr["id"]: table.ids.number(tr["id"]) for tr in tracks}
    for tr in sorted(tracks, key=lambda tr: numbers[tr["id"]]):
        x, P = np.asarray(tr["x"], dtype=float), np.asarray(tr["P"], dtype=float)
        track = table.add(Track(tracker.updater.new_filter(x, P, tr["t"]), Estimate(tr["t"], x, P, method.name,
                                                                                      "centre")))
        tracker.taken_over(track)
        track.id = tr["id"]
    table.ids.issued = max(numbers.values())
    return True
