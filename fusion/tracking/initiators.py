r"""Initiation of 3D tracks from the plots of a frame that no track took.

A 2D radar plot fixes a sphere and an angle plot a ray, so a track starts from a *pair*
across sensors: the ray meets the range sphere (:func:`fusion.init3d.spherical_to_position`;
no pair if they do not meet, or only touch), and the radar's own azimuth, which the point
did not use, must agree with it within the χ²(1) gate — at either crossing when the
angle sensor is outside the sphere, each crossing a candidate of its own. Each
consistent pair gathers the nearest plot in its gate from every other sensor of the
frame, so one target seen by four sensors starts one track, and the pairs are taken by
*support*: most sensors first, then least total ``d²``. A plot starts a track alone only
if nothing in its frame could pair with it (a 2D radar plot in a frame without angle
plots, or the reverse; a 3D radar plot always): a lone plot's broad prior attracts
clutter. The reasons and the cases: docs/algorithms.md, "Initiation from sensors that
see part of the position".

Across frames (:meth:`Initiator.groups_across`, the sweep tracker's): a rotating radar
crosses a target at a time fixed by its azimuth, an angle sensor looks at fixed times,
and the two may never fall in one frame. A 2D radar plot then pairs with an angle plot
up to ``window`` seconds apart, *moved* to the angle plot's time (:func:`moved`): the
target went ``v·Δt`` meanwhile, ``v ~ N(0, σ_v² I)`` by the velocity prior, which adds
``(σ_v Δt)²`` to the range's variance and ``(σ_v Δt / r)²`` to the azimuth's. The pair's
state is at the angle plot's time. (That error is correlated with the velocity the
track will estimate; the initial state takes it as independent, a little conservative
in position.)
"""

from __future__ import annotations

import heapq
import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from .. import batch
from ..angles import wrap_pi
from ..init3d import FAR, NEAR, initial_state, spherical_to_position
from ..measurement.kinds import KINDS, RAY, SPHERE, model_of, partners
from ..measurement.models import MIN_HORIZONTAL_RANGE, SphericalModel
from ..types import Measurement
from .hypotheses import by_sensor, gate_threshold, mahalanobis2

_PAIR_PREFILTER = 10.0  # × the gate's σ: azimuth misfit beyond which a pair is not evaluated


