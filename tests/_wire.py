"""Support for the tests of the wire format and of what the fuser does with it: a valid
message of every kind, the bad value of every field with the cause it must be rejected
for, and a scenario's messages as its sensors publish them."""

from __future__ import annotations

import copy
import math
from functools import lru_cache

import msgpack

from schemas import KeySpace, encode, encode_measurement
from sensors_sim import load_scenario, sensor_events


SITE = [1.0, 2.0, 3.0]


def pack(d: dict) -> bytes:
    return msgpack.packb(d, use_bin_type=True)


_LOCAL = {"track": "T1", "node": "s1", "method": "PHHNV", "x": [1.0, 2.0], "P": [[2.0, 0.1], [0.1, 3.0]],
          "nis": 0.5, "nis_dof": 2}
# A measurement a node sends up (a map of the message, with its kind)
UPLINKED = {"kind": "range_az", "sensor": "s1", "site": SITE, "az": 3.0, "std_az": 0.02, "range": 1e4,
            "std_range": 20.0}
# A local IMM's per-model terms: m = 2 models of the n = 2 states
_TERMS = {"xs": [[1.0, 2.0], [1.5, 2.0]], "Ps": [[[1.0, 0.0], [0.0, 1.0]], [[2.0, 0.0], [0.0, 2.0]]],
          "prior_xs": [[0.5, 1.5], [0.5, 1.0]], "prior_Ps": [[[3.0, 0.0], [0.0, 4.0]], [[3.0, 0.0], [0.0, 5.0]]],
          "loglik": [-1.0, -2.5]}


def good(kind: str) -> dict:
    env = {"v": 1, "kind": kind, "src": "s1", "seq": 3, "t": 2.0}
    body = {
        "bearing": {"sensor": "s1", "site": SITE, "az": 0.1, "std_az": 0.01},
        "azel": {"sensor": "s1", "site": SITE, "az": 6.2, "std_az": 0.001, "el": 0.2, "std_el": 0.001},
        "range_az": {"sensor": "s1", "site": SITE, "az": 3.0, "std_az": 0.02, "range": 1e4, "std_range": 20.0},
        "az_el_range": {"sensor": "s1", "site": SITE, "az": 1.0, "std_az": 0.02, "el": -0.1, "std_el": 0.02,
                        "range": 5e3, "std_range": 10.0},
        "watermark": {"final": False},
        "track": {"track": "T1", "node": "centre", "method": "SS", "x": [1.0, 2.0], "P": [[2.0, 0.1], [0.1, 3.0]],
                  "nis": 1.5, "nis_dof": 2},
        "init_request": {"node": "s1", "measurement": UPLINKED},
        "local_report": {**_LOCAL, "existence": 0.75, "prior_x": [0.5, 1.5], "prior_P": [[3.0, 0.0], [0.0, 4.0]],
                         "KH": [[0.2, 0.0], [0.0, 0.1]], "feedback_t": 1.0, "models": _TERMS},
        "prediction_report": {**{k: v for k, v in _LOCAL.items() if k not in ("nis", "nis_dof")},
                              "measurement": UPLINKED, "feedback_t": 1.0, "models": _TERMS},
        "measurement_report": {"node": "s1", "measurement": UPLINKED},
        "drop": {"node": "s1", "track": "L3"},
        "init": {"track": "L1", "method": "PHHNV", "x": [1.0, 2.0], "P": [[2.0, 0.1], [0.1, 3.0]]},
        "feedback": {"track": "L1", "method": "PHHNV", "x": [1.0, 2.0], "P": [[2.0, 0.1], [0.1, 3.0]],
                     "update": {"x": [1.0, 2.0], "P": [[1.0, 0.0], [0.0, 1.0]]},
                     "models": {"xs": _TERMS["xs"], "Ps": _TERMS["Ps"], "mu": [0.75, 0.25]}},
        "drop_track": {"track": "L1"},
        "truth": {"target": "T1", "x": [1.0, 2.0, 3.0]},
        "jam_state": {"pos": SITE, "on": True, "mode": "barrage", "power": 100.0, "law": "uniform",
                      "affects": ["s1"]},
        "status": {"state": "running", "role": "sensor", "counters": {"published": 4}, "events": ["x"]},
    }[kind]
    return {**env, **body}


