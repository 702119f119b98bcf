"""Shared fixtures: every test that talks Zenoh gets its own deployment and free ports."""

from __future__ import annotations

import fcntl
import json
import os
import subprocess
import sys
import time
import uuid
from pathlib import Path
from types import SimpleNamespace

import pytest

import services  # noqa: F401  (before any NumPy: one BLAS thread here and in the workers, as in the services)

ROOT = Path(__file__).resolve().parents[1]  # the repository
DATA = Path(__file__).resolve().parent / "data"
CROSSING = DATA / "crossing.toml"  # three aircraft crossing in clutter: the many-target scenario


def pytest_collection_modifyitems(config, items):
    """The tests marked ``spread`` (long live runs with no fixture of a wider scope than
    the test) are spread evenly through the collection. xdist's load scheduler hands
    each worker consecutive tests in chunks of up to a twelfth of what is left: a module
    of 14 live runs of 25–57 s went to one worker in one chunk and ran there one after the
    other: 470 s of a 783 s run at -n 4 (a per-test timeline), and the last minutes of a
    run at -n 6 with the machine otherwise idle (11:18 against 8:26 for the same commit)."""
    spread = [it for it in items if it.get_closest_marker("spread")]
    if not spread:
        return
    rest = [it for it in items if not it.get_closest_marker("spread")]
    step = len(rest) / len(spread)
    out: list = []
    for k, it in enumerate(spread):  # one before each step-th of the others
        out.append(it)
        out += rest[round(k * step):round((k + 1) * step) if k + 1 < len(spread) else len(rest)]
    items[:] = out


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


def _shared_run(tmp_path_factory, scenario: str, *extra: str, name: str | None = None,
                watch: bool = False) -> tuple:
    """``zfusion run --scenario SCENARIO --speed max EXTRA`` with a recording and a
    summary, made once per test session: the first worker to ask makes it under a file
    lock in the directory every xdist worker of the session shares, the others wait for
    it and read what it wrote. ``(summary, recording path, process, wall seconds)``, the
    process's ``stdout``, ``stderr`` and ``returncode`` as attributes; with ``watch``, a
    test session the run dials has counted the fused estimates it published per track:
    ``(..., published)``."""
    base = tmp_path_factory.getbasetemp()
    shared = (base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base) / f"shared-{name or scenario}"
    shared.mkdir(exist_ok=True)
    result = shared / "result.json"
    with open(shared / "lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # released when the file is closed
        if not result.exists():
            result.write_text(json.dumps(_run_once(shared, scenario, extra, watch)))
    r = json.loads(result.read_text())
    assert r["returncode"] == 0, r["stderr"][-3000:]
    out = (json.loads((shared / "out.json").read_text()), shared / "out.rrd", SimpleNamespace(**r), r["seconds"])
    return (*out, r["published"]) if watch else out


def _run_once(where: Path, scenario: str, extra: tuple[str, ...], watch: bool) -> dict:
    deployment = f"t{uuid.uuid4().hex[:10]}"
    published: dict[str, int] = {}
    t0 = time.monotonic()
    if watch:
        import zenoh

        from schemas import KeySpace, decode
        from services.launcher import free_port
        from services.node import ZenohOptions

        ep = f"tcp/127.0.0.1:{free_port()}"

        def on_fused(sample) -> None:
            msg = decode(sample.payload.to_bytes())
            if msg.kind == "track":
                published[msg.body["track"]] = published.get(msg.body["track"], 0) + 1

        with zenoh.open(ZenohOptions(listen=[ep]).to_config()) as session:
            sub = session.declare_subscriber(KeySpace(deployment).fused("fuser"), on_fused)
            try:
                p = _run_cli(where, scenario, (*extra, "--connect", ep), deployment)
            finally:
                sub.undeclare()
    else:
        p = _run_cli(where, scenario, extra, deployment)
    return {"stdout": p.stdout, "stderr": p.stderr, "returncode": p.returncode,
            "seconds": time.monotonic() - t0, "published": published}


def _run_cli(where: Path, scenario: str, extra: tuple[str, ...], deployment: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "services.cli", "run", "--scenario", scenario, "--speed", "max",
                           "--rrd", str(where / "out.rrd"), "--json", str(where / "out.json"), *extra,
                           "--deployment", deployment], capture_output=True, text=True, timeout=600)


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
    """:data:`CROSSING`: centralised SS, many targets, watched (:func:`_shared_run`)."""
    return _shared_run(tmp_path_factory, str(CROSSING), name="crossing", watch=True)


@pytest.fixture(scope="session")
def crossing():
    """The loaded :data:`CROSSING` scenario."""
    from sensors_sim import load_scenario

    return load_scenario(CROSSING)
