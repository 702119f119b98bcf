"""fusion.tracking.initiators: a new 3D track from an angle plot's ray and a 2D radar
plot's range sphere, at the crossing the radar's azimuth confirms."""

from __future__ import annotations

import math

import numpy as np
import pytest

from fusion.init3d import FAR, NEAR, InitPriors
from fusion.methods import make_method
from fusion.tracking.initiators import Initiator
from fusion.types import Measurement


# Initiation at either crossing of a range sphere ------------------------------------------
_RADAR, _ANGLE_OUT, _ANGLE_IN = np.zeros(3), np.array([0.0, 50e3, 0.0]), np.array([0.0, 10e3, 0.0])


def _pair(p, angle_site, rng=None):
    """Noise-free plots of the point p: an angle sensor at ``angle_site`` (az, el) and a
    2D radar at the origin (az, slant range ``rng``, default |p|); σ 1 mrad, 1°, 20 m."""
    e, n, u = p - angle_site
    a = Measurement(0.0, "angle", "azel", np.array([math.atan2(e, n) % (2 * math.pi), math.atan2(u, math.hypot(e, n))]),
                    np.array([1e-3, 1e-3]), angle_site, 0)
    r = Measurement(0.0, "radar", "range_az", np.array([math.atan2(p[0], p[1]) % (2 * math.pi),
                                                         np.linalg.norm(p) if rng is None else rng]),
                    np.array([math.radians(1.0), 20.0]), _RADAR, 0)
    return a, r


def _crossings(a, r):
    """Closed form: the distances t along the ray where |s + t·u − s_r| = r, t > 0."""
    az, el = a.z
    u = np.array([math.cos(el) * math.sin(az), math.cos(el) * math.cos(az), math.sin(el)])
    w = a.site - r.site
    b, c = u @ w, w @ w - r.z[1] ** 2
    disc = b * b - c
    return [] if disc <= 0 else [t for t in (-b - math.sqrt(disc), -b + math.sqrt(disc)) if t > 0]


@pytest.mark.parametrize("site, p, root", [
    (_ANGLE_OUT, np.array([3e3, 30e3, 5e3]), NEAR),   # angle sensor outside the sphere, aircraft at its near crossing
    (_ANGLE_OUT, np.array([1e3, -10e3, 3e3]), FAR),   # outside, the ray goes past the radar: aircraft at the far one
    (_ANGLE_IN, np.array([3e3, 30e3, 5e3]), FAR),     # inside the sphere: the near root is behind the sensor
])
def test_a_pair_starts_at_the_crossing_the_radar_azimuth_confirms(site, p, root):
    """The ray of an angle plot crosses the radar plot's range sphere at
    t± = −b ± √(b² − c) (fusion.init3d); ahead of the sensor are both when it lies
    outside the sphere, only t₊ inside. The pair keeps the crossing(s) whose radar
    azimuth is in the gate, and the track starts there. The old rule took t₊ always: the
    first case started no track."""
    a, r = _pair(p, site)
    ts = _crossings(a, r)
    assert len(ts) == (2 if site is _ANGLE_OUT else 1)
    t_true = float(np.linalg.norm(p - site))
    assert min(abs(t - t_true) for t in ts) < 1e-6 * t_true  # the closed form finds the aircraft
    cands = Initiator(9, InitPriors(), 0.999).pair_consistency(a, r)
    assert [c[0] for c in cands] == [root]
    np.testing.assert_allclose(cands[0][2][:3], p, atol=1e-6 * t_true)
    assert cands[0][1] < 1e-12  # noise-free: the radar azimuth fits exactly
    method = make_method("SS", {"association": "gnn", "confirm_m": 1, "confirm_n": 1})
    out = []
    for m in sorted([a, r], key=lambda m: m.order_key):
        out += method.advance(m.t - 0.5) + method.process(m)
    out += method.finish()
    assert len(out) == 1
    np.testing.assert_allclose(out[0].x[:3], p, atol=1e-6 * t_true)


@pytest.mark.parametrize("rng", [10e3, 9e3])
def test_a_ray_that_touches_or_misses_the_sphere_makes_no_pair(rng):
    """A horizontal ray due north from (10, −50, 0) km passes the radar at 10 km: a
    sphere of 10 km it touches (b² = c exactly, where t no longer depends on r: the
    Jacobian is singular), one of 9 km it misses — no candidate either way, and the
    frame's two plots start no pair (each waits: a partner kind is in the frame)."""
    a = Measurement(0.0, "angle", "azel", np.array([0.0, 0.0]), np.array([1e-3, 1e-3]), np.array([10e3, -50e3, 0.0]), 0)
    r = Measurement(0.0, "radar", "range_az", np.array([math.pi / 2, rng]), np.array([math.radians(1.0), 20.0]), _RADAR, 0)
    assert _crossings(a, r) == []
    ini = Initiator(9, InitPriors(), 0.999)
    assert ini.pair_consistency(a, r) == []
    assert [g[:2] for g in ini.groups([a, r])] == []
    inside = Measurement(0.0, "radar", "range_az", np.array([math.pi / 2, 10_001.0]), r.std, _RADAR, 0)
    assert len(_crossings(a, inside)) == 2  # 1 m larger: crossings 141 m either side of the tangent point, both in the gate
    assert {c[0] for c in ini.pair_consistency(a, inside)} == {NEAR, FAR}
    assert len(ini.groups([a, inside])) == 1  # one track from the pair, not two
