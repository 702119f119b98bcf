"""Scenario loader: units to SI, geodetic sites, and located errors for bad files."""

from __future__ import annotations

import math
import re

import numpy as np
import pymap3d
import pytest

from sensors_sim import ScenarioError, load_scenario
from sensors_sim.segments import ConstantAcceleration, CoordinatedTurn, Static, Waypoints
from conftest import ROOT

GOOD = """\
description = "loader test"
seed = 4
duration_s = 30.0
truth_dt_s = 0.5

[origin]
lat_deg = 21.0285
lon_deg = 105.8542
alt_m = 10.0

[defaults]
topology = "centralised"
method = "SS"

[tracker]
motion = "ca"
q = 0.01

[targets.T1]
pos_km = [6.0, 8.0, 2.0]
vel_mps = [-120.0, -60.0, 5.0]
acc_mps2 = [0.5, 1.0, -0.05]
jerk_psd = 0.01

[[targets.T1.segments]]
type = "ca"
duration_s = 10.0

[[targets.T1.segments]]
type = "turn"
turn_rate_deg_s = 2.0

[targets.E1]
lat_deg = 21.10
lon_deg = 105.90
alt_m = 0.0
segments = [{ type = "static" }]

[sensors.radar2d]
kind = "radar2d"
pos_m = [0.0, 0.0, 0.0]
period_s = 1.0
std_az_deg = 1.0
std_range_m = 20.0
fov_az_deg = [300.0, 60.0]
max_range_km = 50.0

[sensors.angle]
kind = "angle"
lat_deg = 21.0300
lon_deg = 105.8600
alt_m = 25.0
period_s = 0.5
start_s = 0.5
std_az_rad = 0.001
std_el_deg = 0.05
p_detect = 0.9
fov_el_deg = [0.0, 80.0]
band = "X"

[jammers.jam]
pos_km = [20.0, 25.0, 3.0]
mode = "spot"
band = "X"
search_delay_s = 5.0
schedule_s = [[10.0, 20.0], [25.0, inf]]
range_km = 100.0
power_w = 3.0
outlier_law = "uniform"
outlier_std_deg = 5.0
"""


def write(tmp_path, text, name="case.toml"):
    path = tmp_path / name
    path.write_text(text)
    return path


def line_of(text: str, marker: str) -> int:
    """1-based line of the first line containing ``marker`` (the test's own oracle)."""
    for i, line in enumerate(text.splitlines(), 1):
        if marker in line:
            return i
    raise AssertionError(f"{marker!r} not in the test text")


def test_good_file_loads_in_si_units(tmp_path):
    sc = load_scenario(write(tmp_path, GOOD))
    assert (sc.name, sc.seed, sc.duration, sc.truth_dt) == ("case", 4, 30.0, 0.5)
    assert sc.origin == (21.0285, 105.8542, 10.0)
    assert sc.tracker == {"motion": "ca", "q": 0.01}
    assert sc.defaults == {"topology": "centralised", "method": "SS"}
    np.testing.assert_allclose(sc.targets["T1"].x0, [6000, 8000, 2000, -120, -60, 5, 0.5, 1.0, -0.05])
    segs = sc.targets["T1"].segments
    assert isinstance(segs[0], ConstantAcceleration) and segs[0].duration == 10.0
    assert isinstance(segs[1], CoordinatedTurn) and segs[1].rate == pytest.approx(math.radians(2.0))
    assert isinstance(sc.targets["E1"].segments[0], Static)
    r, a = sc.sensors["radar2d"], sc.sensors["angle"]
    np.testing.assert_allclose(r.std, [math.radians(1.0), 20.0])
    np.testing.assert_allclose(r.fov_az, [math.radians(300.0), math.radians(120.0)])
    assert r.max_range == 50e3 and r.fov_el == (-math.pi / 2, math.pi / 2) and r.p_detect == 1.0
    np.testing.assert_allclose(a.std, [0.001, math.radians(0.05)])
    np.testing.assert_allclose(a.fov_el, [0.0, math.radians(80.0)])
    assert (a.period, a.start, a.p_detect, a.band, a.targets) == (0.5, 0.5, 0.9, "X", ("T1", "E1"))
    j = sc.jammers["jam"]
    assert (j.mode, j.band, j.search_delay, j.reach, j.power, j.outlier_law) == ("spot", "X", 5.0, 100e3, 3.0, "uniform")
    assert j.schedule == ((10.0, 20.0), (25.0, math.inf))
    assert j.outlier_std == pytest.approx(math.radians(5.0)) and j.p_outlier is None and j.period == 1.0
    assert sc.process_ids() == ["radar2d", "angle", "jam", "truth"]
    assert sc.kind_of("angle") == "angle" and sc.kind_of("radar2d") == "radar2d"


