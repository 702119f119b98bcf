"""A sensor emulator as a real process over Zenoh: byte-identical streams for one seed,
different streams for another."""

from __future__ import annotations

import signal
import socket
import subprocess
import sys
import time

import pytest
import zenoh

from _runs import sensor_stream
from schemas import KeySpace, decode
from services.node import ZenohOptions

pytestmark = pytest.mark.slow


def test_same_seed_same_bytes_other_seed_other_bytes(deployment):
    a = sensor_stream(deployment + "a", "patent-3d", "radar2d", "--seed", "1", timeout=60)
    b = sensor_stream(deployment + "b", "patent-3d", "radar2d", "--seed", "1", timeout=60)
    c = sensor_stream(deployment + "c", "patent-3d", "radar2d", "--seed", "2", timeout=60)
    kinds = [decode(x).kind for x in a]
    assert kinds.count("range_az") == 31 and kinds.count("watermark") == 31
    assert decode(a[-1]).body["final"] is True
    assert a == b
    assert [x for x in a if decode(x).kind == "range_az"] != [x for x in c if decode(x).kind == "range_az"]


def test_a_restart_that_overlaps_the_old_session_is_seen(deployment):
    """A restarted process may declare its token before the loss of the old session is
    noticed (kill -9 under load). Tokens are per incarnation (``alive/<id>/<session>``),
    so the watcher sees the new one appear anyway: Zenoh merges tokens on one key, and a
    second token on the old key would go unseen. This is how a tracker notices a
    restarted fuser."""
    keys = KeySpace(deployment)
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        ep = f"tcp/127.0.0.1:{s.getsockname()[1]}"
    watcher = zenoh.open(ZenohOptions(listen=[ep]).to_config())
    old = zenoh.open(ZenohOptions(connect=[ep]).to_config())
    new = zenoh.open(ZenohOptions(connect=[ep]).to_config())
    seen: list[tuple[str, str]] = []
    try:
        sub = watcher.liveliness().declare_subscriber(
            keys.alive("fuser"), lambda smp: seen.append((str(smp.kind), *keys.alive_process(str(smp.key_expr)))),
            history=True)
        old_inc, new_inc = str(old.zid()), str(new.zid())
        old_token = old.liveliness().declare_token(keys.alive("fuser", old_inc))
        deadline = time.monotonic() + 10
        while len(seen) < 1 and time.monotonic() < deadline:
            time.sleep(0.02)
        new_token = new.liveliness().declare_token(keys.alive("fuser", new_inc))  # the old one still alive
        while len(seen) < 2 and time.monotonic() < deadline:
            time.sleep(0.02)
        put = str(zenoh.SampleKind.PUT)
        assert seen == [(put, "fuser", old_inc), (put, "fuser", new_inc)]
        for x in (new_token, old_token, sub):
            x.undeclare()
    finally:
        for s in (new, old, watcher):
            s.close()
    with pytest.raises(ValueError, match="incarnation"):
        keys.alive("fuser", "a/b")
    with pytest.raises(ValueError, match="not a liveliness token"):
        keys.alive_process(keys.status("fuser"))


def test_sigterm_while_it_waits_for_its_consumers_is_a_clean_stop(deployment):
    """A sensor stopped while it waits for ``--wait-for``'s processes (a run stopped
    before its fuser was up) says "stopped" at once and exits 0, not 2 as if the wait had
    failed. The times are bounds a loaded host keeps: quiet, the exit takes ~0.3 s; at
    load 15-20 (a CI beside four engineers' runs) it took 2.1 s, the interpreter's and the
    session's teardown, not the stop (a status says it first)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        ep = f"tcp/127.0.0.1:{s.getsockname()[1]}"
    keys = KeySpace(deployment)
    hub = zenoh.open(ZenohOptions(listen=[ep]).to_config())
    said: list[str] = []
    try:
        sub = hub.declare_subscriber(keys.status("radar2d"), lambda smp: said.append(decode(smp.payload.to_bytes())
                                                                                        .body["state"]))
        p = subprocess.Popen([sys.executable, "-m", "services.cli", "sensor", "--scenario", "patent-3d", "--id",
                              "radar2d", "--wait-for", "fuser", "--deployment", deployment, "--connect", ep],
                             stderr=subprocess.PIPE, text=True)
        deadline = time.monotonic() + 30
        while "starting" not in said and time.monotonic() < deadline:
            time.sleep(0.02)
        assert "starting" in said, p.stderr
        t = time.monotonic()
        p.send_signal(signal.SIGTERM)
        while "stopped" not in said and time.monotonic() < t + 10:
            time.sleep(0.02)
        told = time.monotonic() - t
        _, err = p.communicate(timeout=10)
        assert p.returncode == 0 and "Traceback" not in err, err
        assert told < 2.0 and time.monotonic() - t < 5.0, (told, time.monotonic() - t)
        sub.undeclare()
    finally:
        hub.close()
