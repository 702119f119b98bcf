"""``zfusion run`` end to end: separate OS processes over Zenoh, a real recording, a JSON
summary equal to the in-process evaluation, bad input shrugged off, clean Ctrl-C."""

from __future__ import annotations

import json
import math
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import msgpack
import numpy as np
import psutil
import pytest
import zenoh

from schemas import KeySpace, encode
from services.node import ZenohOptions

from conftest import zfusion
from _runs import FusedWatch, in_process
from _recording import rerun_exe

pytestmark = pytest.mark.slow


def _run(tmp_path: Path, *extra: str, timeout: float = 90) -> tuple[dict, Path, subprocess.CompletedProcess]:
    rrd, js = tmp_path / "out.rrd", tmp_path / "out.json"
    p = subprocess.run([sys.executable, "-m", "services.cli", "run", "--scenario", "patent-3d", "--rrd", str(rrd),
                        "--json", str(js), *extra], capture_output=True, text=True, timeout=timeout)
    assert p.returncode == 0, p.stderr[-3000:]
    return json.loads(js.read_text()), rrd, p


def test_run_patent_3d_max_speed(patent_3d_run):
    doc, rrd, p, seconds = patent_3d_run
    assert seconds < 90  # no wait on a dead peer (20 s at load 3.5; a loaded start takes 30)
    ss = doc["methods"]["SS"]
    radar_alone = in_process("patent-3d", "RADAR2D")["rmse_pos"]
    assert ss["rmse_pos"] < 0.2 * radar_alone, (ss["rmse_pos"], radar_alone)
    assert ss["n_updates"] == 31
    assert set(doc["sources"]) >= {"radar2d", "angle", "truth"}
    assert all(not s["dead_intervals"] and s["rejected"] == 0 for s in doc["sources"].values())
    assert "SS" in p.stdout and "rmse_pos" in p.stdout
    v = subprocess.run([rerun_exe(), "rrd", "verify", str(rrd)], capture_output=True, text=True)
    assert v.returncode == 0, v.stderr
    rows = rrd_rows(rrd)
    # one row per measurement and per fused update, read back from the file
    assert rows["/world/meas/radar2d"] == rows["/world/meas/angle"] == 31
    assert rows["/world/tracks/centre/T1"] == rows["/metrics/error_pos/SS"] == 31
    assert rows["/metrics/nees/SS"] == rows["/metrics/nees/SS/hi"] == 31
    assert rows["/world/truth/T1"] == 31


def rrd_rows(path: Path) -> dict[str, int]:
    """Rows per entity path of a recording, read from the file."""
    from rerun.chunk import RrdReader

    rows: dict[str, int] = {}
    for chunk in RrdReader(path).stream():
        if not chunk.is_static:
            rows[chunk.entity_path] = rows.get(chunk.entity_path, 0) + chunk.num_rows
    return rows


@pytest.mark.parametrize("speed", ["max", "5"])
def test_distributed_equals_in_process(tmp_path, deployment, speed, request):
    doc = (request.getfixturevalue("patent_3d_run") if speed == "max"
           else _run(tmp_path, "--speed", speed, "--deployment", deployment))[0]
    ref = in_process("patent-3d", "SS")
    got = doc["methods"]["SS"]
    assert got["n_updates"] == ref["n_updates"]
    assert got["series"]["t"] == ref["series"]["t"]
    for key in ("rmse_pos", "anees"):
        np.testing.assert_allclose(got["series"][key], ref["series"][key], rtol=0, atol=1e-9)


def _tree(pid: int) -> list[psutil.Process]:
    try:
        return psutil.Process(pid).children(recursive=True)
    except psutil.NoSuchProcess:
        return []


def _wait_children(pid: int, n: int, timeout: float = 120) -> list[psutil.Process]:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        kids = _tree(pid)
        if len(kids) >= n:
            return kids
        time.sleep(0.1)
    raise AssertionError(f"only {len(_tree(pid))} children after {timeout} s")


