r"""Noise jammers: their state, and their effect on the sensors.

Both are pure functions of the scenario and the time, so a sensor computes how it is
jammed from the scenario alone (not from ``jam/*`` messages) and a distributed run and
an in-process run contaminate identically.

A jammer is on during its schedule ``[t_on, t_off)``. While on it affects a sensor within
``reach`` if it is a ``barrage`` jammer (wide band), or a ``spot`` jammer on the sensor's
``band`` from ``search_delay`` after each switch-on (document 003). The
jamming-to-signal ratio at a sensor observing a target at ``d_t``, the jammer at ``d_j``
(both floored at 1 m), powers referred to ``d₀`` = 1 km::

    ρ_j = (P_j / P_s) · (d_t / d₀)^k / (d_j / d₀)²,     k = 2 passive, 4 radar

* noise: ``σ_J² = σ²·(1 + Σ_j ρ_j)``; outliers with probability ``p_j = 1 − exp(−ρ_j)``
  (≈ ρ_j when weak, 63 % at 0 dB);
* a jammer with ``p_outlier`` fixes p instead and adds no Gaussian noise: the thesis's
  ``(1 − p)·N(0, σ²) + p·outlier(σ₂)``;
* several jammers act independently, ``p = 1 − Π_j (1 − p_j)``; the outlier's law and
  std are those of the jammer with the largest ``p_j`` (the first on a tie).

An outlier replaces the angles by truth + noise of std ``outlier_std`` (``laplacian`` or
``uniform``, :mod:`sensors_sim.noise`), and ranges by truth + noise of
``outlier_std_range`` if the jammer gives one.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Iterator

import numpy as np

from .spec import JammerSpec, Scenario, SensorSpec
from .trajectories import iter_times

_D_REF = 1000.0  # m: the distance powers are referred to
_D_MIN = 1.0  # m: floor of distances in the J/S ratio (a jammer flying over a sensor)


@dataclass(frozen=True, eq=False)
class JamState:
    """What a jammer is doing at time ``t`` (published on ``jam/<jammer>``; the fields
    the ``jam_state`` message carries have its names: pos, on, mode, power, law, affects).

    ``pos`` is its ENU position; ``law`` the outlier law; ``band`` the victim band of a
    spot jammer (None: barrage, every band); ``searching`` is True while a spot jammer
    that is on has not yet found its band; ``affects`` lists the sensors it currently
    jams (in scenario order).
    """

    jammer: str
    t: float
    pos: np.ndarray
    on: bool
    mode: str
    band: str | None
    power: float
    reach: float
    law: str
    outlier_std: float
    p_outlier: float | None
    searching: bool
    affects: tuple[str, ...]


def switched_on_at(jammer: JammerSpec, t: float) -> float | None:
    """Start of the schedule interval containing ``t``, or None if the jammer is off."""
    for t_on, t_off in jammer.schedule:
        if t_on <= t < t_off:
            return t_on
    return None


def _has_found(jammer: JammerSpec, t: float) -> bool:
    t_on = switched_on_at(jammer, t)
    return t_on is not None and (jammer.mode == "barrage" or t >= t_on + jammer.search_delay)


def affects(jammer: JammerSpec, sensor: SensorSpec, t: float) -> bool:
    """Whether ``jammer`` jams ``sensor`` at time ``t`` (schedule, mode, band, reach)."""
    if not _has_found(jammer, t):
        return False
    if jammer.mode == "spot" and sensor.band != jammer.band:
        return False
    return float(np.linalg.norm(sensor.site.position(t) - jammer.site.position(t))) <= jammer.reach


def jam_state(scenario: Scenario, jammer_id: str, t: float) -> JamState:
    """The state of ``jammer_id`` at scenario time ``t``."""
    j = scenario.jammer(jammer_id)
    on = switched_on_at(j, t) is not None
    return JamState(
        jammer=j.id, t=float(t), pos=j.site.position(t), on=on, mode=j.mode, band=j.band,
        power=j.power, reach=j.reach, law=j.outlier_law, outlier_std=j.outlier_std,
        p_outlier=j.p_outlier, searching=on and not _has_found(j, t),
        affects=tuple(s.id for s in scenario.sensors.values() if affects(j, s, t)),
    )


def jam_events(scenario: Scenario, jammer_id: str) -> Iterator[JamState]:
    """The jammer's state every ``period`` from 0 up to the duration, for publishing."""
    j = scenario.jammer(jammer_id)
    for t in iter_times(0.0, j.period, scenario.duration):
        yield jam_state(scenario, jammer_id, float(t))


def jam_to_signal(jammer: JammerSpec, sensor: SensorSpec, d_jammer: float, d_target: float) -> float:
    """ρ = (P_j/P_s)·(d_t/d₀)^k/(d_j/d₀)², k = 4 for radars, 2 otherwise (module doc)."""
    k = 4 if sensor.active else 2
    d_t = max(d_target, _D_MIN) / _D_REF
    d_j = max(d_jammer, _D_MIN) / _D_REF
    return jammer.power / sensor.signal_power * d_t**k / d_j**2


def outlier_probability(rho: float) -> float:
    """``p = 1 − exp(−ρ)``: the outlier probability at jamming-to-signal ratio ρ."""
    return -math.expm1(-rho)


@dataclass(frozen=True)
class JamEffect:
    """How the jammers acting on one sensor contaminate one measurement.

    ``variance_gain`` multiplies the Gaussian error variance; ``p_outlier`` is the
    probability of an outlier of law ``outlier_law`` and std ``outlier_std`` (angles)
    / ``outlier_std_range`` (ranges; None: none); ``jammers`` are the ids acting.
    """

    p_outlier: float
    variance_gain: float
    outlier_law: str
    outlier_std: float
    outlier_std_range: float | None
    jammers: tuple[str, ...]


def jam_effect(scenario: Scenario, sensor_id: str, t: float, target_position: np.ndarray) -> JamEffect | None:
    """The combined effect of every jammer on ``sensor_id`` observing a target at
    ``target_position`` at time ``t``; None if no jammer affects it."""
    sensor = scenario.sensor(sensor_id)
    site = sensor.site.position(t)
    d_target = float(np.linalg.norm(np.asarray(target_position) - site))
    acting, p_each, gain = [], [], 1.0
    for j in scenario.jammers.values():
        if not affects(j, sensor, t):
            continue
        if j.p_outlier is not None:
            p = j.p_outlier
        else:
            rho = jam_to_signal(j, sensor, float(np.linalg.norm(j.site.position(t) - site)), d_target)
            p, gain = outlier_probability(rho), gain + rho
        acting.append(j)
        p_each.append(p)
    if not acting:
        return None
    lead = acting[int(np.argmax(p_each))]  # argmax: first on a tie
    return JamEffect(
        p_outlier=1.0 - math.prod(1.0 - p for p in p_each),
        variance_gain=gain,
        outlier_law=lead.outlier_law,
        outlier_std=lead.outlier_std,
        outlier_std_range=lead.outlier_std_range,
        jammers=tuple(j.id for j in acting),
    )
