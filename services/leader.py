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

What a standby that *starts* late cannot have: the tracks of the data it never heard.
It joins mid-stream like a restarted fuser (:mod:`services.fuser`), so until its tracks
and the leader's have the same history (a track confirmed after both joined), a
takeover gives new ids for the older tracks. docs/reliability.md says what was measured.
"""

from __future__ import annotations

import threading
import time
from typing import Callable

import zenoh

from schemas import KeySpace


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
        held = any(r.ok is not None for r in session.liveliness().get(self._key, timeout=1.0))
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