LINK_KINDS = ["init_request", "local_report", "prediction_report", "measurement_report", "drop", "init", "feedback",
              "drop_track"]
ALL_KINDS = ["bearing", "azel", "range_az", "az_el_range", "watermark", "track", *LINK_KINDS, "truth", "jam_state",
             "status"]
# Fields a message may leave out
OPTIONAL = ("final", "nis", "nis_dof", "existence", "affects", "counters", "events", "feedback_t", "models", "update")


def with_field(d: dict, field: str, value) -> dict:
    """A deep copy of message ``d`` with ``field`` (``a.b`` inside the map ``a``) set to
    ``value``; a ``value`` of :data:`ABSENT` removes it."""
    out = copy.deepcopy(d)
    *path, last = field.split(".")
    inner = out
    for p in path:
        inner = inner[p]
    if value is ABSENT:
        inner.pop(last, None)
    else:
        inner[last] = value
    return out


ABSENT = object()


# (field, bad value, expected cause) for each kind; every field of every kind is covered.
BAD_ENVELOPE = [("v", 2, "version"), ("v", None, "version"), ("kind", "nope", "kind"), ("kind", 3, "type"),
                ("src", "a/b", "value"), ("src", 5, "type"), ("seq", -1, "range"), ("seq", 1.5, "type"),
                ("t", math.nan, "non-finite"), ("t", math.inf, "non-finite"), ("t", "0", "type")]


