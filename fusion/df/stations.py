r"""KF+TR and MKF+TR split into a node per DF station and a centre (:mod:`fusion.network`'s
protocol and in-process composition).

A *station node* smooths its station's bearings (:func:`fusion.df.methods.make_station_smoother`:
a KF, or MKF cross-fed from the centre's fix) and sends each smoothed bearing up as a
``bearing`` measurement with the smoothed std; the *centre* localises with Torrieri on
the latest smoothed bearing of every station (:class:`fusion.df.methods.SmootherTorrieriMethod`
with the smoothing done upstream).

Many emitters (``association`` in the table): a station hears one bearing per emitter,
with nothing that says which, so a node keeps *bearing tracks*, one smoother each,
takes a scan's bearings by a χ²(1) gate on each smoother's prediction and global
nearest neighbour, starts a track from every bearing none takes and deletes a track
after ``delete_misses`` scans without one; every smoothed bearing goes up as a bearing
of the station. The centre associates them into emitters as the centralised tracker
associates raw bearings (:class:`fusion.df.multi.MultiEmitterMethod`).
"""

from __future__ import annotations

import math

import numpy as np

from ..angles import wrap_pi
from ..measurement.kinds import kinds_of
from ..links import MeasurementReport
from ..network import Centre, FramedNode, LocalNode, Split
from ..tracking.config import AssociationConfig
from ..tracking.hypotheses import Hypotheses, gate_threshold
from ..types import Estimate, Measurement
from .methods import DFConfig, SmootherTorrieriMethod, make_station_smoother
from .models import bearing_of
from .multi import MultiEmitterMethod


class StationNode(LocalNode):
    """A DF station of KF+TR / MKF+TR: smooths its bearings, sends each smoothed
    bearing (a ``bearing`` measurement with the smoothed std) up."""

    kinds = kinds_of("df")

    def __init__(self, sensor: str, config: dict | None, cross_fed: bool):
        c = DFConfig.from_dict(config)
        super().__init__(sensor, c.pair_tol)
        self.smoother = make_station_smoother(c, cross_fed)

    def _process(self, m, alone):
        return [MeasurementReport(m.t, self.node, self._next_seq(), self.smoother.update(m))]


class MultiStationNode(FramedNode):
    """A DF station of KF+TR / MKF+TR with many emitters (module docstring): the
    bearings of a scan are plots of its bearing tracks; every track's smoothed bearing
    goes up."""

    kinds = kinds_of("df")

    def __init__(self, sensor: str, config: dict | None, cross_fed: bool, association: AssociationConfig):
        c = DFConfig.from_dict(config)
        super().__init__(sensor, c.pair_tol)
        self.config, self.cross_fed, self.association = c, cross_fed, association
        self._associator = association.associator()
        self.tracks: list = []  # bearing smoothers, in birth order
        self.misses: list[int] = []

    def hypotheses(self, frame: list[Measurement]) -> Hypotheses:
        """The scan's bearings against the bearing tracks: ``d² = wrap(β − β̂)² / (P⁻ + σ²)``
        on each smoother's prediction ``(β̂, P⁻ = P + q)``, χ²(1) gate."""
        betas = np.array([bearing_of(m)[1] for m in frame])
        sigmas = np.array([self.config.sigma_of(m) for m in frame])
        x = np.array([tr.x[0] for tr in self.tracks])
        var = np.array([tr.P[0, 0] + tr.q for tr in self.tracks])  # the smoother's predicted variance
        r = wrap_pi(betas[None, :] - x[:, None])
        n = len(self.tracks)
        return Hypotheses(frame, range(n), (r * r / (var[:, None] + sigmas[None, :] ** 2)).reshape(n, len(frame)),
                          np.full(n, gate_threshold(1, self.association.gate_prob)), np.ones(n, dtype=bool))

    def _process(self, frame: list[Measurement], alone: bool) -> list[MeasurementReport]:
        taken: dict[int, int] = {}  # bearing -> track
        if self.tracks:
            taken = {c: k for k, c in self._associator.associate(self.hypotheses(frame)).pairs}
        old = len(self.tracks)
        self.misses = [0 if k in taken.values() else n + 1 for k, n in enumerate(self.misses)]
        out = []
        for c, m in enumerate(frame):
            if c not in taken:
                taken[c] = len(self.tracks)
                self.tracks.append(make_station_smoother(self.config, self.cross_fed))
                self.misses.append(0)
            out.append(MeasurementReport(m.t, self.node, self._next_seq(), self.tracks[taken[c]].update(m)))
        keep = [k for k in range(len(self.tracks)) if k >= old or self.misses[k] < self.association.delete_misses]
        self.tracks = [self.tracks[k] for k in keep]
        self.misses = [self.misses[k] for k in keep]
        return out


class StationCentre(Centre):
    """The centre of KF+TR / MKF+TR: Torrieri on the latest smoothed bearings
    (:class:`fusion.df.methods.SmootherTorrieriMethod` with the smoothing done upstream);
    with ``association`` in the table, on each emitter's: the smoothed bearings are
    associated into emitters as raw ones are (:class:`fusion.df.multi.MultiEmitterMethod`)."""

    def __init__(self, name: str, config: dict | None):
        super().__init__()
        self.name = name
        association, rest = AssociationConfig.split(config)

        def make() -> SmootherTorrieriMethod:
            return SmootherTorrieriMethod(name == "MKF+TR", rest, smoothed_upstream=True)

        self.method = make() if association is None else MultiEmitterMethod(name, make, association)

    def process(self, u: MeasurementReport) -> list[Estimate]:
        return self.method.process(u.measurement)

    def advance(self, t: float) -> list[Estimate]:
        # t = inf is the end, which finish() closes (the DF methods take finite watermarks)
        return self.method.advance(t) if math.isfinite(t) else []

    def finish(self) -> list[Estimate]:
        return self.method.finish()


def station_split(name: str, cross_fed: bool) -> Split:
    """KF+TR (``cross_fed=False``) / MKF+TR: one emitter, or many with ``association``
    in the table."""

    def node(sensor, config):
        association, rest = AssociationConfig.split(config)
        if association is None:
            return StationNode(sensor, rest, cross_fed)
        return MultiStationNode(sensor, rest, cross_fed, association)

    return Split(name, node, lambda c: StationCentre(name, c))
