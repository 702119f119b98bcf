r"""Track initialisation from the first scan — one initialiser for every 3D method.

A scan is the list of measurements a method treats as simultaneous (see
:mod:`fusion.patent`). From it we take, per spherical component, the best source:

* direction: azimuth from the measurement with the smallest σ_az, taken at that
  sensor's site ``s``; elevation from the best elevation-measuring sensor at the same
  site (the angle sensor itself, normally), else from the prior ``(el, el_std)``;
* range: from the range-measuring sensor with the smallest σ_range, else from the
  prior ``(range, range_std)``.

With a 2D radar and an angle sensor in the first scan this is the angle sensor's az/el
and the radar's range — the same initial state for every fused method, so comparisons
are fair. Position is the spherical → Cartesian conversion ``p = s + t·u(az, el)`` with
``u = [cos el sin az, cos el cos az, sin el]`` (compass azimuth, ENU) and ``t`` the
distance along the ray; its covariance is the converted one, ``J diag(σ_az², σ_el², σ_t²) Jᵀ``
with ``J = ∂p/∂(az, el, range)`` analytic. When the range comes from a sensor at another
site ``s_r``, ``t`` is where the ray meets the sphere ``|p − s_r| = r``:
``t² + 2bt + c = 0``, ``t± = −b ± √(b² − c)``, ``b = u·(s − s_r)``, ``c = |s − s_r|² − r²``.
Inside the sphere (c < 0) only ``t₊`` is ahead of the sensor; outside it (c > 0, b < 0)
both are, the near ``t₋`` and the far ``t₊``, and the first scan alone cannot tell them
apart: the far root is the default, a caller that can (a pair's azimuth consistency,
:class:`fusion.mtt.Initiator`) names the root. ``J`` includes ``t``'s dependence on the
angles and on r (singular at tangency, b² = c, which counts as a miss); if the ray misses
that sphere the range measurement is not used (prior instead).

A position report (a kind that is not sited: it states the point itself,
:mod:`fusion.measurement.kinds`) needs none of this: when the scan holds one, the
position and its covariance are those of the report with the smallest ``tr R``.

Velocity and acceleration start at zero with prior standard deviations per axis
(horizontal ``vel_std``/``acc_std``, vertical ``vel_std_up``/``acc_std_up``),
uncorrelated with position.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from .measurement.kinds import KINDS, kinds_of
from .types import Measurement

INIT_KINDS = kinds_of("3d")
_SAME_SITE_TOL = 1e-6  # m


@dataclass(frozen=True)
class InitPriors:
    """Priors for what the first scan does not give.

    Defaults (generic, not fitted to any scenario):
        range = 10 000 m, range_std = 5 000 m — slant range when no sensor measures it;
        el = 0.1 rad (≈ 5.7°), el_std = 0.1 rad — elevation when no sensor measures it;
        vel_std = vel_std_up = 200 m/s, acc_std = acc_std_up = 10 m/s² (≈ 1 g) — per
        axis, horizontal (east, north) and vertical.
    These are *not* non-informative for acceleration: six 1 s scans of 10–20 m
    position noise measure it only to a few m/s², so at scan 5 a 10 m/s² prior still
    weighs (expected NEES deficit 0.44 of 9 for SS on patent-3d), and a Monte Carlo
    run about a fixed truth finds the filters conservative there. A prior bounding the
    flight envelope (1 km/s, 100 m/s²) no longer weighs by then (0.006); the patent-3d
    scenarios give it to the methods that observe the whole state
    (docs/consistency.md §3, §8). The vertical ones are
    separate because a tracker that cannot observe the vertical (a 2D radar alone, or
    HNV's radar-local EKF) keeps the vertical prior uncertainty, and an EKF with a
    large uncertainty along an unobservable direction gains spurious information as
    its linearisation point moves; a physical vertical prior (e.g. 20 m/s, 1 m/s² for
    air targets) keeps such a tracker in its linear regime.
    """

    range: float = 10_000.0
    range_std: float = 5_000.0
    el: float = 0.1
    el_std: float = 0.1
    vel_std: float = 200.0
    vel_std_up: float = 200.0
    acc_std: float = 10.0
    acc_std_up: float = 10.0

    def __post_init__(self):
        for name in ("range", "range_std", "el_std", "vel_std", "vel_std_up", "acc_std", "acc_std_up"):
            v = getattr(self, name)
            if not np.isfinite(v) or v <= 0.0:
                raise ValueError(f"init prior {name} must be finite and > 0, got {v!r}")
        if not np.isfinite(self.el) or abs(self.el) >= np.pi / 2:
            raise ValueError(f"init prior el must lie in (-π/2, π/2), got {self.el!r}")


def _component(m: Measurement, name: str) -> tuple[float, float] | None:
    i = KINDS[m.kind].index(name)
    if i is None:
        return None
    return float(m.z[i]), float(m.std[i])


def _best(scan: Sequence[Measurement], name: str, site=None) -> tuple[Measurement, float, float] | None:
    """The measurement giving component ``name`` with the smallest std (first on ties)."""
    best = None
    for m in scan:
        c = _component(m, name)
        if c is None or (site is not None and np.max(np.abs(np.asarray(m.site, float) - site)) > _SAME_SITE_TOL):
            continue
        if best is None or c[1] < best[2]:
            best = (m, c[0], c[1])
    return best


FAR, NEAR = 1, -1  # the root of the ray–sphere crossing: t = −b + root·√(b² − c)


def spherical_to_position(site, az: float, el: float, rng: float, range_site=None, root: int = FAR):
    """``p = s + t·u(az, el)`` and ``J = ∂p/∂(az, el, range)`` (3 × 3); see the module docstring.

    ``range_site`` (default: ``site``) is where ``rng`` is measured from; ``root``
    (:data:`FAR` or :data:`NEAR`) which crossing of its sphere. Returns ``None`` if the
    ray from ``site`` misses or touches that sphere, or that root is not ahead (t ≤ 0).
    """
    s = np.asarray(site, dtype=float)
    ce, se, ca, sa = np.cos(el), np.sin(el), np.cos(az), np.sin(az)
    u = np.array([ce * sa, ce * ca, se])
    u_az = np.array([ce * ca, -ce * sa, 0.0])
    u_el = np.array([-se * sa, -se * ca, ce])
    w = s - (s if range_site is None else np.asarray(range_site, dtype=float))
    if not np.any(w):
        return s + rng * u, np.column_stack([rng * u_az, rng * u_el, u])
    b = float(u @ w)
    disc = b * b - (float(w @ w) - rng * rng)
    if disc <= 0.0:
        return None
    t = -b + root * np.sqrt(disc)
    if t <= 0.0:
        return None
    # From t² + 2bt + c = 0: (t + b) dt = r dr − t db, db = w·du.
    tb = t + b
    J = np.column_stack(
        [
            t * u_az - u * t * float(w @ u_az) / tb,
            t * u_el - u * t * float(w @ u_el) / tb,
            u * rng / tb,
        ]
    )
    return s + t * u, J


def initial_state(scan: Sequence[Measurement], n_x: int, priors: InitPriors = InitPriors(), root: int = FAR):
    """Initial ``(x, P)`` (n_x = 6 or 9) from the first scan: position from its best
    position report, else from the best azimuth (and elevation at its site) and the best
    range (at the ray–sphere ``root`` when measured from another site), else the
    ``priors``, with the converted covariance; velocity and acceleration zero with their
    prior stds."""
    if n_x not in (6, 9):
        raise ValueError(f"3D track state length must be 6 (CV) or 9 (CA), got {n_x}")
    scan = list(scan)
    for m in scan:
        if m.kind not in INIT_KINDS:
            raise ValueError(f"cannot initialise a 3D track from a {m.kind!r} measurement (sensor {m.sensor!r})")
    x = np.zeros(n_x)
    P = np.zeros((n_x, n_x))
    points = [m for m in scan if not KINDS[m.kind].sited]
    if points:
        best = min(points, key=lambda m: float(np.trace(m.R)))
        x[:3], P[:3, :3] = best.z, best.R
    else:
        x[:3], P[:3, :3] = _spherical_position(scan, priors, root)
    P[3:6, 3:6] = np.diag([priors.vel_std**2, priors.vel_std**2, priors.vel_std_up**2])
    if n_x == 9:
        P[6:9, 6:9] = np.diag([priors.acc_std**2, priors.acc_std**2, priors.acc_std_up**2])
    return x, 0.5 * (P + P.T)


def _spherical_position(scan: list[Measurement], priors: InitPriors, root: int) -> tuple[np.ndarray, np.ndarray]:
    """The position and its covariance from the scan's spherical components (module docstring)."""
    az_src = _best(scan, "az")
    if az_src is None:
        raise ValueError("cannot initialise a 3D track from an empty scan")
    m_dir, az, s_az = az_src
    site = np.asarray(m_dir.site, dtype=float)
    el_src = _best(scan, "el", site)
    el, s_el = (el_src[1], el_src[2]) if el_src else (priors.el, priors.el_std)

    conv = None
    rng_src = _best(scan, "range")
    if rng_src is not None:
        conv = spherical_to_position(site, az, el, rng_src[1], rng_src[0].site, root)
        s_r = rng_src[2]
    if conv is None:  # no range sensor, or its sphere misses the ray: prior range from the direction site
        conv = spherical_to_position(site, az, el, priors.range)
        s_r = priors.range_std
    p, J = conv
    return p, J @ np.diag([s_az**2, s_el**2, s_r**2]) @ J.T
