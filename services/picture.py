"""The current picture: the fuser's live tracks, for whoever joins mid-session.

A process that starts late (a recorder, a display, ``zfusion picture``) has missed the
tracks the fuser has been publishing on ``fused``. The fuser therefore keeps, per live
track, the bytes of the last ``fused`` message it published about it, and answers a
Zenoh query on ``picture/<fuser>`` (:meth:`schemas.KeySpace.picture`) with one reply per track
— exactly those bytes, so a late joiner decodes them as it decodes ``fused`` — and a
last reply, a ``watermark`` of the picture's time (the latest fused time): "this is
the picture as of t", so that an empty picture is an answer too.

A track is live until its stream has gone ``delete_misses`` frames without reporting
it (a frame: a distinct time of the fuser's output; :class:`Reports`), the rule the
trackers delete by: a confirmed track is reported every frame until deleted. Memory:
one message per live track, plus one frame number per track followed.

The system fuser of the regional topology also keeps the picture of each region's
stream (:class:`RegionPictures`: each track the region publishes, as the last
estimate ``regional/<region>`` carried for it, a ``track`` message from the region,
until a frame of the region drops its id) and answers ``picture/<region>`` with it: a
regional fuser serves no picture of its own, and the one restarted with no standby to
join rebuilds its tracks from its region's picture (:mod:`services.leader`), where a
joining standby rebuilds from its leader's. Memory: one message per track each region
publishes (until a frame drops it).
"""

from __future__ import annotations

import json
import math
import sys
import threading
import time
from typing import TYPE_CHECKING, Callable, Iterable

import zenoh

from fusion.mtt import AssociationConfig
from schemas import KeySpace, SchemaError, decode, encode, encode_estimate, to_estimate
from schemas.keys import DEFAULT_FUSER
from fusion.types import Estimate

if TYPE_CHECKING:
    from fusion.regional import RegionalFrame


class Reports:
    """Which tracks one stream reported in which of its frames (a frame: a distinct time
    of its reports), to tell when a track has gone."""

    def __init__(self) -> None:
        self.t = -math.inf  # the current frame's time
        self.frame = 0
        self._last: dict[str, int] = {}  # track -> the frame it was last reported in

    def report(self, track: str, t: float, misses: int) -> list[str]:
        """Note a report of ``track`` at ``t``; returns the tracks that a new frame shows
        to have missed ``misses`` frames (forgotten from now on)."""
        gone = []
        if t > self.t:
            self.t = t
            self.frame += 1
            gone = [p for p, f in self._last.items() if self.frame - 1 - f >= misses]
            for p in gone:
                del self._last[p]
        self._last[track] = max(self._last.get(track, 0), self.frame)
        return gone

    def forget(self, track: str) -> bool:
        """Stop following ``track``; whether it was followed."""
        return self._last.pop(track, None) is not None


class Picture:
    """The fuser's live tracks (module docstring). :meth:`published` is called by the
    fuser's loop, :meth:`replies` by Zenoh's query thread: a lock keeps them apart."""

    def __init__(self, src: str, delete_misses: float = AssociationConfig.delete_misses):
        self.src = src
        self.delete_misses = delete_misses
        self.t = -math.inf
        self._reports = Reports()
        self._last: dict[str, bytes] = {}  # track id -> its last fused message
        self._lock = threading.Lock()

    def published(self, e: Estimate, data: bytes) -> None:
        """The fuser published ``data`` (the encoding of ``e``) on ``fused``."""
        with self._lock:
            for gone in self._reports.report(e.track, e.t, self.delete_misses):
                self._last.pop(gone, None)
            self._last[e.track] = data
            self.t = max(self.t, e.t)

    def forget(self, track: str) -> None:
        """``track`` has gone from its stream (its fuser says so): no longer in the picture."""
        with self._lock:
            self._reports.forget(track)
            self._last.pop(track, None)

    def replies(self) -> list[bytes]:
        """What a query is answered with: every live track's message, then the watermark."""
        with self._lock:
            tracks = list(self._last.values())
            t = self.t
        return tracks + [encode("watermark", self.src, 0, t if math.isfinite(t) else 0.0, final=False)]

    def serve(self, session: zenoh.Session, keys: KeySpace):
        """Declare the queryable (the caller undeclares it, or closes the session)."""
        key = keys.picture(self.src)

        def on_query(query: zenoh.Query) -> None:
            for data in self.replies():
                query.reply(key, data)

        return session.declare_queryable(key, on_query)


class RegionPictures:
    """The system fuser's picture of each region's stream (module docstring): one
    :class:`Picture` a region, under the region's name, fed the frames the system fuser
    takes from ``regional/<region>`` (:meth:`frame`, from its intake). A frame carries
    the confirmed tracks its region's tracker reported in it (a sweep tracker's: those a
    sector updated) and the ids its region no longer publishes, which leave the picture
    at once; no frame count ends a track here (a sweep's track goes unreported for
    frames), so the picture is the region's published tracks, each as last carried. A
    frame older than the picture (a publisher's cache given again) changes nothing."""

    def __init__(self, regions: Iterable[str]):
        self.pictures = {r: Picture(r, delete_misses=math.inf) for r in regions}

    def frame(self, f: "RegionalFrame", seq: int) -> None:
        """Region ``f.region``'s frame ``f``, the message ``seq`` of its stream."""
        picture = self.pictures.get(f.region)
        if picture is None or f.t < picture.t:
            return
        for e in f.tracks:
            picture.published(e, encode_estimate(e, f.region, seq))
        for track in f.dropped:
            picture.forget(track)

    def serve(self, session: zenoh.Session, keys: KeySpace) -> list:
        """Declare each region's queryable (the caller undeclares them, or closes the session)."""
        return [p.serve(session, keys) for p in self.pictures.values()]


