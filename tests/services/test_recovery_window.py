"""The recovery window, ``recovery_s`` of a site or scenario file (docs/live.md): it sizes
every live publisher's cache (a sensor's, a tracker's and the fuser's through
:func:`services.source.recovery_cache`, a gateway's through
:func:`services.ingest.process.gateway_cache`), 30 s when the file does not say, and a
value that is not a number of seconds in (0, 3600] is refused on one line, exit 2,
before anything starts."""

from __future__ import annotations

import subprocess
import sys
import textwrap
from types import SimpleNamespace

import pytest

from _scenarios import HEADER
from conftest import ROOT
from sensors_sim.spec import RECOVERY_S
from services.errors import UserError
from services.ingest.process import TICK_S, _site_sensors, gateway_cache
from services.scenario import load, load_site
from services.source import recovery_cache

SITE = "recovery_s = 5.0\n" + HEADER + textwrap.dedent("""\
    [sensors.df]
    kind = "df"
    pos_m = [0.0, 0.0, 0.0]
    period_s = 2.0
    std_az_deg = 1.0
""")


def _with(tmp_path, scenario: str, line: str) -> str:
    """The built-in ``scenario`` with ``line`` first, as a file of that name."""
    path = tmp_path / f"{scenario}.toml"
    path.write_text(line + "\n" + (ROOT / "sensors_sim/scenarios" / f"{scenario}.toml").read_text(encoding="utf-8"),
                    encoding="utf-8")
    return str(path)


def test_the_default_is_30_s_and_sizes_the_caches_as_before():
    sc = load("patent-3d-orbit")
    assert sc.recovery == RECOVERY_S == 30.0 and load_site("patent-3d-orbit").recovery == 30.0
    # twice 30 s of one target's plot and one watermark a second
    assert [recovery_cache(sc, s) for s in sc.sensors] == [120, 120]
    assert gateway_cache(1.0, RECOVERY_S) == 2 * 30 * (2 + 1 / TICK_S) == 720


def test_the_window_sizes_the_sensors_and_the_gateways_caches(tmp_path):
    """patent-3d-orbit with 10 s: each sensor's cache is a third of the default's, as
    taken by a scenario run's processes (``--scenario``) and a live session's
    (``--site``); air-picture-live with 5 s: 2 x 5 s x (20 aircraft at most + 10 false
    alarms + 1 watermark) a radar scan of 1 s."""
    ref = _with(tmp_path, "patent-3d-orbit", "recovery_s = 10.0")
    default = load("patent-3d-orbit")
    for sc in (load(ref), load_site(ref)):
        assert sc.recovery == 10.0
        assert [recovery_cache(sc, s) for s in sc.sensors] == [40, 40]
        assert [3 * recovery_cache(sc, s) for s in sc.sensors] == [recovery_cache(default, s) for s in sc.sensors]
    many = load(_with(tmp_path, "air-picture-live", "recovery_s = 5"))
    assert recovery_cache(many, "radar1") == 2 * 5 * (20 + 10 + 1) and recovery_cache(many, "angle1") == 2 * 5 * 26
    assert gateway_cache(1.0, 10.0) == 240 and gateway_cache(2.0, 5.0) == 2 * 5 * (1 + 10)


def test_a_gateway_takes_the_window_of_its_site_file(tmp_path):
    (tmp_path / "site.toml").write_text(SITE, encoding="utf-8")
    assert load_site(str(tmp_path / "site.toml")).recovery == 5.0
    _, sensors, recovery = _site_sensors(SimpleNamespace(site=str(tmp_path / "site.toml")), ["df"])
    assert recovery == 5.0 and gateway_cache(sensors["df"].period, recovery) == 2 * 5 * (1 + 10)


@pytest.mark.parametrize("value, why", [
    ("0", "must be > 0 (got 0)"),
    ("-10.0", "must be > 0 (got -10)"),
    ("7200", "must be <= 3600 (got 7200)"),
    ("inf", "must be a finite number"),
    ("nan", "must be a finite number"),
    ('"10"', "must be a finite number"),
    ("true", "must be a finite number"),
])
def test_a_bad_window_is_refused_on_one_line(tmp_path, value, why):
    ref = _with(tmp_path, "patent-3d-orbit", f"recovery_s = {value}")
    for loader in (load, load_site):
        with pytest.raises(UserError) as e:
            loader(ref)
        assert str(e.value) == f"{ref}:1: recovery_s: {why}"


def test_a_bad_or_misspelt_window_stops_the_command_before_it_starts(tmp_path):
    """``zfusion plan`` (which loads the scenario as ``run`` does): exit 2, one line on
    stderr naming the file, the line and the key; ``recovery`` for ``recovery_s`` is named
    as a misspelling."""
    for line, said in (("recovery_s = 0", "recovery_s: must be > 0 (got 0)"),
                       ("recovery = 10", "recovery: unknown key (did you mean 'recovery_s'?")):
        ref = _with(tmp_path, "patent-3d-orbit", line)
        p = subprocess.run([sys.executable, "-m", "services.cli", "plan", "--scenario", ref],
                           capture_output=True, text=True, timeout=60)
        assert p.returncode == 2 and p.stdout == "", (p.returncode, p.stdout)
        assert p.stderr.count("\n") == 1 and f"patent-3d-orbit.toml:1: {said}" in p.stderr, p.stderr