def test_processes_are_separate_and_ctrl_c_leaves_nothing(tmp_path, deployment):
    watch = FusedWatch(deployment)
    launcher = zfusion("run", "--scenario", "patent-3d", "--speed", "1", "--rrd", str(tmp_path / "x.rrd"),
                       "--deployment", deployment, "--connect", watch.endpoint,
                       stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        watch.wait_until(0.0, launcher, timeout=120)  # every process is up: the sources publish, the fuser fuses
        kids = _wait_children(launcher.pid, 5)
        roles = {}
        for k in _tree(launcher.pid):
            cmd = k.cmdline()
            roles[cmd[cmd.index("services.cli") + 1] + ":" + (cmd[cmd.index("--id") + 1] if "--id" in cmd else "")] = k.pid
        assert {"fuser:fuser", "record:recorder", "sensor:radar2d", "sensor:angle", "sensor:truth"} <= set(roles)
        assert len(set(roles.values())) == len(roles)  # really separate OS processes
        ports = {c.laddr.port for p in [psutil.Process(launcher.pid), *kids] for c in p.net_connections("tcp")
                 if c.status == psutil.CONN_LISTEN}
        assert ports
        launcher.send_signal(signal.SIGINT)
        out, err = launcher.communicate(timeout=30)
        assert launcher.returncode == 130, err[-2000:]
        for k in kids:
            assert not k.is_running() or k.status() == psutil.STATUS_ZOMBIE, k
        for port in ports:
            with socket.socket() as s:
                s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
                s.bind(("127.0.0.1", port))  # raises if anything still listens there
    finally:
        if launcher.poll() is None:
            launcher.kill()
        watch.close()


def test_garbage_on_the_wire_changes_nothing(tmp_path, deployment):
    """Hostile messages of every kind, injected into a live run, are counted and dropped;
    the fused output equals the in-process evaluation of the clean scenario."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    ep = f"tcp/127.0.0.1:{port}"
    session = zenoh.open(ZenohOptions(listen=[ep]).to_config())
    keys = KeySpace(deployment)
    try:
        rrd, js = tmp_path / "g.rrd", tmp_path / "g.json"
        launcher = zfusion("run", "--scenario", "patent-3d", "--speed", "4", "--rrd", str(rrd), "--json", str(js),
                           "--deployment", deployment, "--connect", ep, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
        pub = session.declare_publisher(keys.meas("radar2d"), congestion_control=zenoh.CongestionControl.BLOCK)
        spoof = session.declare_publisher(keys.meas("mallory"), congestion_control=zenoh.CongestionControl.BLOCK)
        fused = []
        sub = session.declare_subscriber(keys.fused("fuser"), lambda s: fused.append(1))
        deadline = time.monotonic() + 60
        while not fused and time.monotonic() < deadline:  # inject only once the run is going
            time.sleep(0.05)
        assert fused, "no fused output within 60 s"
        sub.undeclare()
        good = dict(v=1, kind="range_az", src="radar2d", seq=0, t=1.0, sensor="radar2d", site=[0.0, 0.0, 0.0],
                    az=0.5, std_az=0.01, range=1e4, std_range=20.0)
        bad = [b"\xc1\xc1", b"", msgpack.packb([1, 2, 3]), msgpack.packb({**good, "v": 99}),
               msgpack.packb({**good, "az": math.nan}), msgpack.packb({**good, "az": 7.0}),
               msgpack.packb({**good, "range": -1.0}), msgpack.packb({**good, "kind": "azel"}),
               msgpack.packb({**good, "site": [0.0]}), msgpack.packb({**good, "src": "angle"}),
               msgpack.packb({**good, "t": 1e6, "seq": 10**9}), msgpack.packb(good),  # far future; duplicate seq 0
               msgpack.packb({**good, "kind": "track"}), msgpack.packb({**good, "sensor": "angle"})]
        for _ in range(5):
            for b in bad:
                pub.put(b)
        spoof.put(encode("range_az", "mallory", 0, 2.0, sensor="mallory", site=[0.0, 0.0, 0.0], az=0.5,
                         std_az=0.01, range=1e4, std_range=20.0))
        out, err = launcher.communicate(timeout=90)
        assert launcher.returncode == 0, err[-3000:]
    finally:
        session.close()
    doc = json.loads(js.read_text())
    ref = in_process("patent-3d", "SS")
    np.testing.assert_allclose(doc["methods"]["SS"]["series"]["rmse_pos"], ref["series"]["rmse_pos"], atol=1e-9,
                               rtol=0)
    assert doc["sources"]["radar2d"]["rejected"] >= 5 * 10
    assert "angle" in doc["sources"] and doc["sources"]["angle"]["rejected"] == 0


def test_a_process_that_dies_at_start_up_ends_the_wait_at_once(deployment):
    """The launcher waits up to 60 s for the fuser and recorder to come up; one that has
    exited (here a fuser given a scenario that does not exist) will not, so the wait
    ends as soon as it is seen, with its exit code, and `zfusion run` fails (exit 1)
    instead of hanging for a minute."""
    from services.launcher import free_port
    from services.supervisor import Children
    from services.node import Node

    children = Children()
    children.start("fuser", ["fuser", "--scenario", "no-such-scenario", "--method", "EKF", "--id", "fuser",
                             "--deployment", deployment, "--connect", f"tcp/127.0.0.1:{free_port()}"])
    zopts = ZenohOptions(listen=[f"tcp/127.0.0.1:{free_port()}"])
    with Node("launcher", "launcher", KeySpace(deployment), zopts) as node:
        start = time.monotonic()
        with pytest.raises(TimeoutError, match=r"stopped waiting for fuser: fuser exited with code [1-9]"):
            node.wait_for(["fuser"], 60.0, gone=lambda: children.exited(["fuser"]))
        assert time.monotonic() - start < 30.0
    assert children.exited(["fuser"]).startswith("fuser exited with code")
    children.stop_all()
