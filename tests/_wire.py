"""Support for the tests of the wire format and of what the fuser does with it: a valid
message of every kind, the bad value of every field with the cause it must be rejected
for, and a scenario's messages as its sensors publish them."""

from __future__ import annotations

import math
from functools import lru_cache

import msgpack

from schemas import KeySpace, encode, encode_measurement
from sensors_sim import load_scenario, sensor_events


SITE = [1.0, 2.0, 3.0]


def pack(d: dict) -> bytes:
    return msgpack.packb(d, use_bin_type=True)


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
        "prediction": {"track": "T1", "node": "radar2d", "method": "DDHNV", "x": [1.0], "P": [[1.0]]},
        "truth": {"target": "T1", "x": [1.0, 2.0, 3.0]},
        "jam_state": {"pos": SITE, "on": True, "mode": "barrage", "power": 100.0, "law": "uniform",
                      "affects": ["s1"]},
        "status": {"state": "running", "role": "sensor", "counters": {"published": 4}, "events": ["x"]},
    }[kind]
    return {**env, **body}


ALL_KINDS = ["bearing", "azel", "range_az", "az_el_range", "watermark", "track", "prediction", "truth",
             "jam_state", "status"]


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
    "prediction": [("x", [math.inf], "non-finite")],
    "truth": [("x", [math.nan], "non-finite"), ("target", "*", "value")],
    "jam_state": [("on", 1, "type"), ("mode", "sweep", "value"), ("law", "gauss", "value"),
                  ("power", -1.0, "range"), ("affects", "s1", "type"), ("pos", [0.0], "shape")],
    "status": [("state", "weird", "value"), ("counters", {"a": "b"}, "type"), ("events", [1], "type"),
               ("role", None, "missing"), ("sources", {"s": {"dead_intervals": [[0, "x"]]}}, "type")],
}


CASES = [(k, f, v, c) for k in ALL_KINDS for f, v, c in BAD_ENVELOPE if not (f == "kind" and v == "nope")] + \
        [(k, f, v, c) for k, rows in BAD_FIELDS.items() for f, v, c in rows]


KEYS = KeySpace("unit")


def wire_stream(scenario):
    """(key, bytes) per sensor in publication order: measurements then a watermark per scan."""
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
    out.sort(key=lambda r: r[0])
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
