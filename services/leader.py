"""Who publishes the fused output when a hot standby runs beside the fuser.

A standby (``zfusion fuser --standby``, ``zfusion run --standby``) is a second fuser on
the same inputs. The fuser's ordering is deterministic (:mod:`services.ordering`: the
merged stream is released by the sources' watermarks, not by arrival time), so both
hold the same tracks with the same ids; only the *leader* publishes (estimates,
downlinks, the horizon), under the fuser's identity, with the seq numbers it would have
used, so a consumer sees one stream.

Leadership is a Zenoh liveliness token on ``<deployment>/leader/<fuser>``, held by the
leader's session: it vanishes when that session closes, including on kill -9 (the
peers see the link drop). A fuser started without ``--standby`` leads unless a leader
already holds the token (a restarted fuser while its standby leads: it becomes the new
standby). A standby watches the token and takes it when it goes (a DELETE), or when
none has appeared within ``grace`` seconds of its start (no fuser to stand by for).

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
whole; docs/reliability.md says what is equal, what converges and how fast.
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
from fusion.tracking.manager import MultiTargetTracker
from fusion.tracking.table import CONFIRMED, Track
from fusion.types import Estimate
from schemas import KeySpace


LINK_WAIT_S = 5.0  # how long the election waits for the session's first link (none: a process alone)


def leader_key(keys: KeySpace, fuser: str) -> str:
    """The liveliness token of the leader of ``fuser``'s output."""
    return f"{keys.prefix}/leader/{fuser}"


class Leadership:
    """This process's part in the election of one fuser's leader (module docstring).

    ``leads`` is read by the fuser's loop before each publication; ``event`` is called
    (from Zenoh's thread or the loop's) with a line for the status events."""

    def __init__(self, session: zenoh.Session, keys: KeySpace, fuser: str, standby: bool, grace: float,
                 event: Callable[[str], None], stopping: threading.Event):
        self._session = session
        self._stopping = stopping  # a process being stopped takes nothing over
        self._key = leader_key(keys, fuser)
        self._event = event
        self._lock = threading.Lock()
        self._token = None
        self._seen = False  # a leader's token was seen since the start
        self._deadline = time.monotonic() + grace if standby else None
        self.leads = False
        self.takeovers = 0
        linked = time.monotonic() + LINK_WAIT_S  # a query before the session reaches its peers sees no token
        while not (any(True for _ in session.info.peers_zid()) or any(True for _ in session.info.routers_zid())) \
                and time.monotonic() < linked and not stopping.is_set():
            time.sleep(0.02)
        held = any(r.ok is not None for r in session.liveliness().get(self._key, timeout=1.0))
        self.joins = held  # a leader ran already: this process stands by, joining its stream mid-way
        if not standby and not held:
            self._take("leading")
        elif not standby:
            self._event(f"a leader holds {self._key}: standing by")
        self._sub = session.liveliness().declare_subscriber(self._key, self._on_token, history=True)

    def _on_token(self, sample: zenoh.Sample) -> None:
        if sample.kind == zenoh.SampleKind.PUT:
            self._seen = True
        elif not self.leads:  # the leader's session is gone
            self._take("the leader is gone: taking over")

    def check(self) -> None:
        """A standby that has seen no leader within its grace leads (called by the loop)."""
        if self._deadline is not None and not self.leads and not self._seen and time.monotonic() > self._deadline:
            self._take("no leader within the start grace: leading")

    def _take(self, why: str) -> None:
        with self._lock:
            if self.leads or self._stopping.is_set():
                return
            self._token = self._session.liveliness().declare_token(self._key)
            self.leads = True
            self.takeovers += 1
        self._event(why)

    def undeclare(self) -> None:
        """Give up the token and the watch (the node does, when it closes)."""
        self._sub.undeclare()
        if self._token is not None:
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
    under their ids, the id counter after them. None (and ``method`` untouched) for any
    other method, a method that holds a track already, or a picture without tracks."""
    if picture is None or not picture["tracks"]:
        return None
    latest = [tr for tr in picture["tracks"] if tr["t"] == picture["t"]]  # (the others were no longer reported)
    if isinstance(method, CentralisedMethod):
        if len(latest) != 1 or latest[0]["id"] != method.track or method.filter is not None:
            return None
        track = latest[0]
        method.start(np.asarray(track["x"], dtype=float), np.asarray(track["P"], dtype=float), track["t"])
    elif not (isinstance(method, MultiTargetMethod) and _seed_table(method, latest)):
        return None
    return Rebuilt(picture["t"] + method.group_tol, max(tr["seq"] for tr in latest), tuple(tr["id"] for tr in latest))


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
        track.logic.status, track.logic.hits = CONFIRMED, track.logic.rule.confirm_m
        track.id = tr["id"]
    table.ids.issued = max(numbers.values())
    return True
