"""``zfusion router``: a Zenoh router in a Python process, for tests and small sites.

Production deployments use the official ``zenohd`` (see ``deploy/`` and docs/deploy.md);
this one exists so that a machine with only ``pip install zfusion`` can host a fabric. It
reads the same JSON5 files as ``zenohd`` (``deploy/zenoh/router*.json5``, TLS and access
control included: the Python wheel has both compiled in).
"""

from __future__ import annotations

import json
import signal
import threading

import zenoh

from .node import ZenohOptions

DEFAULT_LISTEN = "tcp/127.0.0.1:7447"


def run(listen: list[str] | None = None, config_file: str | None = None, overrides: list[str] = ()) -> int:
    """Serve until SIGINT/SIGTERM. ``listen`` (if given) replaces the config file's
    endpoints; without a file the router listens on ``DEFAULT_LISTEN``."""
    more = [f"listen/endpoints={json.dumps(listen)}"] if config_file and listen else []
    conf = ZenohOptions(mode="router", listen=listen or [DEFAULT_LISTEN], config_file=config_file,
                        overrides=[*more, *overrides]).to_config()
    zenoh.try_init_log_from_env()  # RUST_LOG=...: e.g. what access control denies
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    session = zenoh.open(conf)
    try:
        print(f"zfusion router listening on {conf.get_json('listen/endpoints')}", flush=True)
        stop.wait()
    finally:
        session.close()
    return 0
