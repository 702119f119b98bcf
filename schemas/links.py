"""Uplinks (``local/<node>``) and downlinks (``feedback/<node>``) of the distributed
topologies on the wire: :class:`fusion.network.Uplink` as one ``uplink`` message and
:class:`fusion.network.Downlink` as one ``downlink`` message (their fields and checks:
:mod:`schemas.messages`, docs/design.md "Wire format"). The fuser's feedback *horizon*
is a ``watermark`` message on the node's ``feedback/`` key.

In memory a local report keeps what the fusion rules read in ``Estimate.extra``
(``prior_x``, ``prior_P``, ``KH``, ``feedback_t`` — a time or ``None`` — and
``prediction``); on the wire they are typed fields of the uplink's ``estimate``
(``feedback_t`` left out when ``None``), and a downlink's DDHNV update
(``extra["sensor_x"]``, ``extra["sensor_P"]``) is two fields of the downlink. The
uplink's ``t`` and ``seq`` are its estimate's time and its measurement's.
"""

from __future__ import annotations

from typing import Any

from fusion.network import Downlink, Uplink
from fusion.types import Estimate

from .messages import Message, encode, measurement_fields, measurement_of

_REPORT = ("prior_x", "prior_P", "KH", "prediction", "feedback_t")
_IMM_REPORT = ("imm_xs", "imm_Ps", "imm_prior_xs", "imm_prior_Ps", "imm_loglik")
_DDHNV = ("sensor_x", "sensor_P")
_IMM_PRIOR = ("imm_xs", "imm_Ps", "imm_mu")


def _estimate_map(e: Estimate, extras: tuple[str, ...], inside: bool) -> dict[str, Any]:
    """The estimate's map; its ``extra`` may hold ``extras`` only, which go into the map
    if ``inside`` (an uplink's), else beside it (a downlink's)."""
    unknown = set(e.extra) - set(extras)
    if unknown:
        raise ValueError(f"a link estimate carries no {', '.join(sorted(unknown))} (takes {', '.join(extras)})")
    d = {"track": e.track, "node": e.node, "method": e.method, "x": e.x, "P": e.P}
    if e.nis is not None:
        d["nis"] = float(e.nis)
    if e.nis_dof is not None:
        d["nis_dof"] = int(e.nis_dof)
    if e.existence is not None:
        d["existence"] = float(e.existence)
    for k in extras if inside else ():
        v = e.extra.get(k)
        if v is not None:
            d[k] = bool(v) if k == "prediction" else float(v) if k == "feedback_t" else v
    return d


def _estimate(b: dict, t: float, extra: dict) -> Estimate:
    return Estimate(t, b["x"], b["P"], b["method"], b["node"], b["track"], b["nis"], b["nis_dof"], extra,
                    b["existence"])


def encode_uplink(u: Uplink, src: str, seq: int) -> bytes:
    """One uplink as one message (``t`` = ``u.t``, ``seq`` as given)."""
    payload: dict[str, Any] = {}
    if u.estimate is not None:
        if u.estimate.t != u.t:
            raise ValueError(f"uplink at t = {u.t!r} carries an estimate at t = {u.estimate.t!r}")
        payload["estimate"] = _estimate_map(u.estimate, _REPORT + _IMM_REPORT, inside=True)
    if u.measurement is not None:
        m = u.measurement
        if m.t != u.t:
            raise ValueError(f"uplink at t = {u.t!r} carries a measurement at t = {m.t!r}")
        payload["measurement"] = {"kind": m.kind, **measurement_fields(m)}
    if u.drop:
        payload["drop"] = True
    return encode("uplink", src, seq, u.t, **payload)


def uplink(msg: Message) -> Uplink:
    """The :class:`~fusion.network.Uplink` of an ``uplink`` message; its node is the
    estimate's ``node`` or the measurement's ``sensor`` (checked to agree)."""
    b = msg.body
    e = m = None
    if b["estimate"] is not None:
        eb = b["estimate"]
        extra = {} if "prior_x" not in eb else {
            "prior_x": eb["prior_x"], "prior_P": eb["prior_P"], "KH": eb["KH"],
            "feedback_t": eb["feedback_t"], "prediction": eb["prediction"]}
        extra.update({k: eb[k] for k in _IMM_REPORT if k in eb})
        e = _estimate(eb, msg.t, extra)
    if b["measurement"] is not None:
        m = measurement_of(b["measurement"]["kind"], b["measurement"], msg.t, msg.seq)
    node = e.node if e is not None else m.sensor
    return Uplink(msg.t, node, msg.seq, e, m, b["drop"])


def encode_downlink(d: Downlink, src: str, seq: int) -> bytes:
    e = d.estimate
    payload: dict[str, Any] = {"estimate": _estimate_map(e, _DDHNV + _IMM_PRIOR, inside=False), "init": bool(d.init)}
    if d.drop:
        payload["drop"] = True
    payload.update({k: e.extra[k] for k in _DDHNV + _IMM_PRIOR if e.extra.get(k) is not None})
    return encode("downlink", src, seq, e.t, **payload)


def downlink(node: str, msg: Message) -> Downlink:
    """The :class:`~fusion.network.Downlink` to ``node`` (the key's) of a ``downlink`` message."""
    b = msg.body
    extra = {} if b["sensor_x"] is None else {"sensor_x": b["sensor_x"], "sensor_P": b["sensor_P"]}
    extra.update(b["models"])
    return Downlink(node, _estimate(b["estimate"], msg.t, extra), b["init"], b["drop"])


def horizon_message(src: str, seq: int, t: float) -> bytes:
    return encode("watermark", src, seq, t, final=False)


__all__ = ["encode_uplink", "uplink", "encode_downlink", "downlink", "horizon_message"]
