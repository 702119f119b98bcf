"""``zfusion eval --topology regional``: refused in one line, before the heavy imports,
for a scenario without [regions] or a split method; scored like any many-target run
with the crossings of its regions, duplicates and id changes."""

from __future__ import annotations

import json
import subprocess
import sys

from services.cli import main
from conftest import ROOT

TWO_REGIONS = ROOT / "tests" / "data" / "two-regions.toml"
# a second aircraft, flying south in the east region, makes it an air picture (set metrics)
SECOND = """[targets.B]
pos_km = [30.0, 30.0, 8.0]
vel_mps = [0.0, -150.0, 0.0]

"""


def test_refusals_are_one_line_before_the_heavy_imports():
    code = ("import sys; from services.cli import main; "
            "rc = main(['eval', '--scenario', 'patent-3d', '--runs', '1', '--methods', 'SS', '--topology', 'regional']); "
            "print(rc, 'fusion.methods' in sys.modules, 'services.evaluation' in sys.modules)")
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert run.stdout.split() == ["2", "False", "False"], run
    assert run.stderr.count("\n") == 1 and "needs [regions.<name>]" in run.stderr and "patent-3d" in run.stderr


def test_split_methods_and_no_methods_are_refused(capsys):
    args = ["eval", "--scenario", str(TWO_REGIONS), "--runs", "1", "--topology", "regional"]
    assert main(args + ["--methods", "SS", "HNV"]) == 2
    assert "HNV is distributed" in capsys.readouterr().err
    assert main(args) == 2
    assert "name the centralised methods" in capsys.readouterr().err


def test_regional_eval_scores_the_system_picture(tmp_path, capsys):
    path = tmp_path / "two.toml"
    path.write_text(TWO_REGIONS.read_text().replace("[sensors.w]", SECOND + "[sensors.w]", 1))
    out = tmp_path / "r.json"
    assert main(["eval", "--scenario", str(path), "--runs", "2", "--methods", "SS", "--topology", "regional",
                 "--json", str(out)]) == 0
    doc = json.loads(out.read_text())
    ss = doc["methods"]["SS"]
    assert doc["topology"] == "regional"
    assert ss["crossings"] == 2  # A crosses from west to east in each run; B stays east
    assert ss["duplicates"] == 0 and ss["id_changes"] == 0 and ss["tracks"] == 4  # two system tracks a run
    assert set(ss["cpu_s"]) == {"west", "east", "system"}
    assert ss["held_after_init"] > 0.99
    central = tmp_path / "c.json"
    assert main(["eval", "--scenario", str(path), "--runs", "2", "--methods", "SS", "--json", str(central)]) == 0
    c = json.loads(central.read_text())["methods"]["SS"]
    assert c["crossings"] == 2 and "cpu_s" not in c  # the scenario's crossings, whatever the topology
    assert ss["gospa"] <= 1.05 * c["gospa"]
