"""In-process evaluation: the same scenario, the same generators, the same estimators,
without processes or Zenoh.

:func:`merged_measurements` produces exactly the stream a distributed fuser feeds its
method — every sensor's events from its own generator, merged in ``(t, sensor, seq)``
order — so for a given scenario and seed the in-process estimates equal those of a
distributed run.
"""

from __future__ import annotations

import heapq
from typing import Iterable

from fusion.methods import make_method
from fusion.types import Estimate, Measurement


def merged_measurements(scenario, run: int = 0, sensors: Iterable[str] | None = None) -> list[Measurement]:
    from sensors_sim import sensor_events

    streams = [
        (ev.measurement for ev in sensor_events(scenario, sid, run=run) if ev.measurement is not None)
        for sid in (sensors if sensors is not None else scenario.sensors)
    ]
    return list(heapq.merge(*streams, key=lambda m: m.order_key))


def run_method(scenario, method_name: str, overrides: dict | None = None, run: int = 0,
               measurements: list[Measurement] | None = None) -> list[Estimate]:
    """Run one method over one Monte Carlo run; returns every estimate it emits."""
    method = make_method(method_name, {**scenario.tracker, **(overrides or {})})
    stream = measurements if measurements is not None else merged_measurements(scenario, run)
    out: list[Estimate] = []
    t_prev = None
    for m in stream:
        if t_prev is not None and m.t > t_prev:
            out.extend(method.advance(t_prev))  # as a watermark would, at each scan boundary
        out.extend(method.process(m))
        t_prev = m.t
    out.extend(method.finish())
    return out
