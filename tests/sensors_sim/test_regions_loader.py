"""``[regions.<name>]`` in scenario and site files: parsed into fusion.regions.Region, and
every mistake one located line."""

from __future__ import annotations

import numpy as np
import pytest

from fusion.regions import boundary_distance
from sensors_sim import ScenarioError, load_scenario, load_site

HEAD = """\
description = "regions"
seed = 1
duration_s = 10.0

[origin]
lat_deg = 21.0
lon_deg = 105.8
alt_m = 0.0

[defaults]
topology = "centralised"
method = "SS"

[targets.T1]
pos_km = [1.0, 1.0, 2.0]
vel_mps = [100.0, 0.0, 0.0]

[sensors.a]
kind = "radar3d"
pos_km = [-10.0, 0.0, 0.0]
period_s = 1.0
std_az_deg = 0.3
std_el_deg = 0.3
std_range_m = 50.0

[sensors.b]
kind = "radar3d"
pos_km = [10.0, 0.0, 0.0]
period_s = 1.0
std_az_deg = 0.3
std_el_deg = 0.3
std_range_m = 50.0
"""

REGIONS = """
[regions.west]
box_km = [-20.0, -20.0, 0.0, 20.0]
margin_km = 5.0
sensors = ["a", "b"]

[regions.east]
polygon_m = [[0.0, -20000.0], [20000.0, -20000.0], [20000.0, 20000.0], [0.0, 20000.0]]
sensors = ["b"]
"""


def write(tmp_path, text):
    p = tmp_path / "case.toml"
    p.write_text(text)
    return p


def test_regions_load_in_metres(tmp_path):
    sc = load_scenario(write(tmp_path, HEAD + REGIONS))
    assert list(sc.regions) == ["west", "east"]
    west, east = sc.regions["west"], sc.regions["east"]
    assert west.margin == 5000.0 and east.margin == 0.0
    assert west.sensors == ("a", "b") and east.sensors == ("b",)
    np.testing.assert_array_equal(west.polygon, [[-20000, -20000], [0, -20000], [0, 20000], [-20000, 20000]])
    assert west.holds(np.array([[3000.0, 0.0], [6000.0, 0.0]])).tolist() == [True, False]
    assert east.inside(np.array([[3000.0, 0.0]])).tolist() == [True]


def test_no_regions_is_an_empty_table(tmp_path):
    assert load_scenario(write(tmp_path, HEAD)).regions == {}


def test_a_site_file_takes_regions(tmp_path):
    site = HEAD.split("[targets.T1]")[0].replace("seed = 1\nduration_s = 10.0\n", "")
    site += HEAD.split('vel_mps = [100.0, 0.0, 0.0]\n')[1] + REGIONS
    spec = load_site(write(tmp_path, site))
    assert set(spec.regions) == {"west", "east"}


@pytest.mark.parametrize("old, new, said", [
    ('sensors = ["b"]\n', 'sensors = ["b", "zz"]\n', r"regions\.east\.sensors: unknown sensor 'zz'"),
    ('sensors = ["b"]\n', 'sensors = []\n', r"regions\.east\.sensors: must be a non-empty list"),
    ("[[0.0, -20000.0], [20000.0, -20000.0], [20000.0, 20000.0], [0.0, 20000.0]]",
     "[[0.0, 0.0], [1.0, 1.0], [2.0, 2.0]]", r"regions\.east\.polygon_m: degenerate polygon"),
    ("[-20.0, -20.0, 0.0, 20.0]", "[0.0, -20.0, -20.0, 20.0]", r"regions\.west\.box_km: must be \[e_min"),
    ("[regions.east]", "[regions.\"ea st\"]", r"region names may use only"),
    ("margin_km = 5.0", "margin_km = -5.0", r"regions\.west\.margin_km: must be >= 0"),
    ("margin_km = 5.0", "margin_km = 5.0\npolygon_km = [[0, 0], [1, 0], [0, 1]]", r"not both"),
])
def test_bad_regions_are_one_located_line(tmp_path, old, new, said):
    text = HEAD + REGIONS
    assert old in text
    with pytest.raises(ScenarioError, match=said) as err:
        load_scenario(write(tmp_path, text.replace(old, new, 1)))
    assert "\n" not in str(err.value) and "case.toml:" in str(err.value)


def test_region_400_quadrants_are_fed_by_every_sensor_that_reaches_them():
    """region-400's four quadrants (and region-4000's, the same): together they cover the
    traffic box; each is fed by exactly the sensors whose coverage disk reaches it or its
    margin; each pair of neighbours overlaps by two margins."""
    small, large = load_scenario("region-400"), load_scenario("region-4000")
    assert list(small.regions) == list(large.regions) == ["nw", "ne", "sw", "se"]
    g = np.linspace(-200e3, 200e3, 41)
    box = np.array([[e, n] for e in g for n in g])
    assert np.all(np.any([r.inside(box) | (boundary_distance(box, r.polygon) < 1e-6)
                          for r in small.regions.values()], axis=0))
    for name, region in small.regions.items():
        other = large.regions[name]
        np.testing.assert_array_equal(region.polygon, other.polygon)
        assert (region.margin, region.sensors) == (other.margin, other.sensors) and region.margin == 25e3
        reach = []
        for sid, s in small.sensors.items():
            p = s.site.points[:1, :2]
            d = 0.0 if region.inside(p)[0] else boundary_distance(p, region.polygon)[0]
            if d <= s.max_range + region.margin:
                reach.append(sid)
        assert list(region.sensors) == reach, name
