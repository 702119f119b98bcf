r"""Measurement models of the 3D sensors, and the EKF step that uses them.

Every 3D sensor measures some of three spherical quantities of the target position
``p = x[:3]`` relative to a site ``s`` (ENU, metres), with ``d = p − s``,
``ρ = √(d_e² + d_n²)`` (horizontal range) and ``r = |d|`` (slant range)::

    az    = atan2(d_e, d_n)  mod 2π     compass azimuth, clockwise from north
    el    = atan2(d_u, ρ)               elevation above the horizontal
    range = r                           slant range

and their gradients with respect to ``p`` (the state's other components do not enter)::

    ∂az/∂p    = [ d_n, −d_e, 0 ] / ρ²
    ∂el/∂p    = [ −d_e d_u / ρ, −d_n d_u / ρ, ρ ] / r²
    ∂range/∂p = d / r

A :class:`SphericalModel` is a list of rows, each one of these components seen from
its own site, with independent noise ``R = diag(std²)``. The sensors are fixed
selections — :class:`Radar2D` (kind ``range_az``: ``[az, range]``), :class:`AngleSensor`
(kind ``azel``: ``[az, el]``), :class:`Radar3D` (kind ``az_el_range``) — and the
patent's composite measurements (SS stacking, LCDD selection) are just other row lists
(:meth:`SphericalModel.stack`, :meth:`SphericalModel.select`), so no method carries its
own copy of the geometry.

Singularities: azimuth and elevation are undefined (and their Jacobians unbounded)
when the target is straight above/below a site (``ρ < MIN_HORIZONTAL_RANGE``); range's
gradient is undefined at zero range (``r < MIN_RANGE``). Both raise ``ValueError``.
"""

from __future__ import annotations

import math
from functools import lru_cache
from typing import Sequence

import numpy as np

from . import kalman
from .angles import TWO_PI
from .types import KIND_COMPONENTS, Measurement

MIN_HORIZONTAL_RANGE = 1e-3  # m: below this, azimuth/elevation of a target are undefined
MIN_RANGE = 1e-3  # m: below this, range's gradient is undefined

_CODES = {"az": 0, "el": 1, "range": 2}