def test_geodetic_sites_are_converted_to_local_enu(tmp_path):
    sc = load_scenario(write(tmp_path, GOOD))
    want = pymap3d.geodetic2enu(21.0300, 105.8600, 25.0, 21.0285, 105.8542, 10.0)
    np.testing.assert_allclose(sc.sensors["angle"].site.position(0.0), want, atol=1e-6)
    want = pymap3d.geodetic2enu(21.10, 105.90, 0.0, 21.0285, 105.8542, 10.0)
    np.testing.assert_allclose(sc.targets["E1"].x0[:3], want, atol=1e-6)
    assert 5000 < sc.targets["E1"].x0[1] < 9000  # ~0.07° of latitude north


def test_waypoints_and_paths(tmp_path):
    text = GOOD.replace("""[[targets.T1.segments]]
type = "turn"
turn_rate_deg_s = 2.0
""", """[[targets.T1.segments]]
type = "waypoints"
points_km = [[1.0, 2.0], [3.0, 4.0, 5.0]]
speed_mps = 200.0
""").replace("""kind = "radar2d"
pos_m = [0.0, 0.0, 0.0]""", """kind = "radar2d"
path_km = [[0.0, 0.0], [1.0, 0.0]]
path_t_s = [0.0, 10.0]""")
    sc = load_scenario(write(tmp_path, text))
    seg = sc.targets["T1"].segments[1]
    assert isinstance(seg, Waypoints) and seg.speed == 200.0
    np.testing.assert_allclose(seg.points, [[1000, 2000, 0], [3000, 4000, 5000]])
    np.testing.assert_allclose(sc.sensors["radar2d"].site.position(5.0), [500.0, 0.0, 0.0])


# Each bad file: (edit of GOOD, field path in the message, marker of the line it must
# name, fragment of the reason). The marker is searched in the *edited* text.
BAD = {
    "negative std": (("std_range_m = 20.0", "std_range_m = -20.0"),
                     "sensors.radar2d.std_range_m", "std_range_m = -20.0", "must be > 0"),
    "zero period": (("period_s = 0.5", "period_s = 0.0"),
                    "sensors.angle.period_s", "period_s = 0.0", "must be > 0"),
    "unknown key": (("max_range_km = 50.0", "max_range_km = 50.0\ncolour = \"red\""),
                    "sensors.radar2d.colour", "colour", "unknown key"),
    "missing field": (("std_el_deg = 0.05\n", ""),
                      "sensors.angle.std_el_rad", "[sensors.angle]", "missing"),
    "missing top-level": (("seed = 4\n", ""), "seed", "description", "missing"),
    "missing table": (("[defaults]\ntopology = \"centralised\"\nmethod = \"SS\"\n", ""),
                      "defaults", "description", "missing"),
    "wrong type": (("seed = 4", "seed = \"four\""), "seed", "seed = ", "must be an integer"),
    "site on a target": (("pos_m = [0.0, 0.0, 0.0]", "pos_m = [6000.0, 8000.0, 2000.0]"),
                         "sensors.radar2d.pos_m", "pos_m = [6000.0", "same place as 'T1'"),
    "two units": (("std_range_m = 20.0", "std_range_m = 20.0\nstd_range_km = 0.02"),
                  "sensors.radar2d.std_range_km", "std_range_km", "only one of"),
    "probability > 1": (("p_detect = 0.9", "p_detect = 1.5"),
                        "sensors.angle.p_detect", "p_detect", "must be <= 1"),
    "bad kind": (('kind = "angle"', 'kind = "sonar"'), "sensors.angle.kind", "sonar", "must be one of"),
    "elevation limits reversed": (("fov_el_deg = [0.0, 80.0]", "fov_el_deg = [80.0, 0.0]"),
                                  "sensors.angle.fov_el_deg", "fov_el_deg", "lowest < highest"),
    "segment without duration": (("type = \"ca\"\nduration_s = 10.0\n", "type = \"ca\"\n"),
                                 "targets.T1.segments[0].duration_s", "[[targets.T1.segments]]",
                                 "only the last segment"),
    "second segment bad rate": (("turn_rate_deg_s = 2.0", "turn_rate_deg_s = 0.0"),
                                "targets.T1.segments[1].turn_rate_deg_s", "turn_rate_deg_s", "must be != 0"),
    "noise without grid": (("truth_dt_s = 0.5\n", ""), "targets.T1.jerk_psd", "jerk_psd", "truth_dt_s"),
    "scans off the grid": (("period_s = 0.5", "period_s = 0.75"),
                           "sensors.angle.period_s", "period_s = 0.75", "truth grid"),
    "spot without band": (('mode = "spot"\nband = "X"\n', 'mode = "spot"\n'),
                          "jammers.jam.band", "[jammers.jam]", "missing"),
    "overlapping schedule": (("[[10.0, 20.0], [25.0, inf]]", "[[10.0, 20.0], [15.0, inf]]"),
                             "jammers.jam.schedule_s", "schedule_s", "not overlapping"),
    "bad outlier law": (('outlier_law = "uniform"', 'outlier_law = "cauchy"'),
                        "jammers.jam.outlier_law", "cauchy", "laplacian, uniform"),
    "unknown target ref": (("band = \"X\"\n\n[jammers", "band = \"X\"\ntargets = [\"T7\"]\n\n[jammers"),
                           "sensors.angle.targets", "T7", "unknown target 'T7'"),
    "jammer ref by a radar": (("max_range_km = 50.0", "max_range_km = 50.0\ntargets = [\"jam\"]"),
                              "sensors.radar2d.targets", "targets = [\"jam\"]", "only DF sensors"),
    "duplicate id": (("[sensors.angle]", "[sensors.T1]"), "sensors.T1", "[sensors.T1]", "already used"),
    "reserved id": (("[sensors.angle]", "[sensors.truth]"), "sensors.truth", "[sensors.truth]", "truth process"),
    "bad topology": (('topology = "centralised"', 'topology = "star"'),
                     "defaults.topology", "star", "must be one of"),
    "latitude out of range": (("lat_deg = 21.0285", "lat_deg = 121.0"), "origin.lat_deg", "121.0", "<= 90"),
    "first scan after the end": (("start_s = 0.5", "start_s = 40.0"),
                                 "sensors.angle.start_s", "start_s", "after the end"),
}