class Initiator:
    """New 3D tracks from the plots of one frame that no track took (module docstring);
    the centralised many-target methods and the distributed centre use it.

    Args:
        n_x: the state size.
        priors: the initial-state priors (:class:`fusion.init3d.InitPriors`).
        gate_prob: ``P_G`` of the pair consistency and gathering gates.
    """

    def __init__(self, n_x: int, priors, gate_prob: float):
        self.n_x = n_x
        self._priors = priors
        self.gate_prob = gate_prob

    def _gate(self, dof: int) -> float:
        return gate_threshold(dof, self.gate_prob)

    def initiate(self, left: list[Measurement], tracks=(), frame=None) -> tuple[dict, list]:
        """The :class:`~fusion.tracking.manager.Initiator` step: no group continues a
        track; :meth:`groups` of the plots left, in stream order, start new ones."""
        return {}, self.groups(sorted(left, key=lambda m: m.order_key))

    def groups(self, left: list[Measurement]) -> list[tuple[list[Measurement], list[Measurement], np.ndarray, np.ndarray]]:
        """``(first, more, x, P)`` per new track from the unclaimed plots of one frame
        (:meth:`groups_across` without earlier plots)."""
        return self.groups_across(left)[0]

    def groups_across(self, left: list[Measurement], earlier: Sequence[Measurement] = (), window: float = 0.0):
        """``(groups, moved)``: ``(first, more, x, P)`` per new track from the unclaimed plots: the plots it
        starts from, those it gathers in the same frame (module docstring) and the
        initial state ``(x, P)`` it starts from (``first``'s).

        Every consistent pair gathers first; pairs are then taken best first by their
        *support* — most sensors in the group, then least total ``d²`` (pair and gathered
        plots) — so a pair of one aircraft's ray with a neighbour's range sphere, which
        only its own sensors agree with, loses to the pairs of either aircraft, which the
        other sensors confirm. A pair whose gathered plots a better group took gathers
        again from what is left and waits its turn with its new support. When the angle
        sensor is outside the radar's range sphere its ray crosses it twice ahead of it:
        each crossing in the gate is a candidate of its own (:meth:`pair_consistency`),
        and the support decides between them as between any two pairs.

        ``earlier``: plots of earlier frames that nothing took (module docstring), each
        paired only with a plot of this frame up to ``window`` seconds apart, its radar
        plot moved to the angle plot's time; such a pair comes after a pair within the
        frame of the same support. ``moved`` maps each moved plot in ``groups`` (by
        ``id``) to the plot it was moved from."""
        current = {m.order_key for m in left}
        pool = [*left, *earlier]
        radars = [r for r in pool if KINDS[r.kind].start == SPHERE]
        r_sensor = np.array([r.sensor for r in radars], dtype=object)
        r_now = np.array([r.order_key in current for r in radars], dtype=bool)
        r_t = np.array([r.t for r in radars], dtype=float)
        vel_std = self._priors.vel_std
        candidates = []
        for a in pool:
            if KINDS[a.kind].start != RAY:
                continue  # the ray: an angle sensor's az/el
            a_now = a.order_key in current
            other = r_sensor != a.sensor
            same = other & r_now if a_now else np.zeros(len(radars), dtype=bool)
            across = other & ~same & (r_now | a_now) & (np.abs(r_t - a.t) <= window)
            near = [radars[i] if same[i] else moved(radars[i], a.t, vel_std) for i in np.flatnonzero(same | across).tolist()]
            for r, roots in _near_spheres(a, near, _PAIR_PREFILTER * math.sqrt(self._gate(1)), self._gate(1)):
                candidates += [(a, r, *pair) for pair in self.pair_consistency(a, r, roots)]
        origin = {id(r): r for r in radars}
        moved_from = {}
        used: set[tuple] = set()
        sensors = _BySensor(left)
        queue = []
        screens = sensors.screen(candidates, self._gate)
        for (a, r, root, d2, x, P), gated in zip(candidates, screens):
            plot = origin.get(id(r))
            if plot is None:
                plot = moved_from[id(r)] = r.moved_from
            more, d2_more = self._gather(a, r, x, P, sensors, used, gated)
            queue.append((-len(more), plot is not r, d2 + d2_more, a.order_key, plot.order_key, root, d2, a, r, x, P,
                          more, gated))
        heapq.heapify(queue)  # (ka, kr, root) is unique: the comparison never reaches the plots
        groups = []
        while queue:
            _, across, _, ka, kr, root, d2, a, r, x, P, more, gated = heapq.heappop(queue)
            if ka in used or kr in used:
                continue
            if any(m.order_key in used for m in more):  # a better group took some: gather again
                more, d2_more = self._gather(a, r, x, P, sensors, used, gated)
                heapq.heappush(queue, (-len(more), across, d2 + d2_more, ka, kr, root, d2, a, r, x, P, more, gated))
                continue
            used |= {ka, kr, *(m.order_key for m in more)}
            groups.append((sorted([a, r], key=lambda m: m.order_key), sorted(more, key=lambda m: m.order_key), x, P))
        # A plot starts a track alone only if nothing in the frame could pair with it
        # (lone 2D radar and angle plots attract clutter through their broad priors).
        kinds = {m.kind for m in left}
        alone = [m for m in left if m.order_key not in used and not (partners(m.kind) & kinds)]
        alone.sort(key=lambda m: (not KINDS[m.kind].fixes_range, m.order_key))  # radars first
        kept = {id(m): moved_from[id(m)] for g in groups for m in g[0] if id(m) in moved_from}
        return groups + [([m], [], *initial_state([m], self.n_x, self._priors)) for m in alone], kept

    def _gather(self, a: Measurement, r: Measurement, x: np.ndarray, P: np.ndarray, sensors: "_BySensor",
                used: set, gated: list):
        """The nearest plot in the χ² gate of the pair's initial state ``(x, P)`` from
        every other sensor, among the plots not ``used``; and the sum of their ``d²``.
        ``gated``: per sensor of ``sensors``, the plots that may be in the gate
        (:meth:`_BySensor.screen`)."""
        more, total = [], 0.0
        for plots, Z, free, first in sensors.free(used, (a.sensor, r.sensor), gated):
            if not free:
                continue
            model = model_of(plots[first], self.n_x)
            d2 = mahalanobis2(model, x, P, Z[free])
            j = int(np.argmin(d2))
            if d2[j] <= self._gate(model.n_z):
                more.append(plots[free[j]])
                total += float(d2[j])
        return more, total

    def pair_consistency(self, a: Measurement, r: Measurement,
                         roots: Sequence[int] = (FAR, NEAR)) -> list[tuple[int, float, np.ndarray, np.ndarray]]:
        """``(root, d², x, P)`` per crossing (among ``roots``) of the angle plot's ray with
        the radar plot's range sphere that is ahead of the angle sensor (``root``:
        :data:`fusion.init3d.FAR` or ``NEAR``, module docstring of :mod:`fusion.init3d`)
        and consistent with the radar's azimuth: ``(x, P)`` the pair's initial state at
        that crossing, ``d²`` of the radar's azimuth against it inside the χ²(1) gate.
        Empty if the ray misses or touches the sphere or no crossing is in the gate."""
        pair = sorted([a, r], key=lambda m: m.order_key)
        model = SphericalModel(("az",), r.site, [r.std[0]], self.n_x)
        out = []
        for root in roots:
            if spherical_to_position(a.site, float(a.z[0]), float(a.z[1]), float(r.z[1]), r.site, root) is None:
                continue
            x, P = initial_state(pair, self.n_x, self._priors, root)
            d2 = float(mahalanobis2(model, x, P, np.array([[r.z[0]]]))[0])
            if d2 <= self._gate(1) and not any(np.array_equal(x, o[2]) for o in out):  # one state: one candidate
                out.append((root, d2, x, P))
        return out


