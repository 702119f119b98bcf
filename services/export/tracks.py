"""The fused tracks as an exporter keeps them: sans-I/O, bytes off ``fused`` in.

:meth:`TrackTable.offer` takes a sample (key and bytes) through the intake every
consumer uses (:class:`services.intake.Intake`: another key, a sample that fails to
decode, a kind other than ``track``, a time before the session's start or beyond its end
(scenario runs: duration + 1 s; live sessions, on UTC: more than ``max_skew`` s ahead of
the clock), a repeat (same source, seq and bytes)) and returns the estimate it brings,
or ``None`` once the sample is counted and dropped (:class:`~services.node.RejectLog`,
rate-limited); so is an update older than the track's latest. A dropped sample leaves the table as if
it never arrived.

A track is gone once the fused stream has had ``delete_misses`` frames (distinct times)
without it, the rule of the fuser's own picture (:class:`services.picture.Reports`); a fuser restarted
with other tracks therefore replaces the old ones within a few frames. Memory: the live
tracks (at most ``MAX_TRACKS``, oldest update dropped first) and the intake's recent
sequence numbers.
"""

from __future__ import annotations

import datetime as dt
from collections import OrderedDict
from typing import Callable

import numpy as np

from fusion.mtt import AssociationConfig
from fusion.types import Estimate, Measurement
from schemas import KeySpace, Message, to_estimate, to_measurement

from ..intake import Intake
from ..live import ClockGuard
from ..node import RejectLog
from ..picture import Reports

MAX_TRACKS = 4096
MAX_SKEW_S = 5.0  # live: how far ahead of this host's clock a time of validity may be


class TrackTable:
    """The latest fused estimate of every live track.

    Args:
        keys: the deployment's key space (samples must come on its ``fused`` key).
        reject: where dropped samples are counted.
        duration: a scenario's duration (s), beyond which data is "future"; None for none.
        delete_misses: frames without a track before it is gone.
        clock: a live session's clock (UTC POSIX seconds), which data may lead by at most
            ``max_skew`` s; None in a scenario run.
    """

    def __init__(self, keys: KeySpace, reject: RejectLog, duration: float | None = None,
                 delete_misses: int = AssociationConfig.delete_misses, clock: Callable[[], float] | None = None,
                 max_skew: float = MAX_SKEW_S):
        self.reject = reject
        self.intake = Intake.of_scenario(keys, reject, ["fused"], duration, dedup=True,
                                         clock=ClockGuard(max_skew) if clock is not None else None)
        self.msg: Message | None = None  # the message of the last estimate taken
        self.keys, self.duration, self.max_skew = keys, duration, max_skew
        self.clock = clock
        self.delete_misses = delete_misses
        self.tracks: OrderedDict[str, Estimate] = OrderedDict()  # by track id, oldest update first
        self._reports = Reports()

    def offer(self, key: str, data: bytes) -> Estimate | None:
        sample = self.intake.offer(key, data, self.clock() if self.clock is not None else None)
        if sample is None:
            return None
        msg = sample.msg
        e = to_estimate(msg)
        last = self.tracks.get(e.track)
        if last is not None and e.t < last.t:
            self.reject(msg.src, "out-of-order", f"{e.track} at t = {e.t:g} s is older than its {last.t:g} s")
            return None
        for gone in self._reports.report(e.track, e.t, self.delete_misses):
            self.tracks.pop(gone, None)
        self.tracks[e.track] = e
        self.tracks.move_to_end(e.track)
        self.msg = msg
        while len(self.tracks) > MAX_TRACKS:
            old, _ = self.tracks.popitem(last=False)
            self._reports.forget(old)
        return e


class Bearings:
    """DF bearings off ``meas`` for a picture's lines (sans I/O): :meth:`offer` takes a
    sample through the intake under ``table``'s rules (its session's times and clock) and
    returns a ``bearing`` measurement, or None (a refused sample is counted in the table's
    reject log; another kind, a watermark, is skipped)."""

    def __init__(self, table: TrackTable):
        self.table = table
        self.intake = Intake.of_scenario(table.keys, table.reject, ["meas"], table.duration,
                                         clock=ClockGuard(table.max_skew) if table.clock is not None else None)

    def offer(self, key: str, data: bytes) -> Measurement | None:
        sample = self.intake.offer(key, data, self.table.clock() if self.table.clock is not None else None)
        if sample is None or sample.msg.kind != "bearing":
            return None
        return to_measurement(sample.msg)


def is_fix(e: Estimate) -> bool:
    """An emitter fix: a state on the map plane, ``[e n]``, or ``[e n ve vn]`` for a moving
    emitter (``motion = "cv"``); every other state is a 3D track."""
    return e.x.size in (2, 4)


def utc_iso(t: float) -> str:
    """POSIX seconds as ISO 8601 UTC with milliseconds, e.g. ``2026-12-01T20:14:33.491Z``."""
    return dt.datetime.fromtimestamp(t, dt.timezone.utc).isoformat(timespec="milliseconds").replace("+00:00", "Z")


def session_time(t: float, live: bool) -> float | str:
    """A time of validity as an export states it: ISO 8601 UTC in a live session (``t`` is
    POSIX seconds there), scenario seconds otherwise."""
    return utc_iso(t) if live else float(t)


def sensor_sites(scenario) -> dict[str, tuple[str, np.ndarray]]:
    """Sensor id -> (kind, ENU position) of a site or scenario (a moving site: where it
    starts; a mobile station whose position comes with its measurements: left out)."""
    return {sid: (s.kind, s.site.position(float(s.start))) for sid, s in scenario.sensors.items()
            if s.site is not None}
