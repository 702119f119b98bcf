r"""The filter of one 3D track, as every 3D method, local tracker and many-target
manager uses it, and the registry of filters by name (``[tracker]`` key ``filter``).

A filter holds a Gaussian ``(x, P)`` at time ``t`` and offers

* :meth:`Filter.set_state` ``(x, P, t)``, restarting from a fed-back prior (a filter with
  state beyond ``(x, P)``, the IMM's mode probabilities, keeps it);
* :meth:`Filter.predicted` ``(t) -> (x⁻, P⁻)``, the prediction without changing it (gates);
* :meth:`Filter.predict` ``(t)``, moving it there with the motion model;
* :meth:`Filter.update` ``(model, z)``, the update with a measurement ``z`` of a
  :class:`fusion.measurement.models.MeasurementModel` at the current time, returning the
  step's ``UpdateResult`` (ν, S, NIS, K);
* :meth:`Filter.update_weighted` ``(model, Z, β, β₀)``, the weighted (PDA) update with
  several plots of one scan, each the track's with probability ``βⱼ`` and none with
  ``β₀`` (:mod:`fusion.pda`; the IMM's per model, with its mode probabilities);
* :meth:`Filter.innovations` ``(model, Z)``, the plots' innovations and their ``S``
  without changing the filter (an EKF's or UKF's; what an associator's likelihoods need);
* :attr:`Filter.KH`, ``K·H`` of the last update: what the track-fusion rules need of a
  local update (:mod:`fusion.track_fusion`). For a filter that does not linearise,
  ``H`` is the statistical linearisation ``Pₓᵤᵀ P⁻⁻¹``, so ``P⁺ = (I − K·H) P⁻``
  holds for every filter.

A new filter is one module with a class of this shape and one line in :data:`FILTERS`.
Given an IMM's :class:`fusion.imm.ModelSet` for a motion model (``motion = "imm"``),
:func:`filter_factory` builds a :class:`fusion.imm.TrackIMM` whose model-matched
filters are the named filter, one per model.
"""

from __future__ import annotations

from functools import partial
from typing import Callable, Protocol

import numpy as np

from .imm import ModelSet, TrackIMM
from .ekf import TrackEKF
from .kalman import UpdateResult
from .measurement.models import MeasurementModel
from .pda import WeightedUpdate
from .ukf import TrackUKF


class Filter(Protocol):
    """The Gaussian filter of one 3D track (module docstring)."""

    x: np.ndarray
    P: np.ndarray
    t: float

    def set_state(self, x: np.ndarray, P: np.ndarray, t: float) -> None: ...
    def predicted(self, t: float) -> tuple[np.ndarray, np.ndarray]: ...
    def predict(self, t: float) -> None: ...
    def update(self, model: MeasurementModel, z: np.ndarray) -> UpdateResult: ...
    def update_weighted(self, model: MeasurementModel, Z: np.ndarray, beta, beta0: float) -> WeightedUpdate: ...

    @property
    def KH(self) -> np.ndarray: ...


#: ``(x, P, t) -> Filter``: a new track's filter from its initial state
NewFilter = Callable[[np.ndarray, np.ndarray, float], Filter]


def _ekf(motion, iterations: int = 1, **options) -> NewFilter:
    return partial(TrackEKF, motion, iterations=iterations, **options)


def _ukf(motion, iterations: int = 1) -> NewFilter:  # (iterations: the EKF's)
    return partial(TrackUKF, motion)


#: name -> ``factory(motion, iterations, **options)`` giving a :data:`NewFilter`;
#: ``iterations`` is the centralised methods' ``ekf_iterations`` (1 for a local tracker),
#: ``options`` what the filter alone takes (the EKF's ``max_climb``)
FILTERS: dict[str, Callable[..., NewFilter]] = {
    "ekf": _ekf,
    "ukf": _ukf,
}


def filter_factory(name: str, motion, iterations: int = 1, **options) -> NewFilter:
    """The filter ``name`` of ``motion`` (with ``options``, those given); for a
    :class:`~fusion.imm.ModelSet`, an IMM of such filters."""
    try:
        make = FILTERS[name]
    except KeyError:
        raise ValueError(f"unknown filter {name!r} (known: {', '.join(FILTERS)})") from None
    options = {k: v for k, v in options.items() if v is not None}
    if isinstance(motion, ModelSet):
        return partial(TrackIMM, motion, [make(m, iterations, **options) for m in motion.models])
    return make(motion, iterations, **options)
