r"""Bearings-only emitter models (documents 000–003).

Geometry is the horizontal plane of the local ENU frame, in metres. Inside ``fusion.df``
a bearing ``β`` is a *math* angle (counter-clockwise from east, radians), as in the
theses::

    β = h(X) = atan2(y_e − y_k, x_e − x_k),     R = σ²

with ``(x_e, y_e)`` the emitter's position (the first two states) and ``(x_k, y_k)`` the
observer's at the time of the bearing (it moves for an airborne DF). Measurements arrive
as :class:`fusion.types.Measurement` of kind ``"bearing"`` whose ``z[0]`` is a *compass*
azimuth; :func:`bearing_of` converts at the edge. A DF azimuth is a horizontal-plane
angle: the site's height is ignored.

Two emitter motion models (``[tracker]`` key ``motion``), one interface that every DF
filter takes (``transition(dt) -> (F, Q)``, ``initial``, ``replays_past``):

* :class:`StaticEmitter` (``"static"``, the theses'): ``X = [x_e, y_e]``, ``Φ = I₂``,
  ``Q = diag(q11, q22)`` added once per *bearing*, whatever the time between bearings;
* :class:`ConstantVelocityEmitter` (``"cv"``): ``X = [x_e, y_e, vx, vy]``,
  ``F(dt) = F₁(dt) ⊗ I₂``, ``Q(dt) = q·Q₁(dt) ⊗ I₂`` with the white-acceleration blocks
  ``F₁ = [[1, dt], [0, 1]]``, ``Q₁ = [[dt³/3, dt²/2], [dt²/2, dt]]`` (:mod:`fusion.motion`),
  ``q`` the acceleration PSD in m²/s³; ``H = [∂h/∂p, 0, 0]``.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from ..angles import compass_to_math, math_to_compass
from ..motion import ConstantVelocity
from ..types import Measurement

_I2 = np.eye(2)
_I2.setflags(write=False)

#: The theses' bearing noise, radians (≈1°).
THESIS_SIGMA = 0.0175
#: The theses' ``q22 = 0.025² km²`` in m² ("cannot be zero"; added per bearing).
THESIS_Q22 = 625.0


def bearing(p, site):
    """Math bearing ``atan2(Δy, Δx)`` from ``site`` to ``p`` (broadcasts over leading axes)."""
    d = np.asarray(p, dtype=float)[..., :2] - np.asarray(site, dtype=float)[..., :2]
    return np.arctan2(d[..., 1], d[..., 0])


def bearing_jacobian(p, site):
    """``∂β/∂p = [−Δy, Δx] / r²`` (shape ``(..., 2)``).

    This is the source documents' ``[−u/((1+u²)Δx), 1/((1+u²)Δx)]`` with ``u = Δy/Δx`` multiplied
    out, so it has no singularity at ``Δx = 0``; only ``r = 0`` (emitter on the site) is
    singular, and that raises.
    """
    d = np.asarray(p, dtype=float)[..., :2] - np.asarray(site, dtype=float)[..., :2]
    r2 = np.sum(d * d, axis=-1)
    if np.any(r2 <= 0.0):
        raise ValueError("bearing_jacobian: the position coincides with the observer site")
    return np.stack([-d[..., 1], d[..., 0]], axis=-1) / r2[..., None]


def emitter_Q(q22: float, q11: float = 0.0) -> np.ndarray:
    """Process noise ``diag(q11, q22)`` in m², added before every bearing update."""
    if q11 < 0.0 or q22 < 0.0:
        raise ValueError(f"emitter_Q: q11={q11} and q22={q22} must be >= 0")
    return np.diag([float(q11), float(q22)])


class StaticEmitter:
    """The theses' static emitter: ``X = [x_e, y_e]``, ``Φ = I₂`` and ``Q`` added before
    every bearing update, independent of ``dt`` (a random walk per bearing, not per second).

    Its position is the same at every time, so bearings may be processed in any order
    (``replays_past``): an initialiser can replay bearings older than its fix.
    """

    name = "static"
    n_x = 2
    replays_past = True

    def __init__(self, Q: np.ndarray):
        self.Q = np.asarray(Q, dtype=float)
        if self.Q.shape != (2, 2):
            raise ValueError(f"StaticEmitter: Q must be 2×2, got shape {self.Q.shape}")

    def transition(self, dt: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
        """``(I₂, Q)`` for any ``dt``."""
        return _I2, self.Q

    def initial(self, p: np.ndarray, P: np.ndarray, vel_std: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
        """The state of a position fix ``(p, P)``: the fix itself."""
        return np.asarray(p, dtype=float).copy(), np.asarray(P, dtype=float).copy()


class ConstantVelocityEmitter:
    r"""A moving emitter at nearly constant velocity: ``X = [x_e, y_e, vx, vy]``::

        F(dt) = [[I₂, dt·I₂], [0, I₂]]
        Q(dt) = q [[dt³/3·I₂, dt²/2·I₂], [dt²/2·I₂, dt·I₂]]

    the exact discretisation of continuous white acceleration of PSD ``q`` (m²/s³) on
    each axis — :class:`fusion.motion.ConstantVelocity`'s per-axis blocks on two axes.
    ``dt = 0`` (bearings of one epoch) gives ``(I, 0)``. Bearings older than the state
    cannot be processed (``replays_past`` is False): the emitter has moved since.
    """

    name = "cv"
    n_x = 4
    replays_past = False

    def __init__(self, q: float):
        self.axis = ConstantVelocity(q)  # validates q >= 0
        self.q = self.axis.q

    def F(self, dt: float) -> np.ndarray:
        return np.kron(self.axis.F_axis(dt), _I2)

    def Q(self, dt: float) -> np.ndarray:
        return np.kron(self.axis.Q_axis(dt), _I2)

    def transition(self, dt: float) -> tuple[np.ndarray, np.ndarray]:
        """``(F(dt), Q(dt))``; ValueError for ``dt < 0``."""
        return self.F(dt), self.Q(dt)

    def initial(self, p: np.ndarray, P: np.ndarray, vel_std: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
        """The state of a position fix ``(p, P)`` with velocity ``0 ± vel_std`` per axis,
        independent of the position: ``[p, 0, 0]``, ``blockdiag(P, vel_std²·I₂)``."""
        x = np.concatenate([np.asarray(p, dtype=float)[:2], np.zeros(2)])
        P4 = np.zeros((4, 4))
        P4[:2, :2] = P
        P4[2:, 2:] = vel_std * vel_std * _I2
        return x, P4


EmitterModel = StaticEmitter | ConstantVelocityEmitter
#: ``[tracker]`` ``motion`` of the DF methods
EMITTER_MOTIONS = ("static", "cv")


def emitter_model(model) -> EmitterModel:
    """``model`` itself, or, for a 2×2 array, the static emitter with that ``Q``."""
    if isinstance(model, (StaticEmitter, ConstantVelocityEmitter)):
        return model
    return StaticEmitter(model)


def bearing_of(m: Measurement) -> tuple[np.ndarray, float]:
    """``(site_xy, β)`` of a bearing measurement: the edge conversion compass → math.

    Raises ValueError for another kind, non-finite values or a malformed site.
    """
    if m.kind != "bearing":
        raise ValueError(f"expected a 'bearing' measurement, got kind {m.kind!r} from {m.sensor!r}")
    z = np.atleast_1d(np.asarray(m.z, dtype=float))
    site = np.atleast_1d(np.asarray(m.site, dtype=float))
    if z.shape != (1,) or not np.isfinite(z[0]):
        raise ValueError(f"bearing from {m.sensor!r} at t={m.t}: z must be one finite azimuth, got {m.z!r}")
    if site.shape not in ((2,), (3,)) or not np.all(np.isfinite(site)):
        raise ValueError(f"bearing from {m.sensor!r} at t={m.t}: site must be a finite 2- or 3-vector, got {m.site!r}")
    return site[:2].copy(), float(compass_to_math(z[0]))


def stated_sigma(m: Measurement) -> float:
    """The sensor's stated bearing standard deviation (radians); must be finite and > 0."""
    s = np.atleast_1d(np.asarray(m.std, dtype=float))
    if s.shape != (1,) or not np.isfinite(s[0]) or s[0] <= 0.0:
        raise ValueError(f"bearing from {m.sensor!r} at t={m.t}: std must be one positive number, got {m.std!r}")
    return float(s[0])


