"""Shared fixtures: every test that talks Zenoh gets its own deployment and free ports."""

from __future__ import annotations

import os
import subprocess
import sys
import time
import uuid
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]  # the repository
DATA = Path(__file__).resolve().parent / "data"
CROSSING = DATA / "crossing.toml"  # three aircraft crossing in clutter: the many-target scenario


@pytest.fixture
def deployment() -> str:
    return f"t{uuid.uuid4().hex[:10]}"


def wait_for(condition, what: str, timeout: float = 60.0, poll: float = 0.05):
    """Until ``condition()`` is true (returned), polling every ``poll`` s; fails naming
    ``what`` after ``timeout`` s (a loaded machine takes seconds to start a process)."""
    deadline = time.monotonic() + timeout
    while not (result := condition()):
        assert time.monotonic() < deadline, f"not within {timeout:g} s: {what}"
        time.sleep(poll)
    return result


def zfusion(*args: str, **kw) -> subprocess.Popen:
    """Start ``zfusion ARGS`` with this interpreter (the installed console script's code)."""
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    return subprocess.Popen([sys.executable, "-m", "services.cli", *args], env=env, **kw)


def _shared_run(tmp_path_factory, scenario: str, *extra: str, name: str | None = None):
    """``zfusion run --scenario SCENARIO --speed max EXTRA`` with a recording and a summary:
    ``(summary, recording path, completed process, wall seconds)``."""
    import json

    tmp = tmp_path_factory.mktemp(f"{name or scenario}-run")
    rrd, js = tmp / "out.rrd", tmp / "out.json"
    t0 = time.monotonic()
    p = subprocess.run([sys.executable, "-m", "services.cli", "run", "--scenario", scenario, "--speed", "max",
                        "--rrd", str(rrd), "--json", str(js), *extra,
                        *([] if "--deployment" in extra else ["--deployment", f"t{uuid.uuid4().hex[:10]}"])],
                       capture_output=True, text=True, timeout=600)
    assert p.returncode == 0, p.stderr[-3000:]
    return json.loads(js.read_text()), rrd, p, time.monotonic() - t0


# Runs shared by the tests that only read what they wrote (each distinct run is seconds of
# six or more processes starting up and working): the scenario's defaults, at --speed max.
@pytest.fixture(scope="session")
def patent_3d_run(tmp_path_factory):
    """patent-3d: centralised SS (:func:`_shared_run`)."""
    return _shared_run(tmp_path_factory, "patent-3d")


@pytest.fixture(scope="session")
def df_multi_run(tmp_path_factory):
    """df-multi: centralised EKF around the emitter association (:func:`_shared_run`)."""
    return _shared_run(tmp_path_factory, "df-multi")


@pytest.fixture(scope="session")
def crossing_run(tmp_path_factory):
    """:data:`CROSSING`: centralised SS, many targets (:func:`_shared_run`), watched from a
    session of the test's own that the run dials: ``(..., published)``, the fused
    estimates the fuser published per track id."""
    import zenoh

    from schemas import KeySpace, decode
    from services.launcher import free_port
    from services.node import ZenohOptions

    deployment = f"t{uuid.uuid4().hex[:10]}"
    ep = f"tcp/127.0.0.1:{free_port()}"
    published: dict[str, int] = {}

    def on_fused(sample) -> None:
        msg = decode(sample.payload.to_bytes())
        if msg.kind == "track":
            published[msg.body["track"]] = published.get(msg.body["track"], 0) + 1

    with zenoh.open(ZenohOptions(listen=[ep]).to_config()) as session:
        sub = session.declare_subscriber(KeySpace(deployment).fused(), on_fused)
        try:
            run = _shared_run(tmp_path_factory, str(CROSSING), "--connect", ep, "--deployment", deployment,
                              name="crossing")
        finally:
            sub.undeclare()
    return (*run, published)


@pytest.fixture(scope="session")
def crossing():
    """The loaded :data:`CROSSING` scenario."""
    from sensors_sim import load_scenario

    return load_scenario(CROSSING)