class _BySensor:
    """A frame's plots left for initiation, by sensor (in order of first appearance), with
    their measurement vectors stacked once for the many gatherings of one frame."""

    def __init__(self, left: Sequence[Measurement]):
        self.groups = [(plots, np.array([m.z for m in plots], dtype=float), [m.order_key for m in plots])
                       for plots in by_sensor(left)]
        self.index = {id(m): i for i, m in enumerate(left)}

    def free(self, used: set, skip: tuple, gated: list):
        """``(plots, Z, free, first)`` per sensor not in ``skip`` with a plot not ``used``,
        sensors in order of their first plot not used (``first``, its index); ``free``: the
        indices of its plots not used, of those ``gated`` names for it (all if None)."""
        out = []
        for g, (plots, Z, keys) in enumerate(self.groups):
            if plots[0].sensor in skip:
                continue
            first = next((i for i, k in enumerate(keys) if k not in used), None)
            if first is None:
                continue
            near = gated[g]
            free = [i for i in (range(first, len(keys)) if near is None else sorted(near)) if keys[i] not in used]
            out.append((self.index[id(plots[first])], plots, Z, free, first))
        out.sort(key=lambda o: o[0])
        return [(plots, Z, free, first) for _, plots, Z, free, first in out]

    def screen(self, candidates: list, gate) -> list[list]:
        """Per candidate pair ``(a, r, root, d², x, P)``, per sensor: the set of plots within
        the χ² gate (``gate(n_z)``, with a relative slack of :data:`_GATE_SLACK`) of the
        pair's state, all pairs against all of a sensor's plots at once; None where not
        screened (a sensor whose plots differ in site or noise, or whose model is not
        spherical, or a pair over its site). :meth:`Initiator._gather` still decides, on
        these plots only: the ones it drops are outside the gate."""
        out = [[None] * len(self.groups) for _ in candidates]
        if not candidates:
            return out
        X = np.array([c[4] for c in candidates], dtype=float)
        P = np.array([c[5][:3, :3] for c in candidates], dtype=float)
        for g, (plots, Z, _) in enumerate(self.groups):
            first = plots[0]
            if not KINDS[first.kind].sited or any(
                    m.corr is not None or not (np.array_equal(m.site, first.site) and np.array_equal(m.std, first.std))
                    for m in plots):
                continue
            model = model_of(first, X.shape[1])
            if not isinstance(model, SphericalModel):
                continue
            rows = np.array([i for i, c in enumerate(candidates) if first.sensor not in (c[0].sensor, c[1].sensor)],
                            dtype=int)
            if not len(rows):
                continue
            try:
                zp, Hp = batch.spherical(model, X[rows])
            except ValueError:  # a pair over the site: not screened
                continue
            S = Hp @ P[rows] @ Hp.transpose(0, 2, 1) + model.R
            try:
                Si = batch._spd_inverse(0.5 * (S + S.transpose(0, 2, 1)))
            except np.linalg.LinAlgError:
                continue
            nu = Z[None, :, :] - zp[:, None, :]
            nu[..., model.angles] = wrap_pi(nu[..., model.angles])
            d2 = np.einsum("kmi,kij,kmj->km", nu, Si, nu)
            inside = d2 <= gate(model.n_z) * (1.0 + _GATE_SLACK)
            for k, i in enumerate(rows.tolist()):
                out[i][g] = set(np.flatnonzero(inside[k]).tolist())
        return out


