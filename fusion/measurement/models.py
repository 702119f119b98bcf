r"""Measurement models: what a filter's update needs to know of a measurement.

A :class:`MeasurementModel` maps a state ``x`` (position first, ``x[:3]`` ENU metres) to
the measurement it predicts, ``ẑ = h(x)``, with additive Gaussian noise of covariance
``R``; the filters (:mod:`fusion.ekf`, :mod:`fusion.ukf`, :mod:`fusion.imm`), the gates
(:mod:`fusion.association`), initiation and the bounds (:mod:`fusion.crb3d`) use only
this protocol. Angle rows (``angles``) have their residuals wrapped to (−π, π].

:class:`SphericalModel` — rows of azimuth, elevation and slant range, each seen from its
own site, ``d = p − s``, ``ρ = √(d_e² + d_n²)``, ``r = |d|``::

    az = atan2(d_e, d_n) mod 2π      ∂az/∂p = [ d_n, −d_e, 0 ] / ρ²
    el = atan2(d_u, ρ)               ∂el/∂p = [ −d_e d_u / ρ, −d_n d_u / ρ, ρ ] / r²
    range = r                        ∂range/∂p = d / r

with ``R = diag(std²)``. A 2D radar, an angle sensor, a 3D radar and the patent's
composite measurements (SS stacking, LCDD selection) are all row lists of it.
Singularities: azimuth and elevation are undefined straight above/below a site
(``ρ < MIN_HORIZONTAL_RANGE``), range's gradient at the site (``r < MIN_RANGE``); both
raise ``ValueError``.

:func:`stack` puts several models' rows into one (``R`` block-diagonal): spherical rows
merge into one :class:`SphericalModel` (its single-state path stays the hand-optimised
one), other models join them in a :class:`StackedModel`.

:class:`PositionModel` — a report of the position itself (ENU metres in the origin's
frame), linear: ``h(x) = x[:3]``, ``H = [I₃ 0]``, with the report's own full ``R``.
"""

from __future__ import annotations

import math
from functools import lru_cache
from typing import Protocol, Sequence

import numpy as np
from scipy.linalg import block_diag

from .. import kalman
from ..angles import TWO_PI

MIN_HORIZONTAL_RANGE = 1e-3  # m: below this, azimuth/elevation of a target are undefined
MIN_RANGE = 1e-3  # m: below this, range's gradient is undefined

_CODES = {"az": 0, "el": 1, "range": 2}