@pytest.mark.parametrize("case", list(BAD), ids=list(BAD))
def test_bad_files_name_file_line_and_field(tmp_path, case):
    (old, new), field, marker, reason = BAD[case]
    assert old in GOOD
    text = GOOD.replace(old, new, 1)
    path = write(tmp_path, text, "bad-case.toml")
    with pytest.raises(ScenarioError) as info:
        load_scenario(path)
    msg = str(info.value)
    assert msg.startswith(f"{path}:{line_of(text, marker)}: {field}: "), msg
    assert reason in msg, msg


def test_toml_syntax_error_names_its_line(tmp_path):
    text = GOOD.replace("q = 0.01", "q = = 0.01")
    path = write(tmp_path, text, "syntax.toml")
    with pytest.raises(ScenarioError, match=rf"^{re.escape(str(path))}:{line_of(text, 'q = =')}: invalid TOML"):
        load_scenario(path)


def test_multiline_arrays_do_not_look_like_table_headers(tmp_path):
    text = GOOD.replace("""kind = "radar2d"
pos_m = [0.0, 0.0, 0.0]""", """kind = "radar2d"
path_km = [
  [0.0, 0.0],
  [1.0, 0.0]
]
path_t_s = [0.0, -10.0]""")
    path = write(tmp_path, text, "multi.toml")
    with pytest.raises(ScenarioError) as info:
        load_scenario(path)
    assert str(info.value).startswith(f"{path}:{line_of(text, 'path_t_s')}: sensors.radar2d.path_t_s: ")


def test_missing_file_and_unknown_name(tmp_path):
    with pytest.raises(ScenarioError, match="cannot read"):
        load_scenario(tmp_path / "nope.toml")
    with pytest.raises(ScenarioError, match="unknown scenario 'no-such-scenario'.*patent-3d"):
        load_scenario("no-such-scenario")


def test_endless_is_a_boolean_of_scenarios_that_can_go_on(tmp_path):
    from sensors_sim import load_scenario

    assert load_scenario("patent-3d-orbit").endless and load_scenario("air-picture-live").endless
    assert not load_scenario("patent-3d").endless
    text = (ROOT / "sensors_sim/scenarios/patent-3d-orbit.toml").read_text()
    (tmp_path / "bad.toml").write_text(text.replace("endless = true", 'endless = "yes"'))
    with pytest.raises(ScenarioError, match="endless"):
        load_scenario(tmp_path / "bad.toml")


@pytest.mark.parametrize("old, new, said", [
    ("period_s = 1.0", "perod_s = 1.0", "sensors.radar2d.period_s: missing (required; 'perod_s' is given: "
                                        "a misspelling of 'period_s'?)"),
    ("std_az_deg = 1.0", "std_az_dg = 1.0", "'std_az_dg' is given: a misspelling of 'std_az_deg'?"),
    ("duration_s = 30.0", "duraton_s = 30.0", "duration_s: missing (required; 'duraton_s' is given"),
])
def test_a_misspelt_required_key_is_named(tmp_path, old, new, said):
    with pytest.raises(ScenarioError) as info:
        load_scenario(write(tmp_path, GOOD.replace(old, new, 1), "typo.toml"))
    assert said in str(info.value)


def test_a_valid_sibling_key_is_not_taken_for_a_misspelling(tmp_path):
    """The angle sensor's std_el_deg is close to the missing std_az_deg but is a key of
    its own: the message must not call it a misspelling."""
    with pytest.raises(ScenarioError) as info:
        load_scenario(write(tmp_path, GOOD.replace("std_az_rad = 0.001\n", "", 1), "sibling.toml"))
    assert "std_az" in str(info.value) and "misspelling" not in str(info.value)


def test_an_unknown_key_close_to_an_allowed_one_is_suggested(tmp_path):
    with pytest.raises(ScenarioError) as info:
        load_scenario(write(tmp_path, GOOD.replace("max_range_km = 50.0", "max_range_km = 50.0\np_detct = 0.9", 1),
                            "unknown.toml"))
    assert "sensors.radar2d.p_detct: unknown key (did you mean 'p_detect'?" in str(info.value)