@dataclass(frozen=True, eq=False)
class Moved(Measurement):
    """A 2D radar plot moved to another time (:func:`moved`); ``moved_from``: the plot."""

    moved_from: Measurement | None = None


def moved(r: Measurement, t: float, vel_std: float) -> Moved:
    """The 2D radar plot ``r`` (azimuth, range) as a plot at time ``t``: the target moved
    ``v·Δt`` meanwhile, ``v ~ N(0, vel_std² I)``, which adds ``(vel_std Δt)²`` to the
    range's variance and ``(vel_std Δt / range)²`` to the azimuth's (module docstring)."""
    step = vel_std * abs(t - r.t)
    std = np.asarray(r.std, dtype=float)
    std = np.hypot(std, [step / max(float(r.z[1]), 1.0), step])
    return Moved(t, r.sensor, r.kind, r.z, std, r.site, r.seq, r.corr, r.identity, moved_from=r)


def _near_spheres(a: Measurement, radars: list[Measurement], k: float,
                  gate: float = math.inf) -> list[tuple[Measurement, tuple[int, ...]]]:
    """The 2D radar plots whose range sphere the angle plot's ray crosses ahead of it at a
    point within ``k`` azimuth σ of the radar's own azimuth, each with the roots that do —
    a cheap screen, all radars at once, before :meth:`Initiator.pair_consistency` (``k`` ≫
    the gate: a crossing it drops is far outside it). The ray-sphere points are
    :func:`fusion.init3d.spherical_to_position`'s.

    Where the pair's direction is the angle plot's (its σ_az below the radar's, as
    :func:`fusion.init3d.initial_state` chooses), the crossing's ``d²`` against the radar's
    azimuth is computed here too, for all radars at once, and a root outside ``gate``
    (with a relative slack of :data:`_GATE_SLACK` for round-off) is dropped:
    ``P_pos = J diag(σ_az², σ_el², σ_r²) Jᵀ`` with ``J = ∂p/∂(az, el, range)`` of the
    crossing, ``H = [n, −e, 0]/ρ²`` of the azimuth from the radar's site, ``d² = ν² / (H
    P_pos Hᵀ + σ_β²)`` — :meth:`Initiator.pair_consistency`'s test, which still decides."""
    if not radars:
        return []
    az, el = float(a.z[0]), float(a.z[1])
    ce, se, ca, sa = math.cos(el), math.sin(el), math.cos(az), math.sin(az)
    u = np.array([ce * sa, ce * ca, se])
    u_az = np.array([ce * ca, -ce * sa, 0.0])
    u_el = np.array([-se * sa, -se * ca, ce])
    sites = np.array([r.site for r in radars], dtype=float)
    Z = np.array([r.z for r in radars], dtype=float)
    std = np.array([r.std for r in radars], dtype=float)
    std_az = std[:, 0]
    w = np.asarray(a.site, dtype=float) - sites
    b = w @ u
    disc = b * b - (np.sum(w * w, axis=1) - Z[:, 1] ** 2)
    sq = np.sqrt(np.where(disc > 0.0, disc, 0.0))
    exact = (float(a.std[0]) < std_az) & np.isfinite(gate)  # the pair's direction is the angle plot's
    keep = {}
    for root in (FAR, NEAR):
        t = -b + root * sq
        d = w + t[:, None] * u  # the point from the radar's site
        misfit = np.abs(wrap_pi(Z[:, 0] - np.arctan2(d[:, 0], d[:, 1])))
        keep[root] = (disc > 0.0) & (t > 0.0) & (misfit <= k * std_az)
        sel = np.flatnonzero(keep[root] & exact)
        if len(sel):
            keep[root][sel] = _crossing_d2(a, u, u_az, u_el, w[sel], b[sel], t[sel], d[sel], Z[sel], std[sel],
                                           misfit[sel]) <= gate * (1.0 + _GATE_SLACK)
    far, near = keep[FAR], keep[NEAR]
    return [(radars[i], (FAR, NEAR) if far[i] and near[i] else (FAR,) if far[i] else (NEAR,))
            for i in np.flatnonzero(far | near).tolist()]


