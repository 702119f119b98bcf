r"""The measurement kinds, one record each: the table the wire, the scenarios, the
gateways, the recorder, the methods and the initiator read.

A :class:`Kind` says

* ``components`` — the rows of ``Measurement.z``, in order (:mod:`.components`);
* ``family`` — ``"3d"`` (the 3D methods use it) or ``"df"`` (bearings on the map plane,
  the direction-finding methods);
* ``start`` — what one report fixes of the target's position, hence what it can start a
  track from: a ``point`` alone, a ``ray`` (direction only) or a ``sphere`` (range, with
  an azimuth: an arc). A ray and a sphere of one family start a track as a pair, at the
  ray's crossing of the sphere (:func:`partners`);
* ``model`` — ``model(site, std, corr, n_x)``, its :class:`~.models.MeasurementModel`
  (None: not for the 3D filters; the DF methods model bearings themselves);
* ``sited`` — ``h`` depends on the reporting sensor's site. An unsited kind reports the
  target's position itself, ``z`` in the origin's ENU frame (metres), whatever the
  sensor's site: a gateway may take it in geodetic coordinates, the recorder draws it as
  a point, the initiator starts a track at it;
* ``own_noise`` — each report states its own noise: its std, and correlation
  coefficients between its components (``Measurement.corr``), so each report carries its
  own full covariance (a cooperative report's accuracy fields); the others state their
  sensor's fixed std, which the site file gives.

:func:`model_of` turns a :class:`~fusion.types.Measurement` into its model: the one way
any code gets the model of a report.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from ..types import Measurement
from .components import AZ, EAST, EL, NORTH, RANGE, UP, Component
from .models import MeasurementModel, PositionModel, spherical

POINT, RAY, SPHERE = "point", "ray", "sphere"
STARTS = (POINT, RAY, SPHERE)
FAMILIES = ("3d", "df")

#: ``model(site, std, corr, n_x)``: site (3,), std (n_z,), corr (n_z, n_z) or None
ModelFactory = Callable[[np.ndarray, np.ndarray, "np.ndarray | None", int], MeasurementModel]


@dataclass(frozen=True)
class Kind:
    """One measurement kind (module docstring)."""

    name: str
    family: str
    components: tuple[Component, ...]
    start: str
    model: ModelFactory | None = None
    sited: bool = True
    own_noise: bool = False

    def __post_init__(self):
        if self.family not in FAMILIES or self.start not in STARTS or not self.components:
            raise ValueError(f"kind {self.name!r}: family {self.family!r}, start {self.start!r}, "
                             f"components {self.components!r}")
        if not self.sited and (self.start != POINT or [c.unit for c in self.components] != ["m"] * 3):
            raise ValueError(f"kind {self.name!r}: an unsited kind reports a position (a point, 3 lengths)")

    @property
    def names(self) -> tuple[str, ...]:
        """The component names, in the order of ``Measurement.z``."""
        return tuple(c.name for c in self.components)

    @property
    def n_z(self) -> int:
        return len(self.components)

    @property
    def angles(self) -> np.ndarray:
        """(n_z,) bool: the angle components."""
        return np.array([c.angle for c in self.components], dtype=bool)

    def index(self, name: str) -> int | None:
        """The row of component ``name``, or None if the kind does not measure it."""
        names = self.names
        return names.index(name) if name in names else None

    @property
    def fixes_range(self) -> bool:
        """One report bounds the target's distance (a point or a sphere, not a ray)."""
        return self.start != RAY


def _spherical(names: tuple[str, ...]) -> ModelFactory:
    def model(site, std, corr, n_x):
        return spherical(names, tuple(site.tolist()), tuple(std.tolist()), int(n_x))
    return model


def _position(site, std, corr, n_x):
    return PositionModel(np.diag(std**2) if corr is None else np.outer(std, std) * corr, n_x)


def _kind(name: str, family: str, components: tuple[Component, ...], start: str, **facts) -> Kind:
    if family == "3d" and "model" not in facts:
        facts["model"] = _spherical(tuple(c.name for c in components))
    return Kind(name, family, components, start, **facts)