def _track_or_none(data: bytes):
    try:
        return decode(data)
    except SchemaError:
        return None  # a bad reply is no part of the picture


class Request:
    """A late joiner's non-blocking request: asked again every ``every`` seconds (a new
    peer learns of the fuser's queryable by gossip, which takes a moment) until a fuser
    answers, the caller no longer needs it (:meth:`cancel`: it has seen ``fused`` itself)
    or ``patience`` seconds have passed. Each track's message goes to ``on_track``, on
    Zenoh's thread, as it comes."""

    def __init__(self, session: zenoh.Session, keys: KeySpace, fuser: str, on_track: Callable[[bytes], None],
                 patience: float = 5.0, every: float = 0.5, clock: Callable[[], float] = time.monotonic):
        self.session, self.keys, self.fuser, self.on_track = session, keys, fuser, on_track
        self.every, self.clock = every, clock
        self.deadline = clock() + patience
        self.answered = False
        self.tracks = 0  # tracks taken from the picture (a status counter: a late joiner shows it has begun)
        self._next = -math.inf

    def cancel(self) -> None:
        self.deadline = -math.inf

    def poll(self) -> None:
        """Ask if it is time to (call it from the process's loop)."""
        now = self.clock()
        if self.answered or now >= self.deadline or now < self._next:
            return
        self._next = now + self.every

        def on_reply(reply: zenoh.Reply) -> None:
            msg = _track_or_none(reply.ok.payload.to_bytes()) if reply.ok is not None else None
            if msg is None or self.answered:
                return
            if msg.kind == "watermark":
                self.answered = True
            elif msg.kind == "track":
                self.on_track(reply.ok.payload.to_bytes())
                self.tracks += 1

        self.session.get(self.keys.picture(self.fuser), on_reply, timeout=self.every,
                         consolidation=zenoh.ConsolidationMode.NONE)


def query(session: zenoh.Session, keys: KeySpace, timeout: float = 2.0, fuser: str = DEFAULT_FUSER) -> dict | None:
    """The picture of ``fuser`` as a JSON-ready dict ``{"t", "fuser", "tracks": [...]}``,
    or None if it does not answer within ``timeout``."""
    found = pictures(session, keys, fuser, timeout)
    return found[0] if found else None


def pictures(session: zenoh.Session, keys: KeySpace, fuser: str, timeout: float = 2.0) -> list[dict]:
    """The pictures of the fusers that answer a query of ``fuser`` (``*``: every fuser),
    one dict each in the order of their ids, as soon as at least one has answered whole;
    empty if none does within ``timeout`` (asked again every 0.25 s meanwhile: see
    :class:`Request`)."""
    deadline = time.monotonic() + timeout
    while True:
        left = deadline - time.monotonic()
        if left <= 0:
            return []
        answers = documents(reply.ok.payload.to_bytes() for reply in session.get(
            keys.picture(fuser), timeout=min(left, 0.25), consolidation=zenoh.ConsolidationMode.NONE)
            if reply.ok is not None)
        complete = [answers[f] for f in sorted(answers) if answers[f]["t"] is not None]
        if complete:
            return complete
        time.sleep(min(0.05, max(0.0, deadline - time.monotonic())))


def documents(replies: Iterable[bytes]) -> dict[str, dict]:
    """Replies to a picture query, as one dict per answering fuser (by id): ``t`` (None
    until its watermark has come) and its ``tracks``, each as JSON-ready values. Several
    processes may answer for one id (a leader and its standby; a system fuser and its
    standby, for a region): a track is taken once, its latest message (by time, then
    seq), and ``t`` is the latest watermark."""
    answers: dict[str, dict] = {}
    tracks: dict[str, dict[str, dict]] = {}
    for data in replies:
        msg = _track_or_none(data)
        if msg is None:
            continue
        doc = answers.setdefault(msg.src, {"t": None, "fuser": msg.src, "tracks": []})
        if msg.kind == "watermark":
            doc["t"] = msg.t if doc["t"] is None else max(doc["t"], msg.t)
        elif msg.kind == "track":
            e = to_estimate(msg)
            mine = tracks.setdefault(msg.src, {})
            if e.track in mine and (mine[e.track]["t"], mine[e.track]["seq"]) >= (e.t, msg.seq):
                continue
            mine[e.track] = {"id": e.track, "t": e.t, "x": e.x.tolist(), "P": e.P.tolist(),
                             "method": e.method, "node": e.node, "nis": e.nis, "nis_dof": e.nis_dof,
                             "existence": e.existence, "seq": msg.seq}
    for src, doc in answers.items():
        doc["tracks"] = list(tracks.get(src, {}).values())
    return answers


def main(keys: KeySpace, zopts, fuser: str, timeout: float) -> int:
    """``zfusion picture``: print each answering fuser's picture as one line of JSON (exit
    1 if none answers)."""
    with zenoh.open(zopts.to_config()) as session:
        docs = pictures(session, keys, fuser, timeout)
    if not docs:
        print(f"zfusion picture: no fuser answered on {keys.picture(fuser)} within {timeout:g} s; check --connect "
              f"(the fabric's endpoint), --deployment and --fuser", file=sys.stderr)
        return 1
    for doc in docs:
        print(json.dumps(doc))
    return 0