def bearing_measurements(
    t: Sequence[float] | np.ndarray,
    sensors: Sequence[str],
    sites: np.ndarray,
    beta: np.ndarray,
    sigma: float | Sequence[float],
) -> list[Measurement]:
    """Build a bearing stream in ``(t, sensor, seq)`` order from math bearings.

    ``sites`` has shape ``(T, S, 2|3)`` (site of sensor ``s`` at epoch ``k``) or
    ``(S, 2|3)`` for fixed stations; ``beta`` has shape ``(T, S)``; ``sigma`` is the
    stated std, one per sensor or one for all. ``seq`` counts epochs. Used to feed
    synthetic bearings (tests, in-process studies) through the streaming methods.
    """
    t = np.asarray(t, dtype=float)
    beta = np.asarray(beta, dtype=float)
    T, S = beta.shape
    sites = np.asarray(sites, dtype=float)
    if sites.ndim == 2:
        sites = np.broadcast_to(sites, (T,) + sites.shape)
    if t.shape != (T,) or len(sensors) != S or sites.shape[:2] != (T, S):
        raise ValueError("bearing_measurements: t (T,), sensors (S), sites (T,S,·) and beta (T,S) disagree")
    sig = np.broadcast_to(np.asarray(sigma, dtype=float), (S,))
    az = math_to_compass(beta)
    order = np.argsort(np.asarray(sensors, dtype=object), kind="stable")
    site3 = np.zeros((T, S, 3))
    site3[..., : sites.shape[2]] = sites
    return [
        Measurement(t=float(t[k]), sensor=sensors[s], kind="bearing", z=np.array([az[k, s]]),
                    std=np.array([sig[s]]), site=site3[k, s].copy(), seq=k)
        for k in range(T)
        for s in order
    ]