class MeasurementModel(Protocol):
    """What a filter, a gate and an initiator use of a measurement (module docstring).

    Attributes:
        n_z, n_x: lengths of the measurement and of the state it is written for.
        components: the name of each row.
        R: noise covariance (n_z × n_z).
        angles: (n_z,) bool, the rows whose residuals wrap to (−π, π].
    """

    n_z: int
    n_x: int
    components: tuple[str, ...]
    R: np.ndarray
    angles: np.ndarray

    def h(self, x: np.ndarray) -> np.ndarray:
        """The predicted measurement of a state (n_x,) → (n_z,), or of a batch (..., n_x) → (..., n_z)."""
        ...

    def jacobian(self, x: np.ndarray) -> np.ndarray:
        """``∂h/∂x`` (n_z × n_x) at one state."""
        ...

    def residual(self, z: np.ndarray, z_hat: np.ndarray) -> np.ndarray:
        """``z − ẑ`` with the angle rows wrapped (broadcasts over leading axes)."""
        ...

    def innovation_and_jacobian(self, z: np.ndarray, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``z − h(x)`` (wrapped) and ``∂h/∂x`` at one state: what an EKF update needs."""
        ...


def _check_z(model, z) -> np.ndarray:
    z = np.asarray(z, dtype=float)
    if z.shape != (model.n_z,):
        raise ValueError(f"measurement must have shape ({model.n_z},) for {model.components}, got {z.shape}")
    return z


class SphericalModel:
    """Rows of spherical components (``az``/``el``/``range``), each seen from a site.

    Args:
        components: component name per row.
        sites: one ENU site (3,) for all rows, or one per row (n_z, 3).
        std: noise standard deviation per row (rad for angles, m for range).
        n_x: length of the state the Jacobian is written for (6 for CV, 9 for CA).
    """

    def __init__(self, components: Sequence[str], sites, std, n_x: int = 9):
        components = tuple(components)
        bad = [c for c in components if c not in _CODES]
        if not components or bad:
            raise ValueError(f"spherical components must be among {sorted(_CODES)}, got {components!r}")
        n_z = len(components)
        sites = np.asarray(sites, dtype=float)
        if sites.shape == (3,):
            sites = np.tile(sites, (n_z, 1))
        if sites.shape != (n_z, 3) or not np.all(np.isfinite(sites)):
            raise ValueError(f"sites must be a finite ENU 3-vector or one per row ({n_z}, 3), got shape {sites.shape}")
        std = np.asarray(std, dtype=float).reshape(-1)
        if std.shape != (n_z,) or not np.all(np.isfinite(std)) or np.any(std <= 0.0):
            raise ValueError(f"std must be {n_z} finite positive values for {components}, got {std!r}")
        n_x = int(n_x)
        if n_x < 3:
            raise ValueError(f"state length n_x must be >= 3 (position first), got {n_x}")
        self.components = components
        self.codes = np.array([_CODES[c] for c in components])
        self.sites = sites
        self.std = std
        self.R = np.diag(std**2)
        self.angles = self.codes != _CODES["range"]
        self.n_z = n_z
        self.n_x = n_x
        self._rho_rows = np.flatnonzero(self.angles)  # rows needing ρ > 0 (az, el)
        self._r_rows = np.flatnonzero(~self.angles)  # rows needing r > 0 (range)
        # The same rows as Python scalars, for the single-state path (see _linearise).
        self._row_list = tuple(zip(self.codes.tolist(), map(tuple, sites.tolist())))
        self._zero_tail = [0.0] * (n_x - 3)
        for a in (self.codes, self.sites, self.std, self.R, self.angles):
            a.setflags(write=False)  # models are shared (cached): keep them immutable

    def __repr__(self) -> str:
        return f"{type(self).__name__}(components={self.components}, std={self.std.tolist()})"

    @property
    def site(self) -> np.ndarray:
        """The site of a single-site model (ValueError if rows have different sites)."""
        if not np.all(self.sites == self.sites[0]):
            raise ValueError("this model's rows have different sites; use .sites")
        return self.sites[0]

    # Geometry ---------------------------------------------------------------------
    def _geometry(self, x: np.ndarray):
        x = np.asarray(x, dtype=float)
        if x.shape[-1] != self.n_x:
            raise ValueError(f"state must have {self.n_x} components, got shape {x.shape}")
        d = x[..., None, :3] - self.sites  # (..., n_z, 3)
        rho = np.hypot(d[..., 0], d[..., 1])
        r = np.hypot(rho, d[..., 2])
        if self._rho_rows.size and rho[..., self._rho_rows].min() < MIN_HORIZONTAL_RANGE:
            raise ValueError(
                f"target straight above/below a sensor site (horizontal range < {MIN_HORIZONTAL_RANGE} m): "
                "azimuth/elevation undefined"
            )
        if self._r_rows.size and r[..., self._r_rows].min() < MIN_RANGE:
            raise ValueError(f"target at a sensor site (zero range < {MIN_RANGE} m): range gradient undefined")
        return d, rho, r

    def h(self, x: np.ndarray) -> np.ndarray:
        """Predicted measurement for a state (n_x,) → (n_z,), or a batch (..., n_x) → (..., n_z)."""
        d, rho, r = self._geometry(x)
        az = np.mod(np.arctan2(d[..., 0], d[..., 1]), TWO_PI)
        az = np.where(az >= TWO_PI, 0.0, az)
        el = np.arctan2(d[..., 2], rho)
        return np.choose(self.codes, (az, el, r))

    def _linearise(self, x: np.ndarray) -> tuple[list[float], np.ndarray]:
        """``h(x)`` (as floats) and ``∂h/∂x`` at one state, the geometry computed once per row.

        The single-track EKF runs this for every update. One state is a handful of
        scalars, so it works on Python floats (``math``): numpy's per-call overhead on
        3-vectors would cost several times the arithmetic. Same formulas, checks and
        errors as :meth:`h` (which is vectorised over many states).
        """
        x = np.asarray(x, dtype=float)
        if x.shape != (self.n_x,):
            raise ValueError(f"state must have {self.n_x} components (one state vector), got shape {x.shape}")
        pe, pn, pu = x[:3].tolist()
        zp: list[float] = []
        rows: list[list[float]] = []
        for code, (se, sn, su) in self._row_list:
            de, dn, du = pe - se, pn - sn, pu - su
            rho = math.hypot(de, dn)
            r = math.hypot(rho, du)
            if code == 2:  # range
                if r < MIN_RANGE:
                    raise ValueError(f"target at a sensor site (zero range < {MIN_RANGE} m): range gradient undefined")
                zp.append(r)
                rows.append([de / r, dn / r, du / r, *self._zero_tail])
                continue
            if rho < MIN_HORIZONTAL_RANGE:
                raise ValueError(
                    f"target straight above/below a sensor site (horizontal range < {MIN_HORIZONTAL_RANGE} m): "
                    "azimuth/elevation undefined"
                )
            if code == 0:  # azimuth, in [0, 2π) as h() gives it
                az = math.atan2(de, dn) % TWO_PI
                zp.append(0.0 if az >= TWO_PI else az)
                rho2 = rho * rho
                rows.append([dn / rho2, -de / rho2, 0.0, *self._zero_tail])
            else:  # elevation
                zp.append(math.atan2(du, rho))
                r2 = r * r
                rows.append([-de * du / (rho * r2), -dn * du / (rho * r2), rho / r2, *self._zero_tail])
        return zp, np.array(rows)

    def jacobian(self, x: np.ndarray) -> np.ndarray:
        """Analytic ``∂h/∂x`` (n_z × n_x) at one state; only the position columns are non-zero."""
        x = np.asarray(x, dtype=float)
        if x.ndim != 1:
            raise ValueError(f"jacobian takes one state vector, got shape {x.shape}")
        return self._linearise(x)[1]

    def residual(self, z: np.ndarray, z_hat: np.ndarray) -> np.ndarray:
        """``z − ẑ`` with angular rows wrapped to (−π, π] (broadcasts over leading axes)."""
        return kalman.innovation(z, z_hat, self.angles)

    def innovation(self, z: np.ndarray, x: np.ndarray) -> np.ndarray:
        """``z − h(x)`` with angular rows wrapped to (−π, π]."""
        return kalman.innovation(_check_z(self, z), self.h(x), self.angles)

    def innovation_and_jacobian(self, z: np.ndarray, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`innovation` and :meth:`jacobian` at one state, in one pass over the geometry:
        what an EKF update needs."""
        z = _check_z(self, z)
        zp, H = self._linearise(x)
        nu = [zi - hi for zi, hi in zip(z.tolist(), zp)]
        for i, (code, _) in enumerate(self._row_list):
            if code != 2:
                nu[i] = _wrap_pi(nu[i])
        return np.array(nu), H

    # Building composite models ----------------------------------------------------
    @staticmethod
    def stack(models: Sequence["SphericalModel"]) -> "SphericalModel":
        """All rows of several models in one (the SS stacked measurement); R block-diagonal
        (:func:`stack`, whose spherical case this is)."""
        return stack(models)

    def select(self, rows: Sequence[int]) -> "SphericalModel":
        """A model of some of this model's rows (in the given order)."""
        rows = list(rows)
        return SphericalModel([self.components[i] for i in rows], self.sites[rows], self.std[rows], self.n_x)


def _wrap_pi(a: float) -> float:
    """:func:`fusion.angles.wrap_pi` of one Python float (same arithmetic, no numpy call)."""
    w = (a + math.pi) % TWO_PI - math.pi
    return math.pi if w == -math.pi else w


# A sensor sends the same site and std scan after scan: build each model once.
@lru_cache(maxsize=1024)
def spherical(components: tuple, site: tuple, std: tuple, n_x: int) -> SphericalModel:
    """The (cached, immutable) :class:`SphericalModel` of one sensor: ``components`` seen
    from one ``site`` (or a site per row, a tuple of them), with ``std``; arguments are
    tuples of Python floats."""
    return SphericalModel(components, site, std, n_x)


@lru_cache(maxsize=1024)
def _stack(models: tuple) -> SphericalModel:
    return SphericalModel(
        [c for m in models for c in m.components],
        np.vstack([m.sites for m in models]),
        np.concatenate([m.std for m in models]),
        models[0].n_x,
    )


class StackedModel:
    """Several models' rows in one measurement: ``h`` and ``∂h/∂x`` stacked, ``R``
    block-diagonal (independent noise between the blocks). Built by :func:`stack`."""

    def __init__(self, blocks: Sequence[MeasurementModel]):
        self.blocks = tuple(blocks)
        self.n_x = self.blocks[0].n_x
        self.components = tuple(c for b in self.blocks for c in b.components)
        self.n_z = len(self.components)
        self.R = block_diag(*[b.R for b in self.blocks])
        self.angles = np.concatenate([np.asarray(b.angles, dtype=bool) for b in self.blocks])
        ends = np.cumsum([b.n_z for b in self.blocks])
        self._slices = [slice(int(e - b.n_z), int(e)) for e, b in zip(ends, self.blocks)]
        for a in (self.R, self.angles):
            a.setflags(write=False)

    def __repr__(self) -> str:
        return f"StackedModel({list(self.blocks)!r})"

    def h(self, x: np.ndarray) -> np.ndarray:
        return np.concatenate([b.h(x) for b in self.blocks], axis=-1)

    def jacobian(self, x: np.ndarray) -> np.ndarray:
        return np.vstack([b.jacobian(x) for b in self.blocks])

    def residual(self, z: np.ndarray, z_hat: np.ndarray) -> np.ndarray:
        return kalman.innovation(z, z_hat, self.angles)

    def innovation_and_jacobian(self, z: np.ndarray, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        z = _check_z(self, z)
        parts = [b.innovation_and_jacobian(z[s], x) for b, s in zip(self.blocks, self._slices)]
        return np.concatenate([p[0] for p in parts]), np.vstack([p[1] for p in parts])


class PositionModel:
    """A position report: ``z = p = x[:3]`` (ENU metres in the origin's frame, whatever the
    reporting sensor's site), ``H = [I₃ 0]``, noise ``R`` (3 × 3, symmetric positive
    definite: the report's own covariance).

    Args:
        R: the report's noise covariance.
        n_x: length of the state (position first).
    """

    components = ("east", "north", "up")
    n_z = 3

    def __init__(self, R, n_x: int = 9):
        R = np.array(R, dtype=float)
        if R.shape != (3, 3) or not np.all(np.isfinite(R)) or not np.array_equal(R, R.T):
            raise ValueError(f"a position report's R must be a finite symmetric 3×3 matrix, got {R!r}")
        try:
            np.linalg.cholesky(R)
        except np.linalg.LinAlgError:
            raise ValueError(f"a position report's R must be positive definite, got {R!r}") from None
        n_x = int(n_x)
        if n_x < 3:
            raise ValueError(f"state length n_x must be >= 3 (position first), got {n_x}")
        self.n_x = n_x
        self.R = R
        self.angles = np.zeros(3, dtype=bool)
        self._H = np.hstack([np.eye(3), np.zeros((3, n_x - 3))])
        for a in (self.R, self.angles, self._H):
            a.setflags(write=False)

    def __repr__(self) -> str:
        return f"PositionModel(std={np.sqrt(np.diag(self.R)).tolist()})"

    def _state(self, x) -> np.ndarray:
        x = np.asarray(x, dtype=float)
        if x.shape[-1] != self.n_x:
            raise ValueError(f"state must have {self.n_x} components, got shape {x.shape}")
        return x

    def h(self, x: np.ndarray) -> np.ndarray:
        return self._state(x)[..., :3].copy()

    def jacobian(self, x: np.ndarray) -> np.ndarray:
        if self._state(x).ndim != 1:
            raise ValueError(f"jacobian takes one state vector, got shape {np.shape(x)}")
        return self._H

    def residual(self, z: np.ndarray, z_hat: np.ndarray) -> np.ndarray:
        return np.asarray(z, dtype=float) - z_hat

    def innovation_and_jacobian(self, z: np.ndarray, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return _check_z(self, z) - self.h(x), self.jacobian(x)


def stack(models: Sequence[MeasurementModel]) -> MeasurementModel:
    """The rows of ``models`` in order as one model, noise independent between them (the SS
    stacked measurement). Neighbouring spherical models merge into one
    :class:`SphericalModel` (all spherical: exactly :meth:`SphericalModel.stack`); one model
    is itself."""
    if not models:
        raise ValueError("cannot stack zero measurement models")
    n_x = {m.n_x for m in models}
    if len(n_x) != 1:
        raise ValueError(f"cannot stack models written for different state lengths {sorted(n_x)}")
    if len(models) == 1:
        return models[0]
    if all(type(m) is SphericalModel for m in models):
        return _stack(tuple(models))
    blocks: list = []
    run: list[SphericalModel] = []
    for m in models:
        if type(m) is SphericalModel:
            run.append(m)
            continue
        if run:
            blocks.append(SphericalModel.stack(run))
            run = []
        blocks.append(m)
    if run:
        blocks.append(SphericalModel.stack(run))
    return blocks[0] if len(blocks) == 1 else StackedModel(blocks)