class SphericalModel:
    """Rows of spherical components (``az``/``el``/``range``), each seen from a site.

    Args:
        components: component name per row.
        sites: one ENU site (3,) for all rows, or one per row (n_z, 3).
        std: noise standard deviation per row (rad for angles, m for range).
        n_x: length of the state the Jacobian is written for (6 for CV, 9 for CA).
    """

    kind: str | None = None  # the Measurement kind this model is, if it is one

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

    def innovation(self, z: np.ndarray, x: np.ndarray) -> np.ndarray:
        """``z − h(x)`` with angular rows wrapped to (−π, π]."""
        z = np.asarray(z, dtype=float)
        if z.shape != (self.n_z,):
            raise ValueError(f"measurement must have shape ({self.n_z},) for {self.components}, got {z.shape}")
        return kalman.innovation(z, self.h(x), self.angles)

    def innovation_and_jacobian(self, z: np.ndarray, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`innovation` and :meth:`jacobian` at one state, in one pass over the geometry:
        what an EKF update needs."""
        z = np.asarray(z, dtype=float)
        if z.shape != (self.n_z,):
            raise ValueError(f"measurement must have shape ({self.n_z},) for {self.components}, got {z.shape}")
        zp, H = self._linearise(x)
        nu = [zi - hi for zi, hi in zip(z.tolist(), zp)]
        for i, (code, _) in enumerate(self._row_list):
            if code != 2:
                nu[i] = _wrap_pi(nu[i])
        return np.array(nu), H

    # Building composite models ----------------------------------------------------
    @staticmethod
    def stack(models: Sequence["SphericalModel"]) -> "SphericalModel":
        """All rows of several models in one (the SS stacked measurement); R block-diagonal."""
        if not models:
            raise ValueError("cannot stack zero measurement models")
        n_x = {m.n_x for m in models}
        if len(n_x) != 1:
            raise ValueError(f"cannot stack models written for different state lengths {sorted(n_x)}")
        if len(models) == 1:
            return models[0]
        return _stack(tuple(models))

    def select(self, rows: Sequence[int]) -> "SphericalModel":
        """A model of some of this model's rows (in the given order)."""
        rows = list(rows)
        return SphericalModel([self.components[i] for i in rows], self.sites[rows], self.std[rows], self.n_x)

    @classmethod
    def from_measurement(cls, m: Measurement, n_x: int = 9) -> "SphericalModel":
        """The model of an incoming :class:`Measurement` (site from ``m.site``, R from ``m.std``).

        Called on :class:`SphericalModel` it dispatches on ``m.kind``; called on a
        sensor class it also checks that the kind matches.
        """
        try:
            model_cls = MODEL_BY_KIND[m.kind]
        except KeyError:
            raise ValueError(
                f"measurement kind {m.kind!r} from sensor {m.sensor!r} is not a 3D sensor kind "
                f"(expected one of {sorted(MODEL_BY_KIND)})"
            ) from None
        if cls is not SphericalModel and model_cls is not cls:
            raise ValueError(f"{cls.__name__} models kind {cls.kind!r}, got a {m.kind!r} measurement")
        z = np.asarray(m.z, dtype=float)
        if z.shape != (len(KIND_COMPONENTS[m.kind]),) or not np.all(np.isfinite(z)):
            raise ValueError(f"measurement z from sensor {m.sensor!r} must be {KIND_COMPONENTS[m.kind]}, got {m.z!r}")
        site = np.asarray(m.site, dtype=float).reshape(-1)
        std = np.asarray(m.std, dtype=float).reshape(-1)
        if site.shape != (3,) or std.shape != z.shape:
            raise ValueError(
                f"measurement from sensor {m.sensor!r} needs a 3-vector site and {z.size} stds, "
                f"got site {m.site!r}, std {m.std!r}"
            )
        return _sensor_model(model_cls, tuple(site.tolist()), tuple(std.tolist()), int(n_x))


def _wrap_pi(a: float) -> float:
    """:func:`fusion.angles.wrap_pi` of one Python float (same arithmetic, no numpy call)."""
    w = (a + math.pi) % TWO_PI - math.pi
    return math.pi if w == -math.pi else w


class _SensorModel(SphericalModel):
    """A physical sensor: one site, the components of its measurement kind."""

    def __init__(self, site, std, n_x: int = 9):
        super().__init__(KIND_COMPONENTS[self.kind], site, std, n_x)


class Radar2D(_SensorModel):
    """2D radar, kind ``range_az``: ``z = [az, slant range]``, ``std = [σ_az, σ_range]``."""

    kind = "range_az"


class AngleSensor(_SensorModel):
    """Angle sensor (e.g. electro-optical), kind ``azel``: ``z = [az, el]``, ``std = [σ_az, σ_el]``."""

    kind = "azel"


class Radar3D(_SensorModel):
    """3D radar, kind ``az_el_range``: ``z = [az, el, range]``, ``std = [σ_az, σ_el, σ_range]``."""

    kind = "az_el_range"


MODEL_BY_KIND: dict[str, type[_SensorModel]] = {c.kind: c for c in (Radar2D, AngleSensor, Radar3D)}


# A sensor sends the same site and std scan after scan: build each model once.
@lru_cache(maxsize=1024)
def _sensor_model(model_cls, site: tuple, std: tuple, n_x: int) -> _SensorModel:
    return model_cls(site, std, n_x)


@lru_cache(maxsize=1024)
def _stack(models: tuple) -> SphericalModel:
    return SphericalModel(
        [c for m in models for c in m.components],
        np.vstack([m.sites for m in models]),
        np.concatenate([m.std for m in models]),
        models[0].n_x,
    )


def from_measurement(m: Measurement, n_x: int = 9) -> SphericalModel:
    """Shorthand for :meth:`SphericalModel.from_measurement`."""
    return SphericalModel.from_measurement(m, n_x)


# The EKF step ----------------------------------------------------------------------
def motion_predict(motion, x: np.ndarray, P: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Time update over ``dt`` with a motion model: ``F(dt) x``, ``F P Fᵀ + Q(dt)``; for a
    state-dependent model (one with ``transition(x, dt) -> (f(x), ∂f/∂x, Q)``) its ``f(x)``
    and ``J P Jᵀ + Q`` with the Jacobian at ``x``."""
    step = getattr(motion, "transition", None)
    if step is None:
        return kalman.predict(x, P, motion.F(dt), motion.Q(dt))
    fx, J, Q = step(x, dt)
    return fx, kalman.symmetrise(J @ P @ J.T + Q)


def ekf_predict(motion, x: np.ndarray, P: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """:func:`motion_predict` over ``dt`` (``dt = 0``: unchanged)."""
    if dt == 0.0:
        return x, P
    return motion_predict(motion, x, P, dt)


def _ekf_update(model, x, P, z) -> tuple[kalman.UpdateResult, np.ndarray]:
    nu, H = model.innovation_and_jacobian(z, x)
    return kalman.update(x, P, nu, H, model.R), H


def iterated_ekf_update(model: SphericalModel, x: np.ndarray, P: np.ndarray, z: np.ndarray,
                        iterations: int, tol: float = 1e-9) -> tuple[kalman.UpdateResult, np.ndarray]:
    r"""Iterated EKF update: Gauss–Newton steps on the MAP cost
    ``(x − x̄)ᵀ P̄⁻¹ (x − x̄) + (z − h(x))ᵀ R⁻¹ (z − h(x))``, relinearising ``h`` at each
    iterate ``xᵢ``:

        Hᵢ = ∂h/∂x(xᵢ),   νᵢ = [z − h(xᵢ)]_wrapped − Hᵢ (x̄ − xᵢ),   xᵢ₊₁ = x̄ + Kᵢ νᵢ,

    with ``Kᵢ`` the Kalman gain of ``Hᵢ`` about the prior ``(x̄, P̄)``; the covariance is
    the Joseph form with the last ``H``. One iteration is the EKF. It matters where the
    prediction lies far from the measurement's linear regime, e.g. an accurate range
    across a cross-range spread of hundreds of metres (docs/consistency.md §4).

    The returned ν, S and NIS are the first iteration's: those of the prediction, which
    is what a consistency (NIS) test and a gate are about. Stops early once a step moves
    the state by less than ``tol`` relative to its size. Returns the result and the last ``H``.
    """
    first, H = _ekf_update(model, x, P, z)
    res = first
    for _ in range(int(iterations) - 1):
        nu, H = model.innovation_and_jacobian(z, res.x)
        step = kalman.update(x, P, nu - H @ (x - res.x), H, model.R)
        moved = float(np.max(np.abs(step.x - res.x)))
        res = step
        if moved <= tol * (1.0 + float(np.max(np.abs(res.x)))):
            break
    return kalman.UpdateResult(res.x, res.P, first.nu, first.S, first.nis, res.K), H


def ekf_update(model: SphericalModel, x: np.ndarray, P: np.ndarray, z: np.ndarray) -> kalman.UpdateResult:
    """Measurement update linearised at ``x``: ``H = ∂h/∂x(x)``, wrapped ``ν = z − h(x)``,
    Joseph form and NIS via :func:`kalman.update`."""
    return _ekf_update(model, x, P, z)[0]


class TrackEKF:
    r"""Extended Kalman filter of one 3D track.

    Holds ``(x, P, t)``. :meth:`predict` moves it to a later time with the motion
    model (``x ← F x``, ``P ← F P Fᵀ + Q``); :meth:`update` linearises a
    :class:`SphericalModel` at the predicted state and applies the shared Kalman step
    (angle-wrapped innovation, Joseph form, NIS; see :mod:`fusion.kalman`).
    """

    def __init__(self, motion, x: np.ndarray, P: np.ndarray, t: float, iterations: int = 1):
        self.motion = motion
        self.iterations = int(iterations)  # > 1: iterated EKF updates (iterated_ekf_update)
        self.set_state(x, P, t)

    def set_state(self, x: np.ndarray, P: np.ndarray, t: float) -> None:
        x = self.motion.check_state(x)
        P = np.asarray(P, dtype=float)
        if P.shape != (x.size, x.size):
            raise ValueError(f"covariance must be {x.size}×{x.size}, got shape {P.shape}")
        self.x, self.P, self.t = x, P, float(t)

    def predicted(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """The prediction to time ``t`` (>= the filter's time), without changing the filter."""
        if t < self.t:
            raise ValueError(f"cannot predict backwards from t={self.t} to t={t}")
        return ekf_predict(self.motion, self.x, self.P, t - self.t)

    def predict(self, t: float) -> None:
        self.x, self.P = self.predicted(t)
        self.t = float(t)

    def update(self, model: SphericalModel, z: np.ndarray) -> kalman.UpdateResult:
        """Update at the filter's current time; returns the Kalman step's result (ν, S, NIS, K).

        The Jacobian used is kept in ``self.H`` (a local track reports ``K·H``).
        """
        if self.iterations > 1:
            res, self.H = iterated_ekf_update(model, self.x, self.P, z, self.iterations)
        else:
            res, self.H = _ekf_update(model, self.x, self.P, z)
        self.x, self.P, self._K = res.x, res.P, res.K
        return res

    @property
    def KH(self) -> np.ndarray:
        """``K·H`` of the last update (what a local track reports to the fusion rules)."""
        return self._K @ self.H