BAD_FIELDS = {
    "bearing": [("az", 2 * math.pi, "range"), ("az", -0.1, "range"), ("az", math.nan, "non-finite"),
                ("std_az", 0.0, "range"), ("std_az", -1.0, "range"), ("site", [1.0, 2.0], "shape"),
                ("site", [1.0, math.nan, 2.0], "non-finite"), ("site", "x", "type"), ("sensor", "a b", "value"),
                ("extra_field", 1, "unknown-field")],
    "azel": [("el", 2.0, "range"), ("el", -1.6, "range"), ("std_el", math.inf, "non-finite"),
             ("az", True, "type")],
    "range_az": [("range", 0.0, "range"), ("range", -5.0, "range"), ("std_range", 0.0, "range"),
                 ("el", 0.1, "unknown-field")],
    "az_el_range": [("range", math.nan, "non-finite"), ("std_el", "1", "type")],
    "watermark": [("final", "yes", "type")],
    "track": [("x", [], "shape"), ("x", [[1.0]], "shape"), ("P", [[1.0, 0.0], [5.0, 1.0]], "value"),
              ("P", [[1.0]], "shape"), ("P", [[-1.0, 0.0], [0.0, 1.0]], "value"), ("nis", -1.0, "range"),
              ("nis_dof", 0, "range"), ("track", "", "value"), ("node", None, "missing"), ("method", 1, "type"),
              ("x", [1.0] * 100, "shape"), ("extra", [1], "type")],
    "init_request": [("node", "a/b", "value"), ("node", ABSENT, "missing"), ("node", None, "type"),
                     ("measurement", "x", "type"), ("measurement", None, "type"), ("measurement", ABSENT, "missing"),
                     ("measurement", {**UPLINKED, "kind": "sonar"}, "value"),
                     ("measurement", {**UPLINKED, "az": 7.0}, "range"),
                     ("measurement", {**UPLINKED, "el": 0.1}, "unknown-field"),
                     ("measurement", {k: v for k, v in UPLINKED.items() if k != "std_az"}, "missing"),
                     ("measurement", {**UPLINKED, "seq": 3}, "unknown-field"), ("track", "T1", "unknown-field")],
    "local_report": [("existence", 1.5, "range"), ("existence", -0.1, "range"), ("existence", "high", "type"),
                     ("existence", None, "type"),
                     ("x", [1.0, math.nan], "non-finite"), ("x", [], "shape"), ("P", [[1.0, 0.0], [5.0, 1.0]], "value"),
                     ("P", [[1.0]], "shape"), ("P", [[-1.0, 0.0], [0.0, 1.0]], "value"), ("track", "a/b", "value"),
                     ("track", ABSENT, "missing"), ("node", 3, "type"), ("node", ABSENT, "missing"),
                     ("method", None, "type"), ("nis", -1.0, "range"), ("nis", None, "type"), ("nis_dof", 0, "range"),
                     ("nis_dof", 1.5, "type"), ("prior_x", [1.0], "shape"), ("prior_x", ABSENT, "missing"),
                     ("prior_P", [[1.0, 2.0]], "shape"), ("prior_P", [[1.0, math.inf], [0.0, 1.0]], "non-finite"),
                     ("KH", [[0.0, 0.0], [0.0]], "type"), ("KH", ABSENT, "missing"), ("feedback_t", [1.0], "type"),
                     ("feedback_t", None, "type"), ("feedback_t", math.nan, "non-finite"), ("models", [1.0], "type"),
                     ("models", None, "type"), ("models.xs", [[1.0, 2.0, 3.0]], "shape"),
                     ("models.xs", ABSENT, "missing"), ("models.Ps", [[1.0, 0.0], [0.0, 1.0], [2.0, 0.0], [0.0, 2.0]], "shape"),
                     ("models.prior_xs", ABSENT, "missing"), ("models.prior_xs", [[0.5, 1.5]], "shape"),
                     ("models.prior_Ps", [[[math.nan, 0.0], [0.0, 1.0]], [[1.0, 0.0], [0.0, 1.0]]], "non-finite"),
                     ("models.loglik", [0.0], "shape"), ("models.loglik", ABSENT, "missing"),
                     ("models.mu", [0.5, 0.5], "unknown-field"), ("measurement", UPLINKED, "unknown-field"),
                     ("prediction", False, "unknown-field"), ("extra", {}, "unknown-field"),
                     ("estimate", {}, "unknown-field"), ("drop", True, "unknown-field")],
    "prediction_report": [("existence", 0.5, "unknown-field"),
                          ("measurement", ABSENT, "missing"), ("measurement", {**UPLINKED, "az": 7.0}, "range"),
                          ("measurement", {**UPLINKED, "sensor": "a/b"}, "value"), ("nis", 1.0, "unknown-field"),
                          ("nis_dof", 2, "unknown-field"), ("prior_x", [1.0, 2.0], "unknown-field"),
                          ("KH", [[0.0, 0.0], [0.0, 0.0]], "unknown-field"), ("feedback_t", "1", "type"),
                          ("models.loglik", ABSENT, "missing"), ("models.Ps", [[[1.0, 0.0], [0.0, 1.0]]], "shape"),
                          ("x", [], "shape"), ("node", "", "value"), ("track", None, "type"), ("method", 2, "type")],
    "measurement_report": [("node", ABSENT, "missing"), ("measurement", ABSENT, "missing"),
                           ("measurement", {**UPLINKED, "std_range": 0.0}, "range"), ("track", "T1", "unknown-field"),
                           ("x", [1.0], "unknown-field")],
    "drop": [("node", ABSENT, "missing"), ("node", "a b", "value"), ("track", ABSENT, "missing"),
             ("track", "a b", "value"), ("track", None, "type"), ("x", [1.0], "unknown-field"),
             ("estimate", {}, "unknown-field")],
    "init": [("existence", 0.5, "unknown-field"),
             ("track", ABSENT, "missing"), ("track", None, "type"), ("method", 1, "type"), ("method", ABSENT, "missing"),
             ("x", [1.0, math.inf], "non-finite"), ("x", ABSENT, "missing"), ("P", [[-1.0, 0.0], [0.0, 1.0]], "value"),
             ("P", ABSENT, "missing"), ("node", "s1", "unknown-field"), ("init", True, "unknown-field"),
             ("prior_x", [1.0, 2.0], "unknown-field"), ("update", {}, "unknown-field"), ("nis", 1.0, "unknown-field")],
    "feedback": [("existence", 0.5, "unknown-field"),
                 ("update", [1.0], "type"), ("update", None, "type"), ("update.x", [1.0], "shape"),
                 ("update.P", [[1.0]], "shape"), ("update.P", [[1.0, 0.0], [0.0, math.nan]], "non-finite"),
                 ("update.x", ABSENT, "missing"), ("update.P", ABSENT, "missing"), ("update.nis", 1.0, "unknown-field"),
                 ("models.xs", [[1.0, 2.0, 3.0]], "shape"), ("models.xs", ABSENT, "missing"),
                 ("models.Ps", [[1.0, 0.0], [0.0, 1.0], [2.0, 0.0], [0.0, 2.0]], "shape"), ("models.mu", [0.5], "shape"),
                 ("models.mu", [1.5, -0.5], "range"), ("models.mu", ABSENT, "missing"),
                 ("models.loglik", [0.0, 0.0], "unknown-field"), ("models", 1, "type"), ("x", [1.0], "shape"),
                 ("P", [[1.0, 0.0], [5.0, 1.0]], "value"), ("track", "*", "value"), ("sensor_x", [1.0, 2.0], "unknown-field"),
                 ("drop", True, "unknown-field"), ("extra", {}, "unknown-field")],
    "drop_track": [("track", ABSENT, "missing"), ("track", 5, "type"), ("track", "a/b", "value"),
                   ("x", [1.0], "unknown-field"), ("init", False, "unknown-field")],
    "truth": [("x", [math.nan], "non-finite"), ("target", "*", "value")],
    "jam_state": [("on", 1, "type"), ("mode", "sweep", "value"), ("law", "gauss", "value"),
                  ("power", -1.0, "range"), ("affects", "s1", "type"), ("pos", [0.0], "shape")],
    "status": [("state", "weird", "value"), ("counters", {"a": "b"}, "type"), ("events", [1], "type"),
               ("role", None, "missing"), ("sources", {"s": {"dead_intervals": [[0, "x"]]}}, "type")],
}


