"""``[regions.<name>]`` in scenario and site files: parsed into fusion.regions.Region, and
every mistake one located line."""

from __future__ import annotations

import numpy as np
import pytest

from fusion.regions import boundary_distance
from sensors_sim import ScenarioError, load_scenario, load_site
from conftest import ROOT

TWO_REGIONS = ROOT / "tests" / "data" / "two-regions.toml"
SITE_KEYS = ("seed", "duration_s", "[targets.A]", "pos_km = [-25.0", "vel_mps")  # lines only a scenario has


def case(east: str | None = None) -> str:
    """tests/data/two-regions.toml, the east region given as a polygon in metres (or ``east``)."""
    text = TWO_REGIONS.read_text()
    head, _ = text.split("[regions.east]")
    return head + "[regions.east]\n" + (east if east is not None else
                                        "polygon_m = [[0.0, -60000.0], [60000.0, -60000.0], [60000.0, 60000.0], "
                                        "[0.0, 60000.0]]\nsensors = [\"e\", \"s\"]\n")


def write(tmp_path, text):
    p = tmp_path / "case.toml"
    p.write_text(text)
    return p


def test_regions_load_in_metres(tmp_path):
    sc = load_scenario(write(tmp_path, case()))
    assert list(sc.regions) == ["west", "east"]
    west, east = sc.regions["west"], sc.regions["east"]
    assert west.margin == 8000.0 and east.margin == 0.0
    assert west.sensors == ("w", "s") and east.sensors == ("e", "s")
    np.testing.assert_array_equal(west.polygon, [[-60000, -60000], [0, -60000], [0, 60000], [-60000, 60000]])
    assert west.holds(np.array([[7000.0, 0.0], [9000.0, 0.0]])).tolist() == [True, False]
    assert east.inside(np.array([[3000.0, 0.0]])).tolist() == [True]


def test_no_regions_is_an_empty_table(tmp_path):
    assert load_scenario(write(tmp_path, TWO_REGIONS.read_text().split("[regions.west]")[0])).regions == {}


def test_a_site_file_takes_regions(tmp_path):
    site = "\n".join(line for line in case().splitlines() if not line.startswith(SITE_KEYS))
    spec = load_site(write(tmp_path, site))
    assert not hasattr(spec, "targets") and set(spec.regions) == {"west", "east"}


@pytest.mark.parametrize("old, new, said", [
    ('sensors = ["e", "s"]\n', 'sensors = ["e", "zz"]\n', r"regions\.east\.sensors: unknown sensor 'zz'"),
    ('sensors = ["e", "s"]\n', 'sensors = []\n', r"regions\.east\.sensors: must be a non-empty list"),
    ("[[0.0, -60000.0], [60000.0, -60000.0], [60000.0, 60000.0], [0.0, 60000.0]]",
     "[[0.0, 0.0], [1.0, 1.0], [2.0, 2.0]]", r"regions\.east\.polygon_m: degenerate polygon"),
    ("[-60.0, -60.0, 0.0, 60.0]", "[0.0, -60.0, -60.0, 60.0]", r"regions\.west\.box_km: must be \[e_min"),
    ("[regions.east]", "[regions.\"ea st\"]", r"region names may use only"),
    ("margin_km = 8.0", "margin_km = -5.0", r"regions\.west\.margin_km: must be >= 0"),
    ("margin_km = 8.0", "margin_km = 5.0\npolygon_km = [[0, 0], [1, 0], [0, 1]]", r"not both"),
])
def test_bad_regions_are_one_located_line(tmp_path, old, new, said):
    text = case()
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
