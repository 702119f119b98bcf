"""Uplinks (``local/<node>``) and downlinks (``feedback/<node>``) of the distributed
topologies on the wire (:mod:`fusion.network` has their meaning).

An uplink travels as one or two ordinary messages from the local tracker, in this
order: its estimate (kind ``track``, or ``prediction``) and/or its raw measurement
(a measurement kind, ``sensor`` = the node's sensor). DDHNV's uplink carries both, as
two messages with the same ``t`` and consecutive ``seq``. With many targets, a node
that deletes a local track says so by a ``track`` message of that track whose
``extra`` holds ``drop`` (``[1.0]``; absent otherwise). A downlink is a ``track``
message from the fuser whose ``extra`` holds ``init`` (``[1.0]`` or ``[0.0]``) and,
for DDHNV, ``sensor_x``/``sensor_P``; with many targets, ``drop`` (``[1.0]``, absent
otherwise) asks the node to delete its local track ``track``. The fuser's feedback *horizon* is a
``watermark`` message on the same key.

Extras on the wire are arrays, so a local estimate's ``feedback_t`` (a time or None)
travels as ``[t]`` or not at all, and whether it is a prediction is its kind.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from fusion.network import Downlink, Uplink
from fusion.types import Estimate

from .messages import Message, encode, encode_estimate, encode_measurement, to_estimate, to_measurement


def _estimate_to_wire(e: Estimate) -> tuple[Estimate, str]:
    extra = dict(e.extra)
    prediction = bool(extra.pop("prediction", e.nis is None and "prior_x" in extra))
    if "feedback_t" in extra:
        fb = extra.pop("feedback_t")
        if fb is not None:
            extra["feedback_t"] = [float(fb)]
    return dataclasses.replace(e, extra=extra), ("prediction" if prediction else "track")


def estimate_from_wire(msg: Message) -> Estimate:
    e = to_estimate(msg)
    extra = dict(e.extra)
    if "prior_x" in extra:  # a local tracker's report
        fb = np.asarray(extra.get("feedback_t", []), dtype=float).ravel()
        extra["feedback_t"] = float(fb[0]) if fb.size else None
        extra["prediction"] = msg.kind == "prediction"
    return dataclasses.replace(e, extra=extra)


def encode_uplink(u: Uplink, src: str, seq: int) -> list[bytes]:
    """The messages of one uplink; they use ``seq``, ``seq + 1``."""
    out = []
    if u.estimate is not None:
        e, kind = _estimate_to_wire(u.estimate)
        if u.drop:
            e = dataclasses.replace(e, extra={**e.extra, "drop": [1.0]})
        out.append(encode_estimate(e, src, seq, kind))
        seq += 1
    if u.measurement is not None:
        out.append(encode_measurement(dataclasses.replace(u.measurement, seq=seq), src))
    return out


def uplink(node: str, msg: Message, measurement: Message | None = None) -> Uplink:
    """An uplink from its estimate message (``track``/``prediction``), its measurement
    message, or both."""
    if msg.kind in ("track", "prediction"):
        e = estimate_from_wire(msg)
        extra = dict(e.extra)
        drop = _flag(extra.pop("drop", None))
        m = to_measurement(measurement) if measurement is not None else None
        return Uplink(msg.t, node, msg.seq, dataclasses.replace(e, extra=extra), m, drop)
    return Uplink(msg.t, node, msg.seq, None, to_measurement(msg))


def encode_downlink(d: Downlink, src: str, seq: int) -> bytes:
    extra = {**d.estimate.extra, "init": [1.0 if d.init else 0.0]}
    if d.drop:
        extra["drop"] = [1.0]
    return encode_estimate(dataclasses.replace(d.estimate, extra=extra), src, seq, "track")


def downlink(node: str, msg: Message) -> Downlink:
    e = to_estimate(msg)
    extra = dict(e.extra)
    init, drop = _flag(extra.pop("init", None)), _flag(extra.pop("drop", None))
    return Downlink(node, dataclasses.replace(e, extra=extra), init, drop)


def _flag(value) -> bool:
    """A flag extra (``[1.0]`` set; ``[0.0]`` or absent not)."""
    v = np.asarray([] if value is None else value, dtype=float).ravel()
    return bool(v.size and v[0] == 1.0)


def horizon_message(src: str, seq: int, t: float) -> bytes:
    return encode("watermark", src, seq, t, final=False)


__all__ = ["encode_uplink", "uplink", "encode_downlink", "downlink", "horizon_message", "estimate_from_wire"]
