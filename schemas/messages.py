"""Wire messages: msgpack maps with an envelope and a validated payload.

Every message is a msgpack map::

    {"v": 1, "kind": "<kind>", "src": "<process id>", "seq": <int>, "t": <float>, ...payload}

``t`` is the time of validity in seconds of scenario time. Arrays travel as (nested)
lists of floats — msgpack packs Python floats as float64, so values round-trip bit for
bit, and a list is as readable to other tools as it is to us. Shapes are validated.

:func:`decode` is strict: it checks the schema version, the kind, every field's type,
finiteness, range (angles, std > 0, ...) and shape, and raises :class:`SchemaError`
naming the field and a short *cause* (used to count and rate-limit rejections).
:func:`encode` validates too, so a process can never publish what others would reject.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Callable

import msgpack
import numpy as np

from fusion.measurement.kinds import KINDS as _KINDS
from fusion.types import Estimate, Identity, Measurement

from .keys import check_id

SCHEMA_VERSION = 1
MAX_BYTES = 1 << 20  # 1 MiB: far above any real message, stops memory abuse
MAX_DIM = 64  # largest state / array dimension accepted

MEASUREMENT_KINDS = tuple(_KINDS)
# The links of the distributed topologies, one kind per message type of fusion.links:
# node -> centre on local/<node>, centre -> node on feedback/<node> (schemas/links.py)
UP_KINDS = ("init_request", "local_report", "prediction_report", "measurement_report", "drop")
DOWN_KINDS = ("init", "feedback", "drop_track")
KINDS = MEASUREMENT_KINDS + ("watermark", "track", "regional_frame", *UP_KINDS, *DOWN_KINDS, "jam_state", "truth",
                              "status")
FRAME_MAX = 2048  # tracks (and dropped ids) of one regional frame: well under MAX_BYTES


class SchemaError(ValueError):
    """A message failed validation. ``cause`` is short and stable (for counters)."""

    def __init__(self, cause: str, field: str | None, detail: str):
        self.cause = cause
        self.field = field
        self.detail = detail
        where = f"field '{field}': " if field else ""
        super().__init__(f"{cause}: {where}{detail}")


@dataclass(frozen=True)
class Message:
    """A decoded, validated message: envelope plus payload ``body`` (kind-specific)."""

    kind: str
    src: str
    seq: int
    t: float
    body: dict[str, Any]
    v: int = SCHEMA_VERSION


# ---------------------------------------------------------------- field checkers


def _num(d: dict, f: str, *, lo: float = -math.inf, hi: float = math.inf, lo_open: bool = False,
         hi_open: bool = False, optional: bool = False) -> float | None:
    if f not in d or d[f] is None:
        if optional:
            return None
        raise SchemaError("missing", f, "required")
    x = d[f]
    if isinstance(x, bool) or not isinstance(x, (int, float)):
        raise SchemaError("type", f, f"expected a number, got {type(x).__name__}")
    x = float(x)
    if not math.isfinite(x):
        raise SchemaError("non-finite", f, f"{x!r} is not finite")
    if x < lo or x > hi or (lo_open and x == lo) or (hi_open and x == hi):
        lb = "(" if lo_open else "["
        rb = ")" if hi_open else "]"
        raise SchemaError("range", f, f"{x!r} outside {lb}{lo:g}, {hi:g}{rb}")
    return x


# Ids that passed check_id. A deployment has a few dozen, seen on every message; the
# fast paths accept only ids found here and leave any other to the strict checks.
_VALID_IDS: set[str] = set()
_VALID_IDS_MAX = 4096


def _remember_id(x: str) -> None:
    if len(_VALID_IDS) >= _VALID_IDS_MAX:  # bounded: a flood of new ids cannot grow it
        _VALID_IDS.clear()
    _VALID_IDS.add(x)


def _int(d: dict, f: str, *, lo: int = 0, hi: int = 2**63 - 1) -> int:
    if f not in d:
        raise SchemaError("missing", f, "required")
    x = d[f]
    if isinstance(x, bool) or not isinstance(x, int):
        raise SchemaError("type", f, f"expected an integer, got {type(x).__name__}")
    if not lo <= x <= hi:
        raise SchemaError("range", f, f"{x} outside [{lo}, {hi}]")
    return x


def _str(d: dict, f: str, *, ident: bool = False, choices: tuple[str, ...] | None = None,
         optional: bool = False) -> str | None:
    if f not in d or d[f] is None:
        if optional:
            return None
        raise SchemaError("missing", f, "required")
    x = d[f]
    if not isinstance(x, str):
        raise SchemaError("type", f, f"expected a string, got {type(x).__name__}")
    if ident and x not in _VALID_IDS:
        try:
            check_id(x, f)
        except ValueError as e:
            raise SchemaError("value", f, str(e)) from None
        _remember_id(x)
    if choices is not None and x not in choices:
        raise SchemaError("value", f, f"{x!r} not one of {', '.join(choices)}")
    return x


def _bool(d: dict, f: str, *, default: bool | None = None) -> bool:
    if f not in d:
        if default is not None:
            return default
        raise SchemaError("missing", f, "required")
    if not isinstance(d[f], bool):
        raise SchemaError("type", f, f"expected a boolean, got {type(d[f]).__name__}")
    return d[f]


def _array(d: dict, f: str, shape: tuple[int | None, ...], *, optional: bool = False,
           rows: int = MAX_DIM) -> np.ndarray | None:
    """A finite float array of the given shape (``None`` = any size up to MAX_DIM; the
    first dimension up to ``rows``)."""
    if f not in d or d[f] is None:
        if optional:
            return None
        raise SchemaError("missing", f, "required")
    raw = d[f]
    if not isinstance(raw, (list, tuple)):
        raise SchemaError("type", f, f"expected a list, got {type(raw).__name__}")
    try:
        a = np.array(raw, dtype=float)
    except (TypeError, ValueError):
        raise SchemaError("type", f, "expected a (nested) list of numbers") from None
    if raw and any(isinstance(v, bool) for v in (raw if a.ndim == 1 else ())):
        raise SchemaError("type", f, "booleans are not numbers")
    if a.ndim != len(shape) or any(s is not None and s != n for s, n in zip(shape, a.shape)) \
            or any(n > (rows if i == 0 else MAX_DIM) for i, n in enumerate(a.shape)) or a.size == 0:
        want = "×".join("n" if s is None else str(s) for s in shape)
        raise SchemaError("shape", f, f"expected shape {want}, got {'×'.join(map(str, a.shape)) or 'scalar'}")
    if not np.all(np.isfinite(a)):
        raise SchemaError("non-finite", f, "contains NaN or inf")
    return a


def _no_extra(d: dict, allowed: set[str]) -> None:
    extra = set(d) - allowed
    if extra:
        raise SchemaError("unknown-field", sorted(map(str, extra))[0], "not part of this message kind")


# ---------------------------------------------------------------- payload schemas

ENVELOPE = {"v", "kind", "src", "seq", "t"}
# Per-source counts a live status may give besides ``rejected`` (non-negative ints).
SOURCE_COUNTS = frozenset({"oosm", "stale", "recovered", "missed"})
def _measurement_fields(kind: str) -> frozenset[str]:
    """The payload fields of a measurement of ``kind``: ``sensor``, ``site``, and per
    component its value and its std (:mod:`fusion.measurement.components`)."""
    comps = _KINDS[kind].components
    return frozenset({"sensor", "site"} | {c.name for c in comps} | {c.std_field for c in comps})


def _check_measurement(kind: str, d: dict, envelope: frozenset | set = ENVELOPE) -> dict:
    k = _KINDS[kind]
    body: dict[str, Any] = {"sensor": _str(d, "sensor", ident=True), "site": _array(d, "site", (3,))}
    for c in k.components:
        body[c.name] = _num(d, c.name, lo=c.lo, hi=c.hi, lo_open=c.lo_open, hi_open=c.hi_open)
        body[c.std_field] = _num(d, c.std_field, lo=0.0, lo_open=True)
    if k.own_noise and d.get("corr") is not None:
        body["corr"] = _corr(d, "corr", k.n_z)
    if "identity" in d:
        body["identity"] = _identity(d)
    _no_extra(d, envelope | _measurement_fields(kind) | ({"corr"} if k.own_noise else set()) | {"identity"})
    return body


_HEX = frozenset("0123456789abcdef")
_CALLSIGN = frozenset("ABCDEFGHIJKLMNOPQRSTUVWXYZ0123456789 ")  # ICAO's flight identification set
ADDRESS_MAX = 8  # characters: six hex digits, or a source's non-ICAO form ("~" and six)


def _identity(d: dict) -> Identity:
    """``identity``: a map with an optional ``address`` (1–8 lower-case hex digits, a
    non-ICAO one led by ``~``) and an optional ``callsign`` (1–8 characters A–Z, 0–9 and
    space, as ICAO's flight identification), at least one of them; present or absent,
    never null."""
    raw = d["identity"]
    if type(raw) is not dict:
        raise SchemaError("type", "identity", f"expected a map, got {type(raw).__name__}")
    _no_extra(raw, {"address", "callsign"})
    address, callsign = raw.get("address"), raw.get("callsign")
    for f, v in (("address", address), ("callsign", callsign)):
        if v is not None and type(v) is not str:
            raise SchemaError("type", f"identity.{f}", f"expected a string, got {type(v).__name__}")
    if address is not None and not (0 < len(address) <= ADDRESS_MAX and set(address.removeprefix("~")) <= _HEX
                                    and address != "~"):
        raise SchemaError("value", "identity.address", "expected up to 8 lower-case hex digits (a '~' first: non-ICAO)")
    if callsign is not None and not (0 < len(callsign) <= 8 and set(callsign) <= _CALLSIGN):
        raise SchemaError("value", "identity.callsign", "expected 1-8 characters A-Z, 0-9 or space")
    if address is None and callsign is None:
        raise SchemaError("value", "identity", "neither an address nor a callsign")
    return Identity(address, callsign)


def _identity_fast(raw: Any) -> Identity | None:
    """:func:`_identity` of a plainly valid one, None for anything else (the strict path
    then decides)."""
    try:
        return _identity({"identity": raw})
    except SchemaError:
        return None


def identity_fields(identity: Identity) -> dict[str, str]:
    """An identity's wire map: its known parts."""
    return {k: v for k, v in (("address", identity.address), ("callsign", identity.callsign)) if v is not None}


def _corr(d: dict, f: str, n: int) -> np.ndarray:
    """A report's correlation coefficients, ``[ρ₁₂, ρ₁₃, …, ρ₂₃, …]`` (the upper triangle
    row by row, n(n−1)/2 values in (−1, 1)), as the n × n matrix; it must be positive
    definite."""
    rho = _array(d, f, (n * (n - 1) // 2,))
    if np.any(np.abs(rho) >= 1.0):
        raise SchemaError("range", f, "correlation coefficients must lie in (-1, 1)")
    C = np.eye(n)
    C[np.triu_indices(n, 1)] = rho
    C = np.triu(C) + np.triu(C, 1).T
    try:
        np.linalg.cholesky(C)
    except np.linalg.LinAlgError:
        raise SchemaError("value", f, "the correlation matrix is not positive definite") from None
    return C


def _check_watermark(d: dict) -> dict:
    _no_extra(d, ENVELOPE | {"final"})
    return {"final": _bool(d, "final", default=False)}


def _estimate_fields(d: dict) -> dict:
    """The fields every estimate has: ``track``, ``node``, ``method``, ``x``, a
    symmetric ``P`` with non-negative variances, optional ``nis``, ``nis_dof`` and
    ``existence`` (the probability that the track's target exists, in [0, 1], from a
    tracker that holds one: JIPDA's)."""
    body = {
        "track": _str(d, "track", ident=True),
        "node": _str(d, "node", ident=True),
        "method": _str(d, "method"),
        **_state(d),
        "nis": _num(d, "nis", lo=0.0, optional=True),
        "nis_dof": None,
        "existence": _num(d, "existence", lo=0.0, hi=1.0, optional=True),
    }
    if d.get("nis_dof") is not None:
        body["nis_dof"] = _int(d, "nis_dof", lo=1, hi=MAX_DIM)
    return body


_ESTIMATE_FIELDS = {"track", "node", "method", "x", "P", "nis", "nis_dof", "existence"}


def _check_track(d: dict) -> dict:
    body = _estimate_fields(d)
    body["extra"] = {}
    extra = d.get("extra", {})
    if not isinstance(extra, dict):
        raise SchemaError("type", "extra", "expected a map")
    for k in extra:
        if not isinstance(k, str):
            raise SchemaError("type", "extra", "keys must be strings")
        body["extra"][k] = _array(extra, k, (None, None)) if isinstance(extra[k], list) and extra[k] \
            and isinstance(extra[k][0], list) else _array(extra, k, (None,))
    body["identity"] = _identity(d) if "identity" in d else None
    _no_extra(d, ENVELOPE | _ESTIMATE_FIELDS | {"extra", "identity"})
    return body


# Links of the distributed topologies (UP_KINDS, DOWN_KINDS): each kind a fixed set of
# fields; an optional one is absent, never null.


def _check_regional_frame(d: dict) -> dict:
    """A regional fuser's frame (:class:`fusion.regional.RegionalFrame`; the region is
    its sender): ``tracks``, each a track's fields and its own ``t``; ``dropped``, the
    ids it no longer publishes."""
    tracks, dropped = d.get("tracks"), d.get("dropped", [])
    if not isinstance(tracks, list) or len(tracks) > FRAME_MAX:
        raise SchemaError("type", "tracks", f"expected a list of at most {FRAME_MAX} tracks")
    if not isinstance(dropped, list) or len(dropped) > FRAME_MAX:
        raise SchemaError("type", "dropped", f"expected a list of at most {FRAME_MAX} track ids")
    body = {"tracks": [_nested({"tracks": e}, "tracks", lambda e: {"t": _num(e, "t"), **_check_track(e)})
                       for e in tracks],
            "dropped": [_str({"dropped": i}, "dropped", ident=True) for i in dropped]}
    _no_extra(d, ENVELOPE | {"tracks", "dropped"})
    return body


def _no_null(d: dict) -> None:
    """In a link an optional field is absent, never null."""
    for k, v in d.items():
        if v is None:
            raise SchemaError("type", str(k), "null: an optional field is left out")


def _nested(d: dict, f: str, check: Callable[[dict], dict], *, optional: bool = False) -> dict | None:
    """A sub-map checked by ``check``; its errors name ``f.<field>``."""
    if f not in d:
        if optional:
            return None
        raise SchemaError("missing", f, "required")
    sub = d[f]
    if not isinstance(sub, dict):
        raise SchemaError("type", f, f"expected a map, got {type(sub).__name__}")
    try:
        return check(sub)
    except SchemaError as e:
        raise SchemaError(e.cause, f"{f}.{e.field}" if e.field else f, e.detail) from None


def _state(d: dict) -> dict:
    """A link's state: ``x``, and ``P`` symmetric with non-negative variances."""
    x = _array(d, "x", (None,))
    P = _array(d, "P", (x.size, x.size))
    if not np.allclose(P, P.T, rtol=1e-9, atol=1e-9 * max(1.0, float(np.max(np.abs(P))))):
        raise SchemaError("value", "P", "covariance is not symmetric")
    if np.any(np.diag(P) < 0):
        raise SchemaError("value", "P", "covariance has a negative variance")
    return {"x": x, "P": P}


def _track_state(d: dict) -> dict:
    """A local track's ``track`` (id), ``method`` and state."""
    return {"track": _str(d, "track", ident=True), "method": _str(d, "method"), **_state(d)}


def _model_terms(n: int) -> Callable[[dict], dict]:
    """A report's per-model terms (m models of the n states): ``xs`` m×n, ``Ps`` m×n×n,
    ``prior_xs`` m×n, ``prior_Ps`` m×n×n, ``loglik`` m."""

    def check(d: dict) -> dict:
        m = _array(d, "xs", (None, n)).shape[0]
        out = {"xs": _array(d, "xs", (m, n)), "Ps": _array(d, "Ps", (m, n, n)), "prior_xs": _array(d, "prior_xs", (m, n)),
               "prior_Ps": _array(d, "prior_Ps", (m, n, n)), "loglik": _array(d, "loglik", (m,))}
        _no_extra(d, set(out))
        return out

    return check


def _model_states(n: int) -> Callable[[dict], dict]:
    """A per-model centre's states: ``xs`` m×n, ``Ps`` m×n×n, ``mu`` m probabilities."""

    def check(d: dict) -> dict:
        m = _array(d, "xs", (None, n)).shape[0]
        out = {"xs": _array(d, "xs", (m, n)), "Ps": _array(d, "Ps", (m, n, n)), "mu": _array(d, "mu", (m,))}
        if np.any(out["mu"] < 0.0) or np.any(out["mu"] > 1.0):
            raise SchemaError("range", "mu", "mode probabilities must be in [0, 1]")
        _no_extra(d, set(out))
        return out

    return check


def _gaussian(n: int) -> Callable[[dict], dict]:
    def check(d: dict) -> dict:
        out = {"x": _array(d, "x", (n,)), "P": _array(d, "P", (n, n))}
        _no_extra(d, set(out))
        return out

    return check


def _uplinked_measurement(d: dict) -> dict:
    kind = _str(d, "kind", choices=MEASUREMENT_KINDS)
    return {"kind": kind, **_check_measurement(kind, d, envelope={"kind"})}


def _link(check: Callable[[dict], dict], fields: set[str]) -> Callable[[dict], dict]:
    """A link kind's checker: no nulls, ``check``'s fields, nothing else."""

    def checker(d: dict) -> dict:
        _no_null(d)
        body = check(d)
        _no_extra(d, ENVELOPE | fields)
        return body

    return checker


def _init_request(d: dict) -> dict:
    return {"node": _str(d, "node", ident=True), "measurement": _nested(d, "measurement", _uplinked_measurement)}


def _local_report(d: dict) -> dict:
    body = {"node": _str(d, "node", ident=True), **_track_state(d), "nis": _num(d, "nis", lo=0.0, optional=True),
            "nis_dof": None, "existence": _num(d, "existence", lo=0.0, hi=1.0, optional=True)}
    if "nis_dof" in d:
        body["nis_dof"] = _int(d, "nis_dof", lo=1, hi=MAX_DIM)
    n = body["x"].size
    body.update(prior_x=_array(d, "prior_x", (n,)), prior_P=_array(d, "prior_P", (n, n)), KH=_array(d, "KH", (n, n)),
                feedback_t=_num(d, "feedback_t", optional=True),
                models=_nested(d, "models", _model_terms(n), optional=True))
    return body


def _prediction_report(d: dict) -> dict:
    body = {"node": _str(d, "node", ident=True), **_track_state(d),
            "measurement": _nested(d, "measurement", _uplinked_measurement),
            "feedback_t": _num(d, "feedback_t", optional=True)}
    body["models"] = _nested(d, "models", _model_terms(body["x"].size), optional=True)
    return body


def _measurement_report(d: dict) -> dict:
    return {"node": _str(d, "node", ident=True), "measurement": _nested(d, "measurement", _uplinked_measurement)}


def _drop(d: dict) -> dict:
    return {"node": _str(d, "node", ident=True), "track": _str(d, "track", ident=True)}


def _feedback(d: dict) -> dict:
    body = _track_state(d)
    n = body["x"].size
    body.update(update=_nested(d, "update", _gaussian(n), optional=True),
                models=_nested(d, "models", _model_states(n), optional=True))
    return body


_STATE = {"track", "method", "x", "P"}
_LINK_CHECKERS: dict[str, Callable[[dict], dict]] = {
    "init_request": _link(_init_request, {"node", "measurement"}),
    "local_report": _link(_local_report, {"node", *_STATE, "nis", "nis_dof", "existence", "prior_x", "prior_P", "KH",
                                          "feedback_t", "models"}),
    "prediction_report": _link(_prediction_report, {"node", *_STATE, "measurement", "feedback_t", "models"}),
    "measurement_report": _link(_measurement_report, {"node", "measurement"}),
    "drop": _link(_drop, {"node", "track"}),
    "init": _link(_track_state, _STATE),
    "feedback": _link(_feedback, {*_STATE, "update", "models"}),
    "drop_track": _link(lambda d: {"track": _str(d, "track", ident=True)}, {"track"}),
}


def _check_truth(d: dict) -> dict:
    body = {"target": _str(d, "target", ident=True), "x": _array(d, "x", (None,))}
    _no_extra(d, ENVELOPE | {"target", "x"})
    return body


def _check_jam_state(d: dict) -> dict:
    aff = d.get("affects", [])
    if not isinstance(aff, list) or not all(isinstance(a, str) for a in aff):
        raise SchemaError("type", "affects", "expected a list of sensor ids")
    body = {
        "pos": _array(d, "pos", (3,)),
        "on": _bool(d, "on"),
        "mode": _str(d, "mode", choices=("barrage", "spot")),
        "power": _num(d, "power", lo=0.0),
        "law": _str(d, "law", choices=("uniform", "laplacian")),
        "affects": list(aff),
    }
    _no_extra(d, ENVELOPE | set(body))
    return body


def _check_status(d: dict) -> dict:
    counters = d.get("counters", {})
    if not isinstance(counters, dict) or not all(
            isinstance(k, str) and isinstance(v, (int, float)) and not isinstance(v, bool)
            for k, v in counters.items()):
        raise SchemaError("type", "counters", "expected a map of string -> number")
    events = d.get("events", [])
    if not isinstance(events, list) or not all(isinstance(e, str) for e in events):
        raise SchemaError("type", "events", "expected a list of strings")
    sources = d.get("sources", {})
    if not isinstance(sources, dict) or not all(
            isinstance(k, str) and isinstance(v, dict) for k, v in sources.items()):
        raise SchemaError("type", "sources", "expected a map of source id -> map")
    for k, v in sources.items():
        iv = v.get("dead_intervals", [])
        if not isinstance(iv, list) or not all(
                isinstance(p, list) and len(p) == 2 and all(
                    x is None or (isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x))
                    for x in p) for p in iv):
            raise SchemaError("type", "sources", f"{k}.dead_intervals must be a list of [start, end|null]")
        counts = set(v) & SOURCE_COUNTS
        if not all(type(v[c]) is int and v[c] >= 0 for c in counts | ({"rejected"} & set(v))) \
                or set(v) - {"dead_intervals", "rejected", "lag_s", "clock"} - SOURCE_COUNTS:
            raise SchemaError("type", "sources", f"{k}: expected dead_intervals, rejected, lag_s, clock and counts "
                                                 f"({', '.join(sorted(SOURCE_COUNTS))})")
        lag = v.get("lag_s")
        if not (lag is None or (type(lag) in (int, float) and math.isfinite(lag))) or \
                v.get("clock", "ok") not in ("ok", "ahead", "behind"):
            raise SchemaError("type", "sources", f"{k}: lag_s must be a finite number or null, clock ok|ahead|behind")
    body = {
        "state": _str(d, "state", choices=("starting", "ready", "running", "done", "stopped")),
        "role": _str(d, "role"),
        "counters": dict(counters),
        "events": list(events),
        "sources": sources,
    }
    _no_extra(d, ENVELOPE | set(body))
    return body


_CHECKERS: dict[str, Callable[[dict], dict]] = {
    **{k: (lambda d, k=k: _check_measurement(k, d)) for k in MEASUREMENT_KINDS},
    "watermark": _check_watermark,
    "track": _check_track,
    "regional_frame": _check_regional_frame,
    **_LINK_CHECKERS,
    "truth": _check_truth,
    "jam_state": _check_jam_state,
    "status": _check_status,
}


# Fast path of validate() for what arrives most: measurements, watermarks, tracks ------
_MEASUREMENT_FIELDS = {k: ENVELOPE | _measurement_fields(k) for k in _KINDS}
# per kind, per component: (value field, std field, limits as _plain_float takes them)
_FAST_COMPONENTS = {k: tuple((c.name, c.std_field, (c.lo, c.hi, c.lo_open, c.hi_open)) for c in kind.components)
                    for k, kind in _KINDS.items()}
_WATERMARK_FIELDS = frozenset(ENVELOPE | {"final"})
_TRACK_FIELDS = frozenset(ENVELOPE | {"track", "node", "method", "x", "P", "nis", "nis_dof", "existence", "extra",
                                      "identity"})
_SEQ_MAX = 2**63 - 1


def _plain_float(x: Any, lo: float, hi: float, lo_open: bool, hi_open: bool) -> bool:
    """``x`` is a Python float that :func:`_num` accepts unchanged with these limits."""
    return (type(x) is float and math.isfinite(x) and (lo < x if lo_open else lo <= x)
            and (x < hi if hi_open else x <= hi))


def _validate_fast(d: Any) -> Message | None:
    """:func:`validate` of a plainly valid measurement, watermark or estimate without
    ``extra``, on Python scalars (and one numpy conversion per array).

    It accepts only what the strict checks accept, and returns the same message. It
    returns ``None`` for anything else: other kinds, ints where floats travel, ids not
    seen before, a covariance that is not exactly symmetric, any doubtful value. The
    strict checks then decide, and name the error.
    """
    if type(d) is not dict:
        return None
    kind, v, src, seq, t = d.get("kind"), d.get("v"), d.get("src"), d.get("seq"), d.get("t")
    if not (type(v) is int and v == SCHEMA_VERSION and type(src) is str and src in _VALID_IDS
            and type(seq) is int and 0 <= seq <= _SEQ_MAX and type(t) is float and math.isfinite(t)):
        return None
    if kind == "watermark":
        final = d.get("final", False)
        if type(final) is not bool or not d.keys() <= _WATERMARK_FIELDS:
            return None
        return Message(kind=kind, src=src, seq=seq, t=t, body={"final": final})
    if kind == "track":
        body = _estimate_body_fast(d)
        return None if body is None else Message(kind=kind, src=src, seq=seq, t=t, body=body)
    fields = _MEASUREMENT_FIELDS.get(kind) if type(kind) is str else None
    identity = None
    if fields is not None and "identity" in d:
        identity = _identity_fast(d["identity"])
        fields = fields | {"identity"} if identity is not None else None
    if fields is None or d.keys() != fields:
        return None
    sensor, site = d["sensor"], d["site"]
    if not (type(sensor) is str and sensor in _VALID_IDS and type(site) is list and len(site) == 3
            and all(type(c) is float and math.isfinite(c) for c in site)):
        return None
    body: dict[str, Any] = {"sensor": sensor, "site": np.array(site)}
    for name, std_field, limits in _FAST_COMPONENTS[kind]:
        value, std = d[name], d[std_field]
        if not (_plain_float(value, *limits) and _plain_float(std, 0.0, math.inf, True, False)):
            return None
        body[name] = value
        body[std_field] = std
    if identity is not None:
        body["identity"] = identity
    return Message(kind=kind, src=src, seq=seq, t=t, body=body)


def _estimate_body_fast(d: dict) -> dict | None:
    if not d.keys() <= _TRACK_FIELDS:
        return None
    identity = None
    if "identity" in d and (identity := _identity_fast(d["identity"])) is None:
        return None
    x, P, track, node, method = d.get("x"), d.get("P"), d.get("track"), d.get("node"), d.get("method")
    nis, nis_dof, extra, existence = d.get("nis"), d.get("nis_dof"), d.get("extra", {}), d.get("existence")
    if not (type(x) is list and 0 < len(x) <= MAX_DIM and all(type(v) is float for v in x)
            and type(P) is list and len(P) == len(x) and all(type(row) is list and len(row) == len(x) for row in P)
            and type(track) is str and track in _VALID_IDS and type(node) is str and node in _VALID_IDS
            and type(method) is str and (nis is None or _plain_float(nis, 0.0, math.inf, False, False))
            and (nis_dof is None or (type(nis_dof) is int and 1 <= nis_dof <= MAX_DIM))
            and (existence is None or _plain_float(existence, 0.0, 1.0, False, False))
            and type(extra) is dict and not extra):
        return None
    try:  # P's entries may still be anything: numpy decides what is a float matrix
        xa, Pa = np.array(x), np.array(P, dtype=float)
    except (TypeError, ValueError):
        return None
    # A sum is finite only if every term is (an overflowing sum just takes the strict path).
    if not (Pa.shape == (len(x), len(x)) and math.isfinite(xa.sum()) and math.isfinite(Pa.sum())
            and (Pa == Pa.T).all() and (Pa.diagonal() >= 0.0).all()):
        return None
    return {"track": track, "node": node, "method": method, "x": xa, "P": Pa, "nis": nis, "nis_dof": nis_dof,
            "existence": existence, "extra": {}, "identity": identity}


def validate(d: Any) -> Message:
    """Validate a decoded msgpack object; return the :class:`Message` or raise."""
    return _validate_fast(d) or _validate_strict(d)


def _validate_strict(d: Any) -> Message:
    """Every check of the wire format, in a fixed order, raising the first failure."""
    if not isinstance(d, dict):
        raise SchemaError("not-a-map", None, f"top level is {type(d).__name__}, expected a map")
    if "v" not in d:
        raise SchemaError("missing", "v", "schema version required")
    if d["v"] != SCHEMA_VERSION or isinstance(d["v"], bool):
        raise SchemaError("version", "v", f"schema version {d['v']!r}, this build speaks {SCHEMA_VERSION}")
    kind = _str(d, "kind")
    if kind not in _CHECKERS:
        raise SchemaError("kind", "kind", f"unknown message kind {kind!r}")
    src = _str(d, "src", ident=True)
    seq = _int(d, "seq")
    t = _num(d, "t")
    return Message(kind=kind, src=src, seq=seq, t=t, body=_CHECKERS[kind](d))


def decode(data: bytes) -> Message:
    """Bytes off the wire -> validated :class:`Message` (or :class:`SchemaError`)."""
    if len(data) > MAX_BYTES:
        raise SchemaError("too-large", None, f"{len(data)} bytes > {MAX_BYTES}")
    try:
        obj = msgpack.unpackb(data, raw=False, strict_map_key=False)
    except Exception as e:  # msgpack raises several unrelated types
        raise SchemaError("malformed", None, f"not valid msgpack ({type(e).__name__})") from None
    return validate(obj)


def _plain(v: Any) -> Any:
    if isinstance(v, dict):
        return {k: _plain(vv) for k, vv in v.items()}
    if isinstance(v, np.ndarray):
        return v.tolist()
    if isinstance(v, np.generic):
        return v.item()
    return v


def encode(kind: str, src: str, seq: int, t: float, **payload: Any) -> bytes:
    """Build, validate and pack a message."""
    d = {"v": SCHEMA_VERSION, "kind": kind, "src": src, "seq": int(seq), "t": float(t)}
    for k, v in payload.items():
        d[k] = _plain(v)
    validate(d)
    return msgpack.packb(d, use_bin_type=True)


# ---------------------------------------------------------------- typed conversions


def measurement_fields(m: Measurement) -> dict[str, Any]:
    """A measurement's payload: ``sensor``, ``site``, its components and their stds, and its
    correlations (``corr``) if it states them."""
    payload: dict[str, Any] = {"sensor": m.sensor, "site": m.site}
    for i, c in enumerate(_KINDS[m.kind].components):
        payload[c.name] = float(m.z[i])
        payload[c.std_field] = float(m.std[i])
    if m.corr is not None:
        corr = np.asarray(m.corr, dtype=float)
        payload["corr"] = corr[np.triu_indices(corr.shape[0], 1)]
    if m.identity is not None:
        payload["identity"] = identity_fields(m.identity)
    return payload


def measurement_of(kind: str, b: dict, t: float, seq: int) -> Measurement:
    """The :class:`Measurement` of a validated measurement payload."""
    comps = _KINDS[kind].components
    return Measurement(t=t, sensor=b["sensor"], kind=kind, z=np.array([b[c.name] for c in comps]),
                       std=np.array([b[c.std_field] for c in comps]), site=b["site"], seq=seq, corr=b.get("corr"),
                       identity=b.get("identity"))


def encode_measurement(m: Measurement, src: str) -> bytes:
    return encode(m.kind, src, m.seq, m.t, **measurement_fields(m))


def to_measurement(msg: Message) -> Measurement:
    return measurement_of(msg.kind, msg.body, msg.t, msg.seq)


def encode_estimate(e: Estimate, src: str, seq: int) -> bytes:
    """An estimate as a ``track`` message. ``extra`` travels as arrays: a number (or bool)
    becomes a one-element list, None is left out; anything else non-numeric is an error."""
    fast = _encode_estimate_fast(e, src, seq)
    if fast is not None:
        return fast
    return encode("track", src, seq, e.t, **_estimate_payload(e))


def _estimate_payload(e: Estimate) -> dict[str, Any]:
    extra = {}
    for k, v in e.extra.items():
        if v is None:
            continue
        extra[k] = [float(v)] if isinstance(v, (bool, int, float, np.integer, np.floating)) else v
    payload = dict(track=e.track, node=e.node, method=e.method, x=e.x, P=e.P, nis=e.nis, nis_dof=e.nis_dof,
                   extra=extra)
    if e.existence is not None:  # optional: left out where the tracker holds none
        payload["existence"] = e.existence
    if e.identity is not None:
        payload["identity"] = identity_fields(e.identity)
    return payload


def _encode_estimate_fast(e: Estimate, src: str, seq: int) -> bytes | None:
    """:func:`encode_estimate` of a plainly valid estimate without ``extra`` (what a fuser
    publishes), checking the numpy arrays themselves instead of re-parsing the lists made
    from them. The same bytes as the strict path; ``None`` leaves anything else to it.

    The covariance must be *exactly* symmetric here (every estimator symmetrises); one
    that is only symmetric within tolerance takes the strict path, which allows that.
    """
    x, P = e.x, e.P
    if any(v is not None for v in e.extra.values()) \
            or type(x) is not np.ndarray or type(P) is not np.ndarray or x.dtype != np.float64 \
            or P.dtype != np.float64 or x.ndim != 1 or not 0 < x.size <= MAX_DIM or P.shape != (x.size, x.size):
        return None
    seq, t = int(seq), float(e.t)  # converted in the strict path's order, which raises the same on junk
    nis, nis_dof, existence = _plain(e.nis), _plain(e.nis_dof), _plain(e.existence)
    # A sum is finite only if every term is (an overflowing sum just takes the strict path).
    if not (math.isfinite(t) and 0 <= seq <= _SEQ_MAX and math.isfinite(x.sum()) and math.isfinite(P.sum())
            and (P == P.T).all() and (P.diagonal() >= 0.0).all()
            and (nis is None or _plain_float(nis, 0.0, math.inf, False, False))
            and (nis_dof is None or (type(nis_dof) is int and 1 <= nis_dof <= MAX_DIM))
            and (existence is None or _plain_float(existence, 0.0, 1.0, False, False))
            and type(e.method) is str and all(type(i) is str and i in _VALID_IDS for i in (src, e.track, e.node))):
        return None
    d = {"v": SCHEMA_VERSION, "kind": "track", "src": src, "seq": seq, "t": t, "track": e.track, "node": e.node,
         "method": e.method, "x": x.tolist(), "P": P.tolist(), "nis": nis, "nis_dof": nis_dof, "extra": {}}
    if existence is not None:
        d["existence"] = existence
    if e.identity is not None:
        identity = identity_fields(e.identity)
        if _identity_fast(identity) is None:
            return None
        d["identity"] = identity
    return msgpack.packb(d, use_bin_type=True)


def to_estimate(msg: Message) -> Estimate:
    b = msg.body
    return Estimate(t=msg.t, x=b["x"], P=b["P"], method=b["method"], node=b["node"], track=b["track"],
                    nis=b["nis"], nis_dof=b["nis_dof"], extra=dict(b["extra"]), existence=b["existence"],
                    identity=b.get("identity"))
