"""The links of the distributed topologies on the wire: every message type of
:mod:`fusion.links` is one message kind, a node's on ``local/<node>`` (:data:`UP`), the
centre's on ``feedback/<node>`` (:data:`DOWN`); the fuser's feedback *horizon* is a
``watermark`` on the node's ``feedback/`` key. The fields and checks of each kind:
:mod:`schemas.messages`, docs/design.md "Links of the distributed topologies".

A type is its kind, so the meaning travels in the envelope (``kind``) and nothing is
carried twice: an up message's time and counter are the envelope's ``t`` and ``seq``
(its estimate's time is ``t``), a down message's node is its key's. Arrays keep their
shapes (per-model covariances m×n×n), optional fields are absent, never null: every
message round-trips bit for bit.
"""

from __future__ import annotations

from typing import Any, Callable

from fusion.links import (Downlink, Drop, DropTrack, Feedback, Gaussian, Init, InitRequest, LocalReport,
                          MeasurementReport, ModelStates, ModelTerms, PredictionReport, Uplink)
from fusion.regional import RegionalFrame
from fusion.types import Estimate, Measurement

from .messages import Message, _estimate_payload, _plain, encode, measurement_fields, measurement_of


def _measurement(m: Measurement, t: float) -> dict[str, Any]:
    if m.t != t:
        raise ValueError(f"a link message at t = {t!r} carries a measurement at t = {m.t!r}")
    return {"kind": m.kind, **measurement_fields(m)}


def _state(e: Estimate, track: str, existence: bool = False) -> dict[str, Any]:
    """A link's track, method and state (``e.extra`` travels on no link; ``existence``
    on a local report only, JIPDA's)."""
    if e.extra:
        raise ValueError(f"a link estimate carries no {', '.join(sorted(e.extra))}")
    if e.existence is not None and not existence:
        raise ValueError("only a local report's estimate carries an existence")
    d = {"track": track, "method": e.method, "x": e.x, "P": e.P}
    if e.existence is not None:
        d["existence"] = float(e.existence)
    return d


def _optional(**fields: Any) -> dict[str, Any]:
    return {k: v for k, v in fields.items() if v is not None}


def _terms(m: ModelTerms | None) -> dict | None:
    return None if m is None else {"xs": m.xs, "Ps": m.Ps, "prior_xs": m.prior_xs, "prior_Ps": m.prior_Ps,
                                   "loglik": m.loglik}


# Up: type -> (kind, payload) and kind -> type ------------------------------------------
def _local_report(u: LocalReport) -> dict[str, Any]:
    e = u.estimate
    return {"node": u.node, **_state(e, e.track, existence=True), "prior_x": u.prior.x, "prior_P": u.prior.P,
            "KH": u.KH,
            **_optional(nis=None if e.nis is None else float(e.nis), nis_dof=None if e.nis_dof is None else int(e.nis_dof),
                        feedback_t=None if u.feedback_t is None else float(u.feedback_t), models=_terms(u.models))}


def _prediction_report(u: PredictionReport) -> dict[str, Any]:
    e = u.estimate
    if e.nis is not None or e.nis_dof is not None:
        raise ValueError("a prediction report's estimate has no NIS")
    return {"node": u.node, **_state(e, e.track), "measurement": _measurement(u.measurement, u.t),
            **_optional(feedback_t=None if u.feedback_t is None else float(u.feedback_t), models=_terms(u.models))}


_UP: dict[type, tuple[str, Callable[[Any], dict[str, Any]]]] = {
    InitRequest: ("init_request", lambda u: {"node": u.node, "measurement": _measurement(u.measurement, u.t)}),
    LocalReport: ("local_report", _local_report),
    PredictionReport: ("prediction_report", _prediction_report),
    MeasurementReport: ("measurement_report", lambda u: {"node": u.node, "measurement": _measurement(u.measurement, u.t)}),
    Drop: ("drop", lambda u: {"node": u.node, "track": u.track}),
}


def encode_uplink(u: Uplink, src: str, seq: int) -> bytes:
    """A node's message as its kind (``t`` = ``u.t``; ``seq``: the sender's counter)."""
    kind, payload = _UP[type(u)]
    return encode(kind, src, seq, u.t, **payload(u))


def _estimate(b: dict, t: float, node: str) -> Estimate:
    return Estimate(t, b["x"], b["P"], b["method"], node, b["track"], b.get("nis"), b.get("nis_dof"),
                    existence=b.get("existence"))


def _measurement_of(b: dict, msg: Message) -> Measurement:
    return measurement_of(b["kind"], b, msg.t, msg.seq)


