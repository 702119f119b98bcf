"""``zfusion router``: a Zenoh router in a Python process, for tests and small sites.

Production deployments use the official ``zenohd`` (see ``deploy/``); this one exists so
that a machine with only ``pip install zfusion`` can host a fabric.
"""

from __future__ import annotations

import json
import signal
import threading

import zenoh


def run(listen: list[str]) -> int:
    conf = zenoh.Config()
    conf.insert_json5("mode", '"router"')
    conf.insert_json5("listen/endpoints", json.dumps(listen))
    conf.insert_json5("scouting/multicast/enabled", "false")
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    session = zenoh.open(conf)
    try:
        print(f"zfusion router listening on {', '.join(listen)}", flush=True)
        stop.wait()
    finally:
        session.close()
    return 0
