"""docs/deploy.md walked through verbatim: the hand-started run of ``patent-3d`` (a plain
router on loopback, every process a client of it, started in the guide's order) gives
the same numbers as ``zfusion run``, and ``zfusion plan`` prints the guide's commands.
Two things are changed: the port (the guide's may be taken) and the sensors' pace,
``--speed 10`` for the guide's real time (the numbers do not depend on it: 3 s instead
of 30)."""

from __future__ import annotations

import json
import os
import re
import shlex
import signal
import subprocess
import sys

import pytest

from services.launcher import free_port
from conftest import ROOT

pytestmark = pytest.mark.slow
ROOT = ROOT
GUIDE = ROOT / "docs" / "deploy.md"


def guide_commands() -> list[str]:
    """The ``zfusion`` lines of the guide's block "A run started by hand, on one machine"."""
    text = GUIDE.read_text()
    section = text[text.index("## A run started by hand, on one machine"):]
    block = re.search(r"```sh\n(.*?)```", section, re.S).group(1)
    return [ln for ln in block.splitlines() if ln.startswith("zfusion ")]


def test_plan_prints_the_guides_commands():
    p = subprocess.run([sys.executable, "-m", "services.cli", "plan", "--scenario", "patent-3d"],
                       capture_output=True, text=True, timeout=60)
    assert p.returncode == 0, p.stderr
    assert [ln for ln in p.stdout.splitlines() if ln.startswith("zfusion ")] == guide_commands()


def test_the_guide_walked_verbatim_gives_the_run_numbers(tmp_path, patent_3d_run):
    lines = guide_commands()
    assert [shlex.split(ln)[1] for ln in lines] == ["router", "fuser", "record", "sensor", "sensor", "sensor"]
    port = str(free_port())  # the guide's port, 7447, may be taken: a free one, nothing else changed
    env = {**os.environ, "PYTHONUNBUFFERED": "1", "PYTHONPATH": str(ROOT)}
    procs = []
    try:
        for i, line in enumerate(lines):
            argv = [a.replace(":7447", f":{port}") for a in shlex.split(line)[1:]]
            if "--speed" in argv:
                assert argv[argv.index("--speed") + 1] == "1"  # the guide's real time
                argv[argv.index("--speed") + 1] = "10"
            piped = argv[0] in ("router", "fuser")
            procs.append(subprocess.Popen([sys.executable, "-m", "services.cli", *argv], cwd=tmp_path, env=env,
                                          stdout=subprocess.PIPE if piped else subprocess.DEVNULL,
                                          stderr=(tmp_path / f"{i}.log").open("w"), text=True))
            if argv[0] == "router":  # up before its clients dial it
                assert "listening" in procs[0].stdout.readline()
        fuser = procs[1]
        out, _ = fuser.communicate(timeout=240)
        assert fuser.returncode == 0, (tmp_path / "1.log").read_text()[-2000:]
        for p in procs[2:]:
            assert p.wait(60) == 0  # the recorder stops by itself (--expect), the sources at their end
    finally:
        for p in procs:
            if p.poll() is None:
                p.send_signal(signal.SIGINT)
                p.wait(20)
    got = json.loads((tmp_path / "result.json").read_text())
    assert (tmp_path / "site.rrd").stat().st_size > 0
    ref, _, r, _ = patent_3d_run  # zfusion run --scenario patent-3d
    for key in ("rmse_pos", "rmse_vel", "rmse_acc", "anees", "n_updates", "series"):
        assert got["methods"]["SS"][key] == ref["methods"]["SS"][key], key
    # the table it printed is the run's
    assert [ln for ln in out.splitlines() if ln.startswith("SS ")] == \
        [ln for ln in r.stdout.splitlines() if ln.startswith("SS ")]
