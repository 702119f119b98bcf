"""The command line's names are checked before the heavy imports: an unknown method or
scenario, or a ``--set`` key no method takes, is one line, exit 2, with numpy, scipy, Zenoh and Rerun never loaded (it took
13-20 s at load 8 when the check came after them)."""

from __future__ import annotations

import json
import subprocess
import sys
from dataclasses import fields

import pytest

from fusion.df.methods import DFConfig
from fusion.methods import METHODS
from fusion.patent import TrackerConfig
from fusion.topology import METHOD_TOPOLOGIES, TRACKER_KEYS
from fusion.tracking.config import AssociationConfig
from services.commands.names import builtin_scenarios

HEAVY = ("numpy", "scipy", "zenoh", "rerun", "sensors_sim")
PROBE = ("import json, sys\n"
         "from services.cli import main\n"
         "code = main(sys.argv[1:])\n"
         f"print(json.dumps([code, sorted(m for m in {HEAVY!r} if m in sys.modules)]))\n")


@pytest.mark.parametrize("argv, says", [
    (["run", "--scenario", "patent-3d", "--method", "XYZ"], "zfusion run: unknown method 'XYZ'; known: EKF,"),
    (["run", "--scenario", "patent-3d", "--live", "--method", "XYZ"], "zfusion run: unknown method 'XYZ'"),
    (["run", "--scenario", "patnet-3d"], "zfusion run: unknown scenario 'patnet-3d': not a file, and not a "
                                         "built-in (air-picture,"),
    (["run", "--scenario", "/nonexistent/s.toml"], "zfusion run: /nonexistent/s.toml: cannot read scenario file"),
    (["eval", "--scenario", "patent-3d", "--runs", "1", "--methods", "SS", "NOPE"], "zfusion eval: unknown method 'NOPE'"),
    (["run", "--scenario", "patent-3d", "--set", "motoin=cv"],
     "zfusion run: unknown tracker config key 'motoin' (did you mean 'motion'? known: association,"),
    (["eval", "--scenario", "jammed-df", "--runs", "1", "--set", "q=1", "--set", "sigam=0.01"],
     "zfusion eval: unknown tracker config key 'sigam' (did you mean 'sigma'?"),
])
def test_an_unknown_name_is_refused_before_the_heavy_imports(argv, says):
    p = subprocess.run([sys.executable, "-c", PROBE, *argv], capture_output=True, text=True, timeout=60,
                       stdin=subprocess.DEVNULL)
    code, loaded = json.loads(p.stdout.strip().splitlines()[-1])
    assert code == 2, p.stderr
    lines = p.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(says), p.stderr
    assert loaded == [], loaded


def test_the_light_tables_are_the_registry_and_the_package():
    assert list(METHOD_TOPOLOGIES.items()) == [(n, s.topology) for n, s in METHODS.items()]
    assert TRACKER_KEYS == ({f.name for f in fields(TrackerConfig)} | {f.name for f in fields(DFConfig)}
                            | set(AssociationConfig.KEYS))
    from sensors_sim import list_scenarios

    assert builtin_scenarios() == [n for n, _ in list_scenarios()]
