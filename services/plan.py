"""``zfusion plan``: the processes of a run and the command that starts each by hand.

``zfusion run`` starts these same processes itself on one machine; a deployment over
several hosts starts them by hand (or from systemd units), each a Zenoh client of one
router. The plan lists them in a working start order:

1. the router;
2. the fuser (with ``--json``: it prints the result table and writes the summary when
   the sources are done) and the recorder (with ``--expect``: it stops once every
   process has reported done, else it runs until signalled);
3. the local trackers of a distributed, feedback or two-stage method;
4. the sources (sensors, the truth clock, jammers), each with ``--wait-for`` its
   consumers, so that nothing it publishes is lost before they listen.

The result is the same as that of ``zfusion run`` with the same scenario, method and
seed: the order of the measurements is fixed by their stamps and watermarks, not by when
each process started (docs/deploy.md).
"""

from __future__ import annotations

import shlex

from schemas import tracker_id

FUSER_ID = "fuser"
RECORDER_ID = "recorder"


def plan(scenario_ref: str, scenario, topology: str, method: str, connect: str, speed: str = "1",
         rrd: str = "site.rrd", json_path: str = "result.json") -> list[tuple[str, list[str]]]:
    """``(process id, argv)`` of every process of a hand-started run, in start order."""
    fabric = ["--zenoh-mode", "client", "--connect", connect]
    given = ["--scenario", scenario_ref, "--seed", str(scenario.seed)]
    trackers = {s: tracker_id(s) for s in scenario.sensors} if topology != "centralised" else {}
    sources = list(scenario.process_ids())
    out = [("router", ["router", "--listen", connect]),
           (FUSER_ID, ["fuser", *given, "--method", method, "--json", json_path, *fabric]),
           (RECORDER_ID, ["record", "--rrd", rrd, *given, "--expect",
                          ",".join([FUSER_ID, *trackers.values(), *sources]), *fabric])]
    out += [(tid, ["tracker", *given, "--sensor", s, "--method", method, *fabric]) for s, tid in trackers.items()]
    for sid in sources:
        consumers = [trackers.get(sid, FUSER_ID), RECORDER_ID] if sid in scenario.sensors else [RECORDER_ID]
        out.append((sid, ["sensor", *given, "--id", sid, "--speed", speed, "--wait-for", ",".join(consumers),
                          *fabric]))
    return out


def format_plan(scenario, topology: str, method: str, steps: list[tuple[str, list[str]]]) -> str:
    lines = [f"# scenario {scenario.name} · topology {topology} · method {method} · seed {scenario.seed} · "
             f"{len(steps) - 1} processes and a router",
             "# start each in its own shell (or end it with &), in this order; the fuser prints the result"]
    for name, argv in steps:
        lines += [f"# {name}", f"zfusion {shlex.join(argv)}"]
    return "\n".join(lines)
