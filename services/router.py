"""``zfusion router``: a Zenoh router in a Python process, for tests and small sites.

Production deployments use the official ``zenohd`` (see ``deploy/`` and docs/deploy.md);
this one exists so that a machine with only ``pip install zfusion`` can host a fabric. It
reads the same JSON5 files as ``zenohd`` (``deploy/zenoh/router*.json5``, TLS and access
control included: the Python wheel has both compiled in).

It stops within a second of SIGINT or SIGTERM, whichever thread the kernel hands the
signal to: Python runs its handler in the main thread only when that thread next runs
Python code, and a signal taken by one of Zenoh's threads does not wake a main thread
blocked without a timeout (it waited for ever). And it does not wait on Zenoh for ever
either: a session that has not closed :data:`CLOSE_WAIT_S` after the stop is left, with
one line on stderr. Once the session is closed there is nothing left to flush but stdio,
and the router leaves without the interpreter's teardown of its modules, which was most
of the time from signal to exit (50 ms on a quiet machine, 250 ms with eight busy
processes on two cores, against 10 ms for the close; over a second once in CI).
"""

from __future__ import annotations

import json
import os
import signal
import sys
import threading
from typing import NoReturn

import zenoh

from .node import ZenohOptions

DEFAULT_LISTEN = "tcp/127.0.0.1:7447"
WAKE_S = 0.2  # s: how often the main thread looks for a stop (a signal another thread took)
CLOSE_WAIT_S = 2.0  # s: how long a stopping router waits for its Zenoh session to close


def _close(session: zenoh.Session) -> None:
    """Close the session; a failure to is one line on stderr (the router is stopping anyway)."""
    try:
        session.close()
    except zenoh.ZError as e:
        print(f"zfusion router: closing its Zenoh session failed: {e}", file=sys.stderr, flush=True)


def run(listen: list[str] | None = None, config_file: str | None = None, overrides: list[str] = ()) -> NoReturn:
    """Serve until SIGINT/SIGTERM, then close the session and end the process with
    status 0 (it does not return). ``listen`` (if given) replaces the config file's
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
        while not stop.wait(WAKE_S):
            pass
    finally:
        closer = threading.Thread(target=_close, args=(session,), name="close", daemon=True)
        closer.start()
        closer.join(CLOSE_WAIT_S)
        if closer.is_alive():  # the interpreter's exit would wait on it again: leave at once
            print(f"zfusion router: its Zenoh session had not closed {CLOSE_WAIT_S:g} s after the stop; exiting "
                  "without it", file=sys.stderr, flush=True)
            os._exit(0)
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(0)  # closed: without the interpreter's teardown (module docstring)
