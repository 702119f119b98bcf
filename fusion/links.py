r"""What the nodes of a distributed topology send up and the centre sends down: one frozen
class per message, its meaning carried by its type, never by a flag.

Up (node → centre), each stamped ``(t, node, seq)``, which orders a node's stream:

* :class:`InitRequest` — a measurement no local track took: the centre answers with an
  :class:`Init` on a fused track, or starts one from it;
* :class:`LocalReport` — a local track's update: its estimate, the prior it started from,
  ``K·H``, the time of the centre estimate it restarted from since its previous report,
  and the per-model terms of a filter with models (an IMM, :meth:`model_terms`);
* :class:`PredictionReport` — a local track's prediction and the measurement the centre
  updates it with (two-stage): its prior is itself and ``K·H = 0``;
* :class:`MeasurementReport` — a measurement for the centre to use as it is (a DF
  station's smoothed bearing);
* :class:`Drop` — the node deleted a local track.

Down (centre → node): :class:`Init` (start local track ``track`` from the estimate),
:class:`Feedback` (the fused estimate as the local track's next prior; two-stage also the
centre's update with this node's measurement; an IMM centre its per-model states),
:class:`DropTrack` (delete local track ``track``).

A message names its *node*, not a sensor: a measurement it carries names its own sensor,
and nothing here ties the two (today each node runs beside one sensor and is named after
it). What the fusion rules read of a report: :mod:`fusion.track_fusion`; each type on the
wire: :mod:`schemas.links`; the protocol: docs/network.md.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .types import Estimate, Measurement

@dataclass(frozen=True, eq=False)
class Gaussian:
    """A mean and its covariance."""

    x: np.ndarray
    P: np.ndarray


@dataclass(frozen=True, eq=False)
class ModelTerms:
    """A filter's per-model terms at a report, ``m`` models of ``n`` states: every model's
    estimate ``xs`` (m, n), ``Ps`` (m, n, n); the prediction its last update started from,
    ``prior_xs``, ``prior_Ps``; that update's log-likelihood per model, ``loglik`` (m,).
    After a prediction (or a restart) the prior is the estimate and the log-likelihood 0."""

    xs: np.ndarray
    Ps: np.ndarray
    prior_xs: np.ndarray
    prior_Ps: np.ndarray
    loglik: np.ndarray


@dataclass(frozen=True, eq=False)
class ModelStates:
    """A per-model centre's state at its time: every model's estimate ``xs`` (m, n),
    ``Ps`` (m, n, n) and the mode probabilities ``mu`` (m,)."""

    xs: np.ndarray
    Ps: np.ndarray
    mu: np.ndarray


# Up ------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class Up:
    """What every message up has: its time, its node and the node's counter."""

    t: float
    node: str
    seq: int

    @property
    def order_key(self) -> tuple[float, str, int]:
        return (self.t, self.node, self.seq)

    @property
    def sensor(self) -> str:
        """The stream the centre groups it in (:class:`fusion.grouping.TimeGrouper` groups
        by ``sensor``): its node's."""
        return self.node


@dataclass(frozen=True, eq=False)
class InitRequest(Up):
    """The node has no local track for ``measurement`` (of one of its sensors): start one."""

    measurement: Measurement


@dataclass(frozen=True, eq=False)
class _Reported(Up):
    """A report of a local track: its ``estimate`` is the node's, at the message's time."""

    estimate: Estimate

    def __post_init__(self) -> None:
        e = self.estimate
        if e.t != self.t or e.node != self.node:
            raise ValueError(f"a report of node {self.node!r} at t = {self.t!r} carries the estimate of node "
                             f"{e.node!r} at t = {e.t!r}")

    @property
    def track(self) -> str:
        return self.estimate.track


@dataclass(frozen=True, eq=False)
class LocalReport(_Reported):
    """A local track's update (module docstring). ``KH`` is ``K·H`` of the update
    (``P = (I − K H) P̄``), ``feedback_t`` None if the track has not restarted from the
    centre since its previous report."""

    prior: Gaussian
    KH: np.ndarray
    feedback_t: float | None = None
    models: ModelTerms | None = None


@dataclass(frozen=True, eq=False)
class PredictionReport(_Reported):
    """A local track's prediction to ``measurement``'s time, and the measurement, for the
    centre's update (two-stage)."""

    measurement: Measurement
    feedback_t: float | None = None
    models: ModelTerms | None = None

    @property
    def prior(self) -> Gaussian:
        return Gaussian(self.estimate.x, self.estimate.P)

    @property
    def KH(self) -> np.ndarray:
        return np.zeros((self.estimate.x.size,) * 2)


@dataclass(frozen=True, eq=False)
class MeasurementReport(Up):
    """A measurement (of one of the node's sensors, processed by the node) for the
    centre to use as it is."""

    measurement: Measurement


@dataclass(frozen=True, eq=False)
class Drop(Up):
    """The node deleted its local track ``track``."""

    track: str


# Down ----------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class Init:
    """Start the local track ``estimate.track`` from ``estimate`` (the centre's)."""

    node: str
    estimate: Estimate

    @property
    def track(self) -> str:
        return self.estimate.track


@dataclass(frozen=True, eq=False)
class Feedback:
    """The fused ``estimate`` as the next prior of the local track ``estimate.track``;
    ``update``: the centre's update of it with this node's measurement (two-stage);
    ``models``: an IMM centre's per-model states, which an IMM restarts from."""

    node: str
    estimate: Estimate
    update: Gaussian | None = None
    models: ModelStates | None = None

    @property
    def track(self) -> str:
        return self.estimate.track


@dataclass(frozen=True, eq=False)
class DropTrack:
    """Delete the local track ``track`` (as of ``t``)."""

    node: str
    t: float
    track: str


Report = LocalReport | PredictionReport
Uplink = InitRequest | LocalReport | PredictionReport | MeasurementReport | Drop
Downlink = Init | Feedback | DropTrack
