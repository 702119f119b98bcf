"""Region geometry (fusion.regions) against closed forms."""

from __future__ import annotations

import math

import numpy as np
import pytest

from fusion.regions import Crossings, Region, box_polygon, boundary_distance, inside_polygon, polygon_area

SQUARE = box_polygon(0.0, 0.0, 2.0, 2.0)
# an L: the square [0, 2]² without its upper-right quarter [1, 2]², clockwise
L_SHAPE = np.array([[0, 0], [0, 2], [1, 2], [1, 1], [2, 1], [2, 0]], dtype=float)


def test_area_is_the_shoelace_formula_with_its_sense():
    assert polygon_area(SQUARE) == pytest.approx(4.0)
    assert polygon_area(L_SHAPE) == pytest.approx(-3.0)  # clockwise: negative


def test_inside_a_concave_polygon():
    pts = np.array([[0.5, 0.5], [1.5, 0.5], [0.5, 1.5], [1.5, 1.5], [-0.1, 1.0], [2.5, 0.5]])
    assert inside_polygon(pts, L_SHAPE).tolist() == [True, True, True, False, False, False]


def test_boundary_distance_closed_forms():
    pts = np.array([[1.0, 0.5], [3.0, 1.0], [3.0, 3.0], [1.5, 1.5], [-1.0, -1.0]])
    want = [0.5, 1.0, math.sqrt(2.0), 0.5, math.sqrt(2.0)]
    assert boundary_distance(pts, SQUARE) == pytest.approx(want, abs=1e-12)
    # the notch of the L: (1.5, 1.5) is 0.5 from the two inner edges
    assert boundary_distance(np.array([[1.5, 1.5]]), L_SHAPE) == pytest.approx([0.5])


def test_held_area_is_the_square_grown_by_its_margin():
    """The points within ``m`` of a 2 x 2 square: area 4 + 8m + πm² (a grid's count)."""
    m = 0.5
    region = Region("r", SQUARE, m, ("s",))
    h = 0.005
    g = np.arange(-1.0 + h / 2, 3.0, h)
    E, N = np.meshgrid(g, g)
    pts = np.column_stack([E.ravel(), N.ravel()])
    area = region.holds(pts).sum() * h * h
    assert area == pytest.approx(4 + 8 * m + math.pi * m * m, rel=2e-3)
    assert region.inside(pts).sum() * h * h == pytest.approx(4.0, rel=2e-3)


def test_vectorised_equals_one_point_at_a_time():
    rng = np.random.default_rng(3)
    pts = rng.uniform(-1, 3, (200, 3))  # a third component (altitude) is ignored
    region = Region("r", L_SHAPE, 0.3, ("s",))
    assert region.holds(pts).tolist() == [bool(region.holds(p)[0]) for p in pts]


@pytest.mark.parametrize("polygon, margin, sensors, said", [
    ([[0, 0], [1, 1], [2, 2]], 0.0, ("s",), "degenerate"),
    ([[0, 0], [1, 0]], 0.0, ("s",), "at least 3"),
    (SQUARE, -1.0, ("s",), "margin"),
    (SQUARE, 0.0, (), "no sensor"),
])
def test_bad_regions_are_refused(polygon, margin, sensors, said):
    with pytest.raises(ValueError, match=said):
        Region("r", np.asarray(polygon, float), margin, sensors)


def test_crossings_count_passages_from_region_to_region():
    west, east = Region("w", box_polygon(0, 0, 10, 10), 1.0, ("s",)), Region("e", box_polygon(10, 0, 20, 10), 1.0, ("s",))
    c = Crossings([west, east])
    path = [5, 9, 11, 15, 25, 19, 9]  # west, west, east, east, outside, east, west
    counts = [c.add({"a": np.array([e, 5.0, 1000.0])}) for e in path]
    assert counts == [0, 0, 1, 0, 0, 0, 1]
    assert c.count == 2