def _terms_of(b: dict | None) -> ModelTerms | None:
    return None if b is None else ModelTerms(b["xs"], b["Ps"], b["prior_xs"], b["prior_Ps"], b["loglik"])


_FROM_UP: dict[str, Callable[[Message], Uplink]] = {
    "init_request": lambda m: InitRequest(m.t, m.body["node"], m.seq, _measurement_of(m.body["measurement"], m)),
    "local_report": lambda m: LocalReport(
        m.t, m.body["node"], m.seq, _estimate(m.body, m.t, m.body["node"]), Gaussian(m.body["prior_x"], m.body["prior_P"]),
        m.body["KH"], m.body["feedback_t"], _terms_of(m.body["models"])),
    "prediction_report": lambda m: PredictionReport(
        m.t, m.body["node"], m.seq, _estimate(m.body, m.t, m.body["node"]), _measurement_of(m.body["measurement"], m),
        m.body["feedback_t"], _terms_of(m.body["models"])),
    "measurement_report": lambda m: MeasurementReport(m.t, m.body["node"], m.seq,
                                                      _measurement_of(m.body["measurement"], m)),
    "drop": lambda m: Drop(m.t, m.body["node"], m.seq, m.body["track"]),
}


def uplink(msg: Message) -> Uplink:
    """The :mod:`fusion.links` message of a node's message (its ``seq`` the envelope's)."""
    return _FROM_UP[msg.kind](msg)


# Down ----------------------------------------------------------------------------------
def _feedback(d: Feedback) -> dict[str, Any]:
    models = None if d.models is None else {"xs": d.models.xs, "Ps": d.models.Ps, "mu": d.models.mu}
    update = None if d.update is None else {"x": d.update.x, "P": d.update.P}
    return {**_state(d.estimate, d.track), **_optional(update=update, models=models)}


_DOWN: dict[type, tuple[str, Callable[[Any], dict[str, Any]]]] = {
    Init: ("init", lambda d: _state(d.estimate, d.track)),
    Feedback: ("feedback", _feedback),
    DropTrack: ("drop_track", lambda d: {"track": d.track}),
}


def encode_downlink(d: Downlink, src: str, seq: int) -> bytes:
    """The centre's message to ``d.node`` (who is the key's, not a field) as its kind."""
    kind, payload = _DOWN[type(d)]
    return encode(kind, src, seq, d.t if isinstance(d, DropTrack) else d.estimate.t, **payload(d))


def _centre_estimate(m: Message) -> Estimate:
    return _estimate(m.body, m.t, "centre")


_FROM_DOWN: dict[str, Callable[[str, Message], Downlink]] = {
    "init": lambda node, m: Init(node, _centre_estimate(m)),
    "feedback": lambda node, m: Feedback(
        node, _centre_estimate(m), None if m.body["update"] is None else Gaussian(m.body["update"]["x"], m.body["update"]["P"]),
        None if m.body["models"] is None else ModelStates(m.body["models"]["xs"], m.body["models"]["Ps"],
                                                          m.body["models"]["mu"])),
    "drop_track": lambda node, m: DropTrack(node, m.t, m.body["track"]),
}


def downlink(node: str, msg: Message) -> Downlink:
    """The :mod:`fusion.links` message to ``node`` (the key's) of a centre's message."""
    return _FROM_DOWN[msg.kind](node, msg)


def horizon_message(src: str, seq: int, t: float) -> bytes:
    return encode("watermark", src, seq, t, final=False)


__all__ = ["encode_uplink", "uplink", "encode_downlink", "downlink", "horizon_message"]


def encode_regional_frame(f: RegionalFrame, src: str, seq: int) -> bytes:
    """A regional fuser's frame as a ``regional_frame`` message on ``fused/<region>``
    (the region is its sender ``src``)."""
    return encode("regional_frame", src, seq, f.t, tracks=[_plain({"t": e.t, **_estimate_payload(e)}) for e in f.tracks],
                  dropped=list(f.dropped))


def regional_frame(msg: Message) -> RegionalFrame:
    """A ``regional_frame`` message back as the frame its region's fuser made."""
    b = msg.body
    tracks = tuple(Estimate(t=e["t"], x=e["x"], P=e["P"], method=e["method"], node=e["node"], track=e["track"],
                            nis=e["nis"], nis_dof=e["nis_dof"], extra=dict(e["extra"]), existence=e["existence"],
                            identity=e["identity"]) for e in b["tracks"])
    return RegionalFrame(msg.src, msg.t, tracks, tuple(b["dropped"]))