CASES = [(k, f, v, c) for k in ALL_KINDS for f, v, c in BAD_ENVELOPE if not (f == "kind" and v == "nope")] + \
        [(k, f, v, c) for k, rows in BAD_FIELDS.items() for f, v, c in rows]


KEYS = KeySpace("unit")


def wire_stream(scenario, lag: dict[str, float] | None = None):
    """(key, bytes) per sensor in publication order: measurements then a watermark per scan;
    ``lag`` delays a sensor's arrivals by that many seconds of its data."""
    out = []
    for sid in scenario.sensors:
        wm = 0
        evs = list(sensor_events(scenario, sid))
        for i, ev in enumerate(evs):
            if ev.measurement is not None:
                out.append((ev.t, sid, KEYS.meas(sid), encode_measurement(ev.measurement, sid)))
            wm += 1
            out.append((ev.t, sid, KEYS.meas(sid), encode("watermark", sid, wm, ev.t, final=i == len(evs) - 1)))
    # interleave sources by time, as a network would (stable within a source)
    out.sort(key=lambda r: r[0] + (lag or {}).get(r[1], 0.0))
    return [(k, b) for _, _, k, b in out]


# The fuzzed scenario ----------------------------------------------------------------
SCENARIO = "patent-3d"
STRANGER = "mallory"  # publishes on meas/mallory; not a sensor of the scenario


@lru_cache(maxsize=None)
def scenario():
    return load_scenario(SCENARIO)


@lru_cache(maxsize=None)
def real_stream() -> tuple[tuple[str, bytes, dict], ...]:
    """The scenario's real wire stream: (key id, bytes, decoded map) in arrival order."""
    return tuple((KEYS.family_and_id(k)[1], b, msgpack.unpackb(b)) for k, b in wire_stream(scenario()))
