"""The Rerun side of a recording: the stream that queues rows and sends them as
columns, the blueprint that lays out its panels, and opening it onto a file (and a
viewer).

A row is a few archetypes of one entity at one time, kept as their classes and
component lists (:data:`Part`) until :meth:`Recording.send_rows` sends each entity's
queued rows with one ``send_columns`` per run of rows of the same shape: building
archetypes row by row is what made per-row logging slow. Timeline ``sim_time``
(scenario seconds) or, in a live session, ``utc`` (a timestamp timeline).
"""

from __future__ import annotations

import logging
import os
import sys
from pathlib import Path
from typing import Any, Sequence

import rerun as rr
import rerun.blueprint as rrb

from ..scoring import GOSPA_CUTOFF
from . import map as recorder_map

log = logging.getLogger("zfusion")


TIMELINE = "sim_time"


LIVE_TIMELINE = "utc"  # live sessions: t is UTC POSIX seconds, a timestamp timeline


VIEWER_PORT = 9876  # Rerun's default: a second run reuses a viewer that is already open


def blueprint(df: bool = False, many: bool = False, geo: bool = False, timeline: str = TIMELINE,
              map_zoom: float | None = None) -> rrb.Blueprint:
    """Scene (with ``geo``: beside the map, at ``map_zoom``) | error and consistency plots
    (many targets: the picture's GOSPA, targets missed and false tracks, NIS) | event log,
    jamming and counters."""
    scene = rrb.Spatial3DView(origin="world", name="Map (ENU; DF on the plane z = 0)" if df else "Scene (ENU)")
    if many:
        plots = rrb.Vertical(
            rrb.TimeSeriesView(origin="metrics/gospa", name=f"GOSPA (m; c = {GOSPA_CUTOFF:g} m, p = 2)"),
            rrb.TimeSeriesView(origin="metrics/picture", name="Targets missed, false tracks"),
            rrb.TimeSeriesView(origin="metrics/nis", name="NIS vs 95% χ² bounds"),
        )
    else:
        plots = rrb.Vertical(
            rrb.TimeSeriesView(origin="metrics/error_pos", name="Position error (m)"),
            rrb.TimeSeriesView(origin="metrics/nees", name="NEES vs 95% χ² bounds"),
            rrb.TimeSeriesView(origin="metrics/nis", name="NIS vs 95% χ² bounds"),
        )
    side = rrb.Vertical(
        rrb.TextLogView(origin="status", name="Events"),
        rrb.TimeSeriesView(origin="jamming", name="Jamming and contamination"),
        rrb.TimeSeriesView(origin="status", name="Process counters"),
        row_shares=[2, 1, 1],
    )
    columns = [scene, recorder_map.view(zoom=map_zoom), plots, side] if geo else [scene, plots, side]
    return rrb.Blueprint(
        rrb.Horizontal(*columns, column_shares=[3, 3, 2, 2] if geo else [3, 2, 2]),
        rrb.BlueprintPanel(state="collapsed"),
        rrb.SelectionPanel(state="collapsed"),
        rrb.TimePanel(state="collapsed", timeline=timeline),
    )


# One archetype of a row, not built yet: its class and its components, each a list of
# instances (a list of one broadcasts to all). Building archetypes row by row is what
# made per-row logging slow; a column of many rows is converted at once.
Part = tuple[type, dict[str, Sequence]]


def part(archetype: type, **components: Sequence) -> Part:
    return archetype, components


def ui_points(points: float) -> list[float]:
    """A radius in UI points, as a one-instance component."""
    return [float(rr.components.Radius.ui_points(points))]


