"""A sensor emulator as a real process over Zenoh: byte-identical streams for one seed,
different streams for another."""

from __future__ import annotations

import socket
import subprocess
import sys

import pytest
import zenoh

from schemas import KeySpace, decode
from services.node import ZenohOptions

pytestmark = pytest.mark.slow


def _capture(deployment: str, seed: int) -> list[bytes]:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        ep = f"tcp/127.0.0.1:{s.getsockname()[1]}"
    keys = KeySpace(deployment)
    got: list[bytes] = []
    session = zenoh.open(ZenohOptions(listen=[ep]).to_config())
    try:
        sub = session.declare_subscriber(keys.meas("radar2d"), lambda smp: got.append(smp.payload.to_bytes()))
        token = session.liveliness().declare_token(keys.alive("probe"))
        p = subprocess.run([sys.executable, "-m", "services.cli", "sensor", "--scenario", "patent-3d", "--id",
                            "radar2d", "--speed", "max", "--seed", str(seed), "--wait-for", "probe",
                            "--deployment", deployment, "--connect", ep], capture_output=True, text=True, timeout=60)
        assert p.returncode == 0, p.stderr[-2000:]
        token.undeclare()
        sub.undeclare()
    finally:
        session.close()
    return got


def test_same_seed_same_bytes_other_seed_other_bytes(deployment):
    a = _capture(deployment + "a", 1)
    b = _capture(deployment + "b", 1)
    c = _capture(deployment + "c", 2)
    kinds = [decode(x).kind for x in a]
    assert kinds.count("range_az") == 31 and kinds.count("watermark") == 31
    assert decode(a[-1]).body["final"] is True
    assert a == b
    assert [x for x in a if decode(x).kind == "range_az"] != [x for x in c if decode(x).kind == "range_az"]