_GATE_SLACK = 1e-6  # relative: the batched d² may differ from the one-pair path by round-off


def _crossing_d2(a: Measurement, u, u_az, u_el, w, b, t, d, Z, std, misfit) -> np.ndarray:
    """:func:`_near_spheres`'s ``d²`` of each radar's azimuth against the crossing ``s + t
    u`` (``inf`` where the crossing is not ahead or is over the radar's site)."""
    with np.errstate(invalid="ignore", divide="ignore"):
        tb = (t + b)[:, None]
        J = np.stack([t[:, None] * u_az - u * (t[:, None] * (w @ u_az)[:, None] / tb),
                      t[:, None] * u_el - u * (t[:, None] * (w @ u_el)[:, None] / tb),
                      u * Z[:, 1:2] / tb], axis=2)  # (n, 3, 3): columns ∂p/∂az, ∂p/∂el, ∂p/∂r
        rho2 = d[:, 0] ** 2 + d[:, 1] ** 2
        H = np.stack([d[:, 1], -d[:, 0], np.zeros(len(d))], axis=1) / rho2[:, None]
        g = np.einsum("ni,nij->nj", H, J)  # H J: the azimuth's gradient in (az, el, range)
        var = np.array([float(a.std[0]) ** 2, float(a.std[1]) ** 2])
        S = g[:, 0] ** 2 * var[0] + g[:, 1] ** 2 * var[1] + g[:, 2] ** 2 * std[:, 1] ** 2 + std[:, 0] ** 2
        d2 = misfit ** 2 / S
    ok = (t > 0.0) & (rho2 >= MIN_HORIZONTAL_RANGE ** 2) & np.isfinite(d2)
    return np.where(ok, d2, np.inf)