class Recording(rr.RecordingStream):
    """A recording stream that queues rows and sends them as columns.

    :meth:`row` queues one row of an entity at a time on the ``sim_time`` timeline (a
    live session's: the ``utc`` timestamp timeline);
    :meth:`send_rows` sends each entity's queued rows, in order, with one
    ``send_columns`` per run of rows made of the same archetypes and components (each
    row stays one row, as ``log`` would make it). ``flush`` and ``disconnect`` send
    first, so whatever is flushed is complete. Static entities and the recording's name
    are remembered (one per entity: a few), so that :meth:`hand_over` can start the next
    file of a rotation (:mod:`services.rotation`) with them.
    """

    def __init__(self, app: str, recording_id: str | None = None, live: bool = False):
        super().__init__(app, recording_id=recording_id)
        self._rows: dict[str, list[tuple[float, tuple[Part, ...]]]] = {}
        self.queued = 0
        self.live = live
        self.timeline = LIVE_TIMELINE if live else TIMELINE
        self._time = "timestamp" if live else "duration"
        self._statics: list[tuple[Any, tuple[Any, ...]]] = []
        self._name: str | None = None

    def log(self, entity_path: Any, *entities: Any, static: bool = False, **kwargs: Any) -> None:
        if static:
            self._statics.append((entity_path, entities))
        super().log(entity_path, *entities, static=static, **kwargs)

    def send_recording_name(self, name: str) -> None:
        self._name = name
        super().send_recording_name(name)

    def hand_over(self, new: "Recording", at: float) -> None:
        """Rotation: the rows queued from time ``at`` on go to ``new``, with every static
        entity and the name; the rest are sent here, and this file is closed."""
        for path, rows in self._rows.items():
            later = [r for r in rows if r[0] >= at]
            if later:
                rows[:] = [r for r in rows if r[0] < at]
                new._rows[path] = later
                new.queued += len(later)
        if self._name is not None:
            new.send_recording_name(self._name)
        for entity_path, entities in self._statics:
            new.log(entity_path, *entities, static=True)
        self.flush()
        self.disconnect()

    def row(self, path: str, t: float, parts: tuple[Part, ...]) -> None:
        self._rows.setdefault(path, []).append((t, parts))
        self.queued += 1

    def send_rows(self) -> None:
        rows, self._rows, self.queued = self._rows, {}, 0
        for path, queued in rows.items():
            start = 0
            while start < len(queued):
                shape = _shape(queued[start][1])
                end = start + 1
                while end < len(queued) and _shape(queued[end][1]) == shape:
                    end += 1
                self._send(path, queued[start:end])
                start = end

    def _send(self, path: str, rows: list[tuple[float, tuple[Part, ...]]]) -> None:
        columns: list[Any] = []
        for i, (archetype, components) in enumerate(rows[0][1]):
            for name in components:
                values: list[Any] = []
                lengths = []
                for _, parts in rows:
                    v = parts[i][1][name]
                    values.extend(v)
                    lengths.append(len(v))
                columns.extend(archetype.columns(**{name: values}).partition(lengths))
        index = rr.TimeColumn(self.timeline, **{self._time: [t for t, _ in rows]})
        self.send_columns(path, indexes=[index], columns=columns)

    def flush(self, **kwargs: Any) -> None:
        self.send_rows()
        super().flush(**kwargs)

    def disconnect(self) -> None:
        self.send_rows()
        super().disconnect()


def _shape(parts: tuple[Part, ...]) -> tuple:
    return tuple((a, tuple(c)) for a, c in parts)


def has_display() -> bool:
    if sys.platform in ("darwin", "win32"):
        return True
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


def open_recording(rrd_path: str, app: str = "zfusion", spawn: bool = False, df: bool = False,
                   port: int = VIEWER_PORT, many: bool = False, geo: bool = False,
                   recording_id: str | None = None, live: bool = False,
                   map_zoom: float | None = None) -> tuple[Recording, bool]:
    """A recording stream writing to ``rrd_path`` and, with ``spawn`` and a display, to a
    Rerun viewer it starts (or one already listening on ``port``). Returns the stream and
    whether a viewer is attached. ``live``: on the ``utc`` timestamp timeline; ``geo``:
    with the map panel, at ``map_zoom``."""
    rec = Recording(app, recording_id, live=live)
    bp = blueprint(df, many, geo, rec.timeline, map_zoom)
    sinks: list[Any] = [rr.FileSink(rrd_path)]
    live = False
    if spawn and not has_display():
        log.warning("zfusion record: --spawn: no display (DISPLAY and WAYLAND_DISPLAY are unset), so no viewer; "
                    "recording to %s only. View it afterwards with `zfusion view %s`, or from this headless machine "
                    "with `rerun --serve-web %s` and a browser through an SSH tunnel (docs/viewing.md).",
                    rrd_path, rrd_path, rrd_path)
    elif spawn:
        exe = Path(sys.executable).with_name("rerun")
        try:
            rr.spawn(port=port, connect=False, executable_path=str(exe) if exe.exists() else None, recording=rec)
            sinks.append(rr.GrpcSink(f"rerun+http://127.0.0.1:{port}/proxy"))
            live = True
        except Exception as e:  # no viewer is no reason to lose the recording
            log.warning("zfusion record: --spawn: could not start the Rerun viewer (%s); recording to %s only",
                        e, rrd_path)
    rec.set_sinks(*sinks, default_blueprint=bp)
    return rec, live


def safe_flush(rec: Recording, timeout: float) -> None:
    """Flush without letting a lost viewer (gRPC sink) stop the recorder; the file sink
    is flushed regardless."""
    try:
        rec.flush(timeout_sec=timeout)
    except Exception as e:  # e.g. "gRPC has been unable to connect": the viewer was closed
        log.debug("recorder: flush: %s", e)
