"""WGS-84 geodetic ↔ local ENU."""

from __future__ import annotations

import numpy as np
import pytest

from fusion.geodetic import LocalFrame, enu_to_geodetic, geodetic_to_enu

A, F = 6378137.0, 1 / 298.257223563
E2 = F * (2 - F)
LAT0, LON0, ALT0 = np.radians(13.75), np.radians(100.5), 10.0   # Bangkok


def test_origin_is_zero():
    np.testing.assert_allclose(geodetic_to_enu(LAT0, LON0, ALT0, LAT0, LON0, ALT0), 0.0, atol=1e-9)
    np.testing.assert_allclose(LocalFrame(13.75, 100.5, ALT0, deg=True).to_enu(13.75, 100.5, ALT0), 0.0, atol=1e-9)


def test_a_point_one_km_north():
    # meridian radius of curvature M = a(1−e²)/(1−e² sin²φ)^{3/2}: 1 km of arc is 1000/M rad
    M = A * (1 - E2) / (1 - E2 * np.sin(LAT0) ** 2) ** 1.5
    e, n, u = geodetic_to_enu(LAT0 + 1000.0 / (M + ALT0), LON0, ALT0, LAT0, LON0, ALT0)
    assert abs(e) < 1e-6
    assert n == pytest.approx(1000.0, abs=0.01)
    assert u == pytest.approx(-1000.0 ** 2 / (2 * (M + ALT0)), abs=0.005)   # ≈ −0.079 m: the earth curves away


def test_east_and_up_directions():
    N = A / np.sqrt(1 - E2 * np.sin(LAT0) ** 2)   # prime-vertical radius
    e, n, u = geodetic_to_enu(LAT0, LON0 + 1000.0 / ((N + ALT0) * np.cos(LAT0)), ALT0, LAT0, LON0, ALT0)
    assert e == pytest.approx(1000.0, abs=0.01) and u < 0
    # a parallel is a small circle: it bends north of the tangent plane by d² tanφ / 2N
    assert n == pytest.approx(1000.0 ** 2 * np.tan(LAT0) / (2 * N), rel=0.01)
    np.testing.assert_allclose(geodetic_to_enu(LAT0, LON0, ALT0 + 500.0, LAT0, LON0, ALT0), [0, 0, 500.0], atol=1e-6)


def test_round_trip_and_degrees():
    rng = np.random.default_rng(1)
    enu = rng.uniform(-50e3, 50e3, size=(20, 3)) * [1, 1, 0.1]
    frame = LocalFrame(LAT0, LON0, ALT0)
    lat, lon, alt = frame.to_geodetic(enu)
    np.testing.assert_allclose(frame.to_enu(lat, lon, alt), enu, atol=1e-6)
    lat_d, lon_d, _ = enu_to_geodetic(*enu.T, np.degrees(LAT0), np.degrees(LON0), ALT0, deg=True)
    np.testing.assert_allclose(np.radians(lat_d), lat, rtol=1e-12)


def test_bad_latitude_is_an_error():
    with pytest.raises(ValueError, match="lat0"):
        geodetic_to_enu(0.0, 0.0, 0.0, 95.0, 0.0, 0.0, deg=True)
    with pytest.raises(ValueError, match="origin latitude"):
        LocalFrame(2.0, 0.0)


@pytest.mark.parametrize("lat, lon", [(21.5, 106.9), (-33.9, 151.2), (21.0285, 105.8542)])
def test_rotation_from_a_point_s_axes_matches_pymap3d(lat, lon):
    """A displacement in the ENU axes at a point far from the origin, carried to the
    origin's frame by ``T = R(o) R(p)ᵀ``, is where pymap3d puts the displaced point
    (exact for any displacement: ENU and ECEF are affine in each other)."""
    frame = LocalFrame(21.0285, 105.8542, 10.0, deg=True)
    alt = 9000.0
    T = frame.rotation_from(lat, lon)
    np.testing.assert_allclose(T @ T.T, np.eye(3), atol=1e-15)
    p = frame.to_enu(lat, lon, alt)
    for d in ([1000.0, 0.0, 0.0], [0.0, 2500.0, -300.0], [-40.0, 75.0, 120.0]):
        q = enu_to_geodetic(*d, lat, lon, alt, deg=True)
        np.testing.assert_allclose(frame.to_enu(*q) - p, T @ np.array(d), rtol=0, atol=1e-6)
