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
# An uplink's measurement (a map of the uplink, with its kind)
UPLINKED = {"kind": "range_az", "sensor": "s1", "site": SITE, "az": 3.0, "std_az": 0.02, "range": 1e4,
            "std_range": 20.0}


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
        "uplink": {"estimate": {**_LOCAL, "prior_x": [0.5, 1.5], "prior_P": [[3.0, 0.0], [0.0, 4.0]],
                               "KH": [[0.2, 0.0], [0.0, 0.1]], "prediction": False, "feedback_t": 1.0}},
        "downlink": {"estimate": {**_LOCAL, "node": "centre"}, "init": True,
                     "sensor_x": [1.0, 2.0], "sensor_P": [[1.0, 0.0], [0.0, 1.0]],
                     "imm_xs": [[1.0, 2.0], [1.5, 2.0]], "imm_Ps": [[1.0, 0.0], [0.0, 1.0], [2.0, 0.0], [0.0, 2.0]],
                     "imm_mu": [0.75, 0.25]},
        "truth": {"target": "T1", "x": [1.0, 2.0, 3.0]},
        "jam_state": {"pos": SITE, "on": True, "mode": "barrage", "power": 100.0, "law": "uniform",
                      "affects": ["s1"]},
        "status": {"state": "running", "role": "sensor", "counters": {"published": 4}, "events": ["x"]},
    }[kind]
    return {**env, **body}


ALL_KINDS = ["bearing", "azel", "range_az", "az_el_range", "watermark", "track", "uplink",
             "downlink", "truth", "jam_state", "status"]


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
    "uplink": [("estimate", [1.0], "type"), ("estimate", None, "type"), ("estimate", ABSENT, "missing"),
               ("estimate.x", [1.0, math.nan], "non-finite"), ("estimate.P", [[1.0, 0.0], [5.0, 1.0]], "value"),
               ("estimate.P", [[1.0]], "shape"), ("estimate.track", "a/b", "value"), ("estimate.node", 3, "type"),
               ("estimate.method", None, "type"), ("estimate.nis", -1.0, "range"), ("estimate.nis_dof", 0, "range"),
               ("estimate.prior_x", [1.0], "shape"), ("estimate.prior_x", ABSENT, "missing"),
               ("estimate.prior_P", [[1.0, 2.0]], "shape"), ("estimate.prior_P", [[1.0, math.inf], [0.0, 1.0]], "non-finite"),
               ("estimate.KH", [[0.0, 0.0], [0.0]], "type"), ("estimate.KH", ABSENT, "missing"),
               ("estimate.prediction", 1.0, "type"), ("estimate.prediction", [1.0], "type"),
               ("estimate.prediction", ABSENT, "missing"), ("estimate.feedback_t", [1.0], "type"),
               ("estimate.feedback_t", None, "type"), ("estimate.feedback_t", math.nan, "non-finite"),
               ("estimate.extra", {}, "unknown-field"), ("estimate.drop", True, "unknown-field"),
               ("drop", 1.0, "type"), ("drop", [1.0], "type"), ("measurement", "x", "type"),
               ("measurement", {**UPLINKED, "kind": "sonar"}, "value"),
               ("measurement", {**UPLINKED, "sensor": "s2"}, "value"),
               ("measurement", {**UPLINKED, "az": 7.0}, "range"),
               ("measurement", {**UPLINKED, "el": 0.1}, "unknown-field"),
               ("measurement", {k: v for k, v in UPLINKED.items() if k != "std_az"}, "missing"),
               ("measurement", {**UPLINKED, "seq": 3}, "unknown-field"),
               ("init", True, "unknown-field")],
    "downlink": [("init", 1.0, "type"), ("init", [1.0], "type"), ("init", ABSENT, "missing"), ("drop", 0, "type"),
                 ("drop", None, "type"), ("estimate", ABSENT, "missing"), ("estimate", 5, "type"),
                 ("estimate.x", [1.0, math.inf], "non-finite"), ("estimate.P", [[-1.0, 0.0], [0.0, 1.0]], "value"),
                 ("estimate.prior_x", [1.0, 2.0], "unknown-field"), ("estimate.track", None, "type"),
                 ("sensor_x", [1.0], "shape"), ("sensor_x", ABSENT, "missing"), ("sensor_P", [[1.0]], "shape"),
                 ("sensor_P", [[1.0, 0.0], [0.0, math.nan]], "non-finite"), ("sensor_P", ABSENT, "missing"),
                 ("imm_xs", [[1.0, 2.0, 3.0]], "shape"), ("imm_xs", ABSENT, "missing"),
                 ("imm_Ps", [[1.0, 0.0], [0.0, 1.0]], "shape"), ("imm_mu", [0.5], "shape"),
                 ("imm_mu", [1.5, -0.5], "range"), ("imm_mu", ABSENT, "missing"), ("imm_loglik", [0.0], "unknown-field"),
                 ("extra", {}, "unknown-field")],
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
