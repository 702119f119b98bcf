r"""Per-station bearing smoothing for KF+TR and MKF+TR (documents 002, 000).

Each DF station smooths its *own* bearing sequence with a scalar random-constant
Kalman filter, ``Φ = 1, H = 1, R = σ², Q = q``::

    β⁻ = β̂,  P⁻ = P + q;   ν = wrap(β − β⁻);   β̂ = β⁻ + Kν,  P = (1 − K)P⁻

(the step is :func:`fusion.kalman.predict`/:func:`~fusion.kalman.update`; the first
bearing initialises ``β̂ = β, P = σ²``). For a static emitter seen from a fixed station
the bearing is a true constant, so ``q = 0`` (the running mean, ``P = σ²/n``) is the
exact model; ``q > 0`` lets the smoother follow a slowly drifting bearing. A moving
observer's bearing is not constant: the smoothers refuse a station whose site moves.

MKF (the thesis's "Modified KF") runs two such filters cross-fed exactly as MEKF does
(:class:`fusion.df.filters.CrossFed`). With both halves identical and the states and
covariances handed over together, MKF is *identical* to the single KF; only the
printed hand-off (A2's variance frozen at its initial value) makes it differ.

The smoothers take a bearing :class:`~fusion.types.Measurement` and return one: the
smoothed compass azimuth with ``std = √P``, same sensor, site, time and seq. So a
station's local tracker can publish its output with the ordinary bearing schema, and the
centre (:func:`fusion.df.triangulation.fix_from_bearings`, Torrieri) takes raw or
smoothed bearings alike. That is the split of the distributed topology (HNV).
"""

from __future__ import annotations

import numpy as np

from ..angles import math_to_compass, wrap_pi
from ..kalman import UpdateResult, predict, update
from ..types import Measurement
from .filters import CrossFed
from .models import bearing_of, stated_sigma

_ONE = np.eye(1)
#: a fixed station may not move more than this between bearings (m).
SITE_TOL = 1e-3


def smoother_step(x: np.ndarray, P: np.ndarray, beta: float, sigma: float, q: float) -> UpdateResult:
    """One random-constant KF step on a (math) bearing; the result's ``x`` is wrapped."""
    xp, Pp = predict(x, P, _ONE, np.array([[q]]))
    res = update(xp, Pp, np.array([wrap_pi(beta - xp[0])]), _ONE, np.array([[sigma * sigma]]))
    return res._replace(x=np.array([wrap_pi(res.x[0])]))


class BearingSmoother:
    """Scalar KF bearing smoother of one fixed DF station.

    Args:
        q: process noise of the bearing per update (rad²), ``>= 0``.
        sigma: bearing std (rad); ``None`` uses each measurement's stated std.
    """

    def __init__(self, q: float = 0.0, sigma: float | None = None):
        if not np.isfinite(q) or q < 0.0:
            raise ValueError(f"smoother q must be finite and >= 0, got {q}")
        if sigma is not None and not sigma > 0.0:
            raise ValueError(f"smoother sigma must be > 0, got {sigma}")
        self.q, self.sigma = float(q), sigma
        self.site: np.ndarray | None = None
        self.sensor: str | None = None
        self.n = 0
        self.x: np.ndarray | None = None  # smoothed math bearing, shape (1,)
        self.P: np.ndarray | None = None

    def _accept(self, m: Measurement) -> tuple[float, float]:
        site, beta = bearing_of(m)
        sigma = stated_sigma(m) if self.sigma is None else float(self.sigma)
        if self.site is None:
            self.site, self.sensor = site, m.sensor
        elif m.sensor != self.sensor:
            raise ValueError(f"bearing smoother of {self.sensor!r} got a bearing from {m.sensor!r}")
        elif np.linalg.norm(site - self.site) > SITE_TOL:
            raise ValueError(f"bearing smoother: station {m.sensor!r} moved; KF+TR needs fixed stations")
        return beta, sigma

    def _first(self, beta: float, sigma: float) -> None:
        self.x, self.P = np.array([beta]), np.array([[sigma * sigma]])

    def _step(self, beta: float, sigma: float) -> None:
        res = smoother_step(self.x, self.P, beta, sigma, self.q)
        self.x, self.P = res.x, res.P

    def update(self, m: Measurement) -> Measurement:
        """Take one raw bearing, return the smoothed bearing (a Measurement)."""
        beta, sigma = self._accept(m)
        if self.n == 0:
            self._first(beta, sigma)
        else:
            self._step(beta, sigma)
        self.n += 1
        return Measurement(t=m.t, sensor=m.sensor, kind="bearing", z=np.array([math_to_compass(self.x[0])]),
                           std=np.array([np.sqrt(self.P[0, 0])]), site=np.asarray(m.site, dtype=float).copy(),
                           seq=m.seq)


class CrossFedBearingSmoother(BearingSmoother):
    """MKF: two scalar KF bearing smoothers cross-fed as in MEKF (each starts its next
    update from the other's output; the first one's is reported). With the ``"swap"``
    hand-off it equals :class:`BearingSmoother`."""

    def __init__(self, q: float = 0.0, sigma: float | None = None, handoff: str = "swap"):
        super().__init__(q, sigma)
        if handoff not in CrossFed.HANDOFFS:
            raise ValueError(f"unknown MKF handoff {handoff!r}; expected one of {CrossFed.HANDOFFS}")
        self.handoff = handoff
        self._pair: CrossFed | None = None

    def _first(self, beta: float, sigma: float) -> None:
        super()._first(beta, sigma)

        def f(x, P, b, s):
            return smoother_step(x, P, b, s, self.q)

        self._pair = CrossFed(f, f, self.x, self.P, self.handoff)

    def _step(self, beta: float, sigma: float) -> None:
        res = self._pair.step(beta, sigma)
        self.x, self.P = res.x, res.P
