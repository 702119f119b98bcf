"""A tracker process sees a restarted fuser in the fuser's first downlink, whose
attachment names the process and Zenoh session that sent it, not only in the new
session's liveliness token: over another path through the fabric the token can come
after the new fuser's first horizon, and a node that took that horizon with its old
tracks sent their reports up, which the new centre drops (busy ci88: the many-target
restart test's picture was not the cold start's from the nodes' join)."""

from __future__ import annotations

import signal
import subprocess
import sys
import threading
import time

import pytest
import zenoh

from conftest import CROSSING
from schemas import KeySpace
from schemas.links import horizon_message
from services.launcher import free_port
from services.node import ZenohOptions

pytestmark = pytest.mark.slow

RESTARTED = "fuser restarted: tracks dropped, asking it for initial states again"


def _wait(condition, what: str, timeout: float = 60.0) -> None:
    deadline = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < deadline, what
        time.sleep(0.02)


def test_a_downlink_of_a_new_fuser_session_restarts_the_handshake(tmp_path, deployment):
    """The test's session is the fuser (its token, its horizons) of a many-target PHHNV
    tracker process. Horizons sent with the same session's name in their attachment,
    with a standby's (another process: it continues the leader's centre) and with none
    change nothing; one sent with another session of the fuser process — whose token
    never comes — makes the node drop its tracks and ask again, once; a horizon of the
    replaced session after it is not taken back for a second restart."""
    keys = KeySpace(deployment)
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    session = zenoh.open(ZenohOptions(listen=[endpoint]).to_config())
    token = session.liveliness().declare_token(keys.alive("fuser", str(session.zid())))
    ready = threading.Event()
    watch = session.liveliness().declare_subscriber(
        keys.alive("trk-angle"), lambda s: s.kind == zenoh.SampleKind.PUT and ready.set(), history=True)
    proc = subprocess.Popen([sys.executable, "-m", "services.cli", "tracker", "--scenario", str(CROSSING),
                             "--sensor", "angle", "--method", "PHHNV", "--fuser", "fuser",
                             "--deployment", deployment, "--connect", endpoint],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    lines: list[str] = []
    reader = threading.Thread(target=lambda: lines.extend(iter(proc.stderr.readline, "")), daemon=True)
    reader.start()
    try:
        _wait(ready.is_set, "the tracker never announced itself")
        down = session.declare_publisher(keys.feedback("trk-angle"), reliability=zenoh.Reliability.RELIABLE,
                                         congestion_control=zenoh.CongestionControl.BLOCK)
        _wait(lambda: down.matching_status.matching, "the tracker never subscribed to its feedback")
        other = "0123456789abcdef0123456789abcdef"  # a session id no token ever names
        mine = str(session.zid())
        standby = "fedcba9876543210fedcba9876543210"
        for seq, sender in enumerate([f"fuser/{mine}", f"fuser-b/{standby}", None, f"fuser/{other}",
                                      f"fuser/{mine}"], start=1):
            down.put(horizon_message("fuser", seq, 0.5), attachment=None if sender is None else sender.encode())
        # a fence: a horizon from another sender, refused (and said) after all of the above
        down.put(horizon_message("intruder", 1, 0.5))
        _wait(lambda: any("dropped message from intruder" in ln for ln in lines), f"no fence: {lines}")
    finally:
        proc.send_signal(signal.SIGINT)
        proc.wait(10)
        reader.join(5)
        watch.undeclare()
        token.undeclare()
        session.close()
    assert proc.returncode == 0, "".join(lines)[-3000:]
    assert sum(RESTARTED in ln for ln in lines) == 1, "".join(lines)[-3000:]
