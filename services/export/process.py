"""The exporter process: ``fused`` in, a sink (the GeoJSON file, CoT to TAK) out.

Like the recorder, an exporter is a listener (:func:`services.listener.run_listener`:
a bounded inbox of ``BACKLOG_MAX`` samples, overflow counted as ``dropped`` and never
pushed back to the fuser; live, recovery; mid-session, the fuser's current picture
first). Its sink, :class:`Exporter`, feeds each sample to the
:class:`~services.export.tracks.TrackTable`, hands every accepted update to the format
:class:`Sink` and lets it do its periodic work (write the file, re-send sensors,
reconnect). A fuser that restarts is just more samples on ``fused``. On SIGINT/SIGTERM
what is queued is still handed over, the sink writes or sends a last time and the
session closes; exit 0. Which sinks there are: :data:`services.export.outputs.OUTPUTS`.
"""

from __future__ import annotations

import logging
import queue
import time
from pathlib import Path

from fusion.mtt import AssociationConfig
from schemas import KeySpace, Message
from schemas.keys import DEFAULT_FUSER
from sensors_sim.spec import SENSOR_KINDS

from ..geo import frame_of
from ..listener import run_listener
from ..node import ListenerInbox, ZenohOptions
from . import cot, geojson
from .tracks import MAX_SKEW_S, Bearings, TrackTable, sensor_sites

log = logging.getLogger("zfusion")

BACKLOG_MAX = 10_000  # samples queued from Zenoh's threads: seconds of fused output
BEARINGS_MAX = 1_000  # DF bearings queued for the CoT exporter between two ticks
WRITE_PERIOD_S = 0.1  # the GeoJSON file is rewritten at most this often (and after the last update)


class Sink:
    """Where the picture goes. ``site`` (a loaded site or scenario) gives the frame and
    the sensors; ``live``: times are UTC, not scenario seconds."""

    def __init__(self, site, live: bool):
        self.frame = frame_of(site.origin)
        self.sensors = sensor_sites(site)
        self.live = live

    def start(self, node, table: TrackTable) -> None:
        """The process's session is open (a sink may subscribe to more, e.g. DF bearings)."""

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
    """Sends what :class:`~services.export.cot.CoTPicture` says: an event per update (and
    the track's trail), each DF station's latest bearing as a line, the sensors at start
    and every ``stale_s / 2``. The bearings come on the DF stations' ``meas`` keys, into an
    inbox of their own (``BEARINGS_MAX``, overflow counted as ``bearings_dropped``). A
    track's uid names its deployment, its fuser and its id there
    (``zfusion.<deployment>.<fuser>.<track>``: two fusers' tracks never share one), a
    sensor's its deployment (``zfusion.<deployment>.sensor.<id>``)."""

    def __init__(self, sender, site, deployment: str, types: cot.Types, stale_s: float, live: bool,
                 fuser: str = DEFAULT_FUSER):
        super().__init__(site, live)
        self.sender = sender
        self.picture = cot.CoTPicture(self.frame, self.sensors, deployment, types, stale_s, live, fuser)
        self.df = {sid: s.kind for sid, s in site.sensors.items() if SENSOR_KINDS[s.kind].measures == "bearing"}
        self._inbox = ListenerInbox(BEARINGS_MAX)
        self._bearings: Bearings | None = None
        self.sent = 0

    def start(self, node, table: TrackTable) -> None:
        self._bearings = Bearings(table)
        for sid in self.df:
            node.subscribe(node.keys.meas(sid), self._inbox)

    def _send(self, events: list[tuple[str, bytes]]) -> None:
        for uid, data in events:
            self.sent += self.sender.send(uid, data)

    def update(self, table: TrackTable, e) -> None:
        self._send(self.picture.update(e, time.time(), time.monotonic()))

    def tick(self, table: TrackTable, final: bool = False) -> None:
        self.sender.poll()
        now, mono = time.time(), time.monotonic()
        latest = {}  # station -> its latest bearing of this tick
        for _ in range(BEARINGS_MAX):
            try:
                m = self._bearings.offer(*self._inbox.get_nowait())
            except queue.Empty:
                break
            if m is not None and m.sensor in self.df:
                latest[m.sensor] = m
        for m in latest.values():
            self._send(self.picture.bearing(m.sensor, self.df[m.sensor], m.site, float(m.z[0]), m.t,
                                            table.tracks.values(), now, mono))
        self._send(self.picture.tick(table.tracks, now, mono))

    def counters(self) -> dict[str, float]:
        return {"sent": self.sent, "send_failed": self.sender.failed, "bearings_dropped": self._inbox.dropped}

    def close(self) -> None:
        self.sender.close()
        self._inbox.close()


class Exporter:
    """An exporter as a listener's sink (:func:`services.listener.run_listener`): the
    fused picture (:class:`~services.export.tracks.TrackTable`) and the :class:`Sink` that
    every accepted update goes to. ``site`` is the loaded site or scenario; ``live``: a
    session on UTC time (no end; data may lead the clock by ``max_skew`` s)."""

    def __init__(self, node, site, sink: Sink, live: bool, max_skew: float):
        association, _ = AssociationConfig.split(getattr(site, "tracker", {}) or {})
        self.table = TrackTable(node.keys, node.reject, None if live else getattr(site, "duration", None),
                                association.delete_misses if association is not None else AssociationConfig.delete_misses,
                                clock=time.time if live else None, max_skew=max_skew)
        self.sink = sink
        sink.start(node, self.table)
        self.events = self.table.intake.events
        self.t = 0.0  # the latest update's time

    def offer(self, key: str, data: bytes, utc: float | None) -> Message | None:
        e = self.table.offer(key, data)
        if e is None:
            return None
        self.t = max(self.t, e.t)
        self.sink.update(self.table, e)
        return self.table.msg

    def tick(self, final: bool = False) -> None:
        self.sink.tick(self.table, final)

    def done(self) -> bool:
        return False  # until stopped

    def now(self) -> float:
        return self.t

    def counters(self) -> dict[str, float]:
        return self.sink.counters()

    def close(self) -> None:
        self.sink.close()


def run(process_id: str, keys: KeySpace, zopts: ZenohOptions, site, make_sink, live: bool = False,
        max_skew: float = MAX_SKEW_S, fuser: str = DEFAULT_FUSER) -> int:
    """Run until SIGINT/SIGTERM. ``site`` is the loaded site or scenario; ``make_sink()``
    builds the sink once the process has its session (so a bad sink is an error at start);
    ``live``: a session on UTC time (no end; data may lead the clock by ``max_skew`` s);
    ``fuser``: the fuser whose tracks it exports."""
    return run_listener(process_id, "exporter", keys, zopts,
                        lambda node: Exporter(node, site, make_sink(), live, max_skew),
                        subscribe=keys.fused(fuser), fuser=fuser, live=live, backlog=BACKLOG_MAX, counted="updates")
