"""The exporter process: ``fused`` in, a sink (the GeoJSON file, CoT to TAK) out.

It joins Zenoh like the recorder and is, like it, only a listener: its subscription is
served by Zenoh's threads into a bounded queue (``BACKLOG_MAX``; overflow is counted as
``dropped``, never pushed back to the fuser). The loop feeds each sample to the
:class:`~services.export.tracks.TrackTable`, hands every accepted update to the sink and
lets the sink do its periodic work (write the file, re-send sensors, reconnect). A fuser
that restarts is just more samples on ``fused``; an exporter that starts (or restarts)
mid-session begins with the fuser's current picture (:class:`services.picture.Request`).
On SIGINT/SIGTERM the loop drains what is queued, the sink writes or sends a last time
and the session closes; exit 0.
"""

from __future__ import annotations

import logging
import queue
import time
from pathlib import Path

from fusion.mtt import AssociationConfig
from schemas import KeySpace

from ..geo import frame_of
from ..node import ListenerInbox, Node, Recovery, ZenohOptions
from ..picture import Request
from . import cot, geojson
from .tracks import MAX_SKEW_S, TrackTable, sensor_sites

log = logging.getLogger("zfusion")

BACKLOG_MAX = 10_000  # samples queued from Zenoh's threads: seconds of fused output
BURST_MAX = 1_000  # samples handled between two ticks, so a sustained stream still gets its file written
WRITE_PERIOD_S = 0.1  # the GeoJSON file is rewritten at most this often (and after the last update)


class Sink:
    """Where the picture goes. ``site`` (a loaded site or scenario) gives the frame and
    the sensors; ``live``: times are UTC, not scenario seconds."""

    def __init__(self, site, live: bool):
        self.frame = frame_of(site.origin)
        self.sensors = sensor_sites(site)
        self.live = live

    def update(self, table: TrackTable, e) -> None:
        """An accepted update ``e``, already in ``table``."""

    def tick(self, table: TrackTable, final: bool = False) -> None:
        """Periodic work (``final``: the process is stopping)."""

    def counters(self) -> dict[str, float]:
        return {}

    def close(self) -> None:
        pass


class GeoJSONSink(Sink):
    """Rewrites ``path`` with the whole picture after updates (at most every ``WRITE_PERIOD_S``)."""

    def __init__(self, path: Path, site, live: bool):
        super().__init__(site, live)
        self.path = path
        self.writes = 0
        self._dirty = True  # the sensors are worth a file before any track
        self._last = -float("inf")

    def update(self, table: TrackTable, e) -> None:
        self._dirty = True

    def tick(self, table: TrackTable, final: bool = False) -> None:
        if self._dirty and (final or time.monotonic() - self._last >= WRITE_PERIOD_S):
            geojson.write_atomic(self.path, geojson.feature_collection(table.tracks.values(), self.sensors,
                                                                       self.frame, self.live))
            self._dirty = False
            self._last = time.monotonic()
            self.writes += 1

    def counters(self) -> dict[str, float]:
        return {"written": self.writes}


class CoTSink(Sink):
    """Sends an event per update, and the sensors at start and every ``stale_s / 2``."""

    def __init__(self, sender, site, deployment: str, types: cot.Types, stale_s: float, live: bool):
        super().__init__(site, live)
        self.sender = sender
        self.deployment = deployment
        self.types = types
        self.stale_s = stale_s
        self.sent = 0
        self._sensors_at = -float("inf")

    def uid(self, what: str) -> str:
        return f"zfusion.{self.deployment}.{what}"

    def update(self, table: TrackTable, e) -> None:
        data = cot.track_event(e, self.frame, self.uid(e.track), self.types, time.time(), self.stale_s, self.live)
        self.sent += self.sender.send(self.uid(e.track), data)

    def tick(self, table: TrackTable, final: bool = False) -> None:
        self.sender.poll()
        if time.monotonic() - self._sensors_at >= self.stale_s / 2:
            self._sensors_at = time.monotonic()
            for sid, (kind, enu) in self.sensors.items():
                uid = self.uid(f"sensor.{sid}")
                data = cot.sensor_event(sid, kind, enu, self.frame, uid, self.types, time.time(), self.stale_s)
                self.sent += self.sender.send(uid, data)

    def counters(self) -> dict[str, float]:
        return {"sent": self.sent, "send_failed": self.sender.failed}

    def close(self) -> None:
        self.sender.close()


def run(process_id: str, keys: KeySpace, zopts: ZenohOptions, site, make_sink, live: bool = False,
        max_skew: float = MAX_SKEW_S) -> int:
    """Run until SIGINT/SIGTERM. ``site`` is the loaded site or scenario; ``make_sink()``
    builds the sink once the process has its session (so a bad sink is an error at start);
    ``live``: a session on UTC time (no end; data may lead the clock by ``max_skew`` s)."""
    duration = None if live else getattr(site, "duration", None)
    association, _ = AssociationConfig.split(getattr(site, "tracker", {}) or {})
    inbox = ListenerInbox(BACKLOG_MAX)

    with Node(process_id, "exporter", keys, zopts) as node:
        table = TrackTable(keys, node.reject, duration,
                           association.delete_misses if association is not None else AssociationConfig.delete_misses,
                           clock=time.time if live else None, max_skew=max_skew)
        sink = make_sink()
        try:
            recovery = None
            if live:  # the live fuser's estimates sent while this exporter was cut off from it come back
                recovery = Recovery(node.processes_by_session())
                node.recovering_subscriber(keys.fused(), inbox, recovery.on_miss)
            else:
                node.subscribe(keys.fused(), inbox)
            late_join = Request(node.session, keys, lambda data: inbox.put((keys.fused(), data)))
            node.announce()
            node.publish_status("ready")
            last_status = time.monotonic()
            t = 0.0

            def recovered() -> dict[str, float]:
                return recovery.counters() if recovery is not None else {}

            def handle(key: str, data: bytes) -> None:
                nonlocal t
                late_join.cancel()  # the fuser's stream (or its picture's first reply): no need to ask again
                e = table.offer(key, data)
                if e is not None:
                    t = max(t, e.t)
                    if recovery is not None:
                        recovery.arrived(table.src, e.t, time.time())
                    node.count("updates")
                    sink.update(table, e)

            while not node.stop.is_set():
                try:
                    handle(*inbox.get(timeout=0.1))
                    for _ in range(BURST_MAX):  # the rest of a burst, then one tick
                        handle(*inbox.get_nowait())
                except queue.Empty:
                    pass
                late_join.poll()
                sink.tick(table)
                if time.monotonic() - last_status >= 1.0:
                    node.publish_status("running", t, extra={**sink.counters(), "dropped": inbox.dropped,
                                                             "backlog": inbox.qsize(), **recovered()})
                    last_status = time.monotonic()
            while True:  # stopping: what is queued is still part of the picture
                try:
                    handle(*inbox.get_nowait())
                except queue.Empty:
                    break
            sink.tick(table, final=True)
            node.publish_status("stopped", t, extra={**sink.counters(), "dropped": inbox.dropped, **recovered()})
        finally:
            sink.close()
    return 0