#: every measurement kind, by name (the wire's measurement message kinds, in this order)
KINDS: dict[str, Kind] = {k.name: k for k in (
    _kind("bearing", "df", (AZ,), RAY),
    _kind("azel", "3d", (AZ, EL), RAY),
    _kind("range_az", "3d", (AZ, RANGE), SPHERE),
    _kind("az_el_range", "3d", (AZ, EL, RANGE), POINT),
    # a cooperative position report (ADS-B, ASTERIX CAT021): ENU metres, its own covariance
    _kind("position", "3d", (EAST, NORTH, UP), POINT, model=_position, sited=False, own_noise=True),
)}


def kind(name: str) -> Kind:
    """The record of kind ``name`` (ValueError naming the known ones)."""
    try:
        return KINDS[name]
    except KeyError:
        raise ValueError(f"unknown measurement kind {name!r} (known: {', '.join(KINDS)})") from None


def kinds_of(family: str) -> frozenset[str]:
    """The names of the kinds of a family (``"3d"``, ``"df"``)."""
    return frozenset(k.name for k in KINDS.values() if k.family == family)


def partners(name: str) -> frozenset[str]:
    """The kinds a report of kind ``name`` starts a track with as a pair: a ray's are
    the spheres of its family, a sphere's the rays; a point needs none."""
    k = kind(name)
    other = {RAY: SPHERE, SPHERE: RAY}.get(k.start)
    return frozenset(o.name for o in KINDS.values() if o.family == k.family and o.start == other)


def fixes(m, component: Component) -> bool:
    """Whether the report ``m`` fixes its target's ``component``: its kind measures it, or
    it is a position (a report that is not sited states the whole point)."""
    k = KINDS[m.kind]
    return component in k.components or not k.sited


def model_for(name: str, site, std, n_x: int = 9, corr=None) -> MeasurementModel:
    """The model of a sensor of kind ``name`` at ``site`` stating ``std`` (and, for a
    kind whose reports state their own noise, ``corr``)."""
    return _build(kind(name), site, std, corr, n_x)


def model_of(m: Measurement, n_x: int = 9) -> MeasurementModel:
    """The model of an incoming :class:`~fusion.types.Measurement` (site ``m.site``, noise
    ``m.std`` and ``m.corr``), for a state of length ``n_x``."""
    k = KINDS.get(m.kind)
    if k is None or k.model is None:
        raise ValueError(f"measurement kind {m.kind!r} from sensor {m.sensor!r} is not a 3D sensor kind "
                         f"(expected one of {sorted(kinds_of('3d'))})")
    z = np.asarray(m.z, dtype=float)
    if z.shape != (len(k.components),) or not np.isfinite(z).all():
        raise ValueError(f"measurement z from sensor {m.sensor!r} must be {k.names}, got {m.z!r}")
    try:
        return _build(k, m.site, m.std, m.corr, n_x)
    except ValueError as e:
        raise ValueError(f"measurement from sensor {m.sensor!r}: {e}") from None


def _build(k: Kind, site, std, corr, n_x: int) -> MeasurementModel:
    if k.model is None:
        raise ValueError(f"measurement kind {k.name!r} has no measurement model for the 3D filters "
                         f"(3D kinds: {', '.join(sorted(kinds_of('3d')))})")
    site = np.asarray(site, dtype=float).reshape(-1)
    std = np.asarray(std, dtype=float).reshape(-1)
    n_z = len(k.components)
    if site.shape != (3,) or std.shape != (n_z,):
        raise ValueError(f"a {k.name} model needs a 3-vector site and {n_z} stds, got site {site!r}, std {std!r}")
    if corr is not None:
        if not k.own_noise:
            raise ValueError(f"a {k.name} measurement states no correlations (its noise is diag(std²))")
        corr = np.asarray(corr, dtype=float)
        if corr.shape != (n_z, n_z):
            raise ValueError(f"a {k.name} correlation matrix is {n_z}×{n_z}, got shape {corr.shape}")
    return k.model(site, std, corr, int(n_x))
