r"""Many targets with the patent's centralised methods (``SS``, ``LCDD``, ``HNDD``,
``RADAR2D``, ``ANGLE``, ``RADAR3D``): a :class:`~fusion.tracking.manager.MultiTargetTracker`
whose every track is one filter, updated with its plots of a frame exactly as the
one-target method updates its filter with a scan.

Switched on by ``association = "gnn"`` in ``[tracker]``, so the method keeps its patent
name; for HNV, PHHNV and DDHNV the same key switches the network's nodes and centre to
many targets (:mod:`fusion.network`).

A *frame* is the group of plots within ``pair_tol`` of its first one
(:class:`fusion.grouping.TimeGrouper`). The parts: the plots of each sensor gated against
the tracks' gating states with sequential gating
(:class:`~fusion.tracking.hypotheses.PlotHypothesiser`), GNN with confirmed tracks first,
pair initiation (:class:`~fusion.tracking.initiators.Initiator`), each track updated by
the method's scan update (:class:`ScanUpdater`) and scoring a hit by
:func:`~fusion.tracking.table.scores_hit`, duplicates removed
(:class:`~fusion.tracking.table.DuplicateWatch`). The steps, the initiation rules and the
keys (:class:`~fusion.tracking.config.AssociationConfig`): docs/algorithms.md, "Many targets".
"""

from __future__ import annotations

import dataclasses
from typing import Callable, Sequence

import numpy as np

from .filters import Filter, NewFilter
from .grouping import TimeGrouper
from .measurement.kinds import model_of
from .patent import GroupedMethod, Piece, TrackerConfig
from .tracking.config import AssociationConfig
from .tracking.hypotheses import PlotHypothesiser
from .tracking.initiators import Initiator
from .tracking.manager import Frame, MultiTargetTracker, Taken
from .tracking.sweep import SweepTracker
from .tracking.table import Track, scores_hit
from .types import Estimate, Measurement

__all__ = ["AssociationConfig", "MultiTargetMethod", "ScanUpdater"]


class ScanUpdater:
    """The updater of a centralised method's tracks: a track's plots of a frame, in
    stream order, are one scan of the method (``pieces``: how a scan becomes updates);
    a track without plots coasts.

    Args:
        name: the method's name (the estimates carry it).
        pieces: ``pieces(scan, n_x) -> [(model, z), ...]``, the method's updates of a scan.
        n_x: the state size.
        new_filter: a new track's filter.
    """

    def __init__(self, name: str, pieces: Callable[[Sequence[Measurement], int], list[Piece]], n_x: int,
                 new_filter: NewFilter):
        self.name, self.pieces, self.n_x, self.new_filter = name, pieces, n_x, new_filter

    def scan(self, f: Filter, scan: Sequence[Measurement]) -> Estimate:
        """Predict ``f`` to the scan's first time and update it with the scan's pieces."""
        t = scan[0].t
        f.predict(t)
        nis, dof = 0.0, 0
        for model, z in self.pieces(scan, self.n_x):
            nis += f.update(model, z).nis
            dof += model.n_z
        return Estimate(t, f.x, f.P, self.name, "centre", None, nis, dof)

    def update(self, track: Track, taken: list[Taken], frame: Frame) -> bool:
        """An assignment's plots: the method's scan update of them, in stream order.
        Weights (JIPDA): each scan's weighted update (``Filter.update_weighted``, the PDA
        update of :mod:`fusion.pda`), in the order the scans were associated — a
        weighted association pairs no plots across sensors, so a method's pieces (LCDD's
        and HNDD's pair of a ray and a sphere) do not apply: every method updates
        sensor by sensor."""
        plots = sorted((m for tk in taken for m in tk.plots), key=lambda m: m.order_key)
        f = track.filter
        if any(tk.weighted for tk in taken):
            f.predict(frame.t)
            for tk in taken:
                f.update_weighted(model_of(tk.plots[0], self.n_x), np.array([m.z for m in tk.plots]), tk.beta, tk.miss)
            track.last = Estimate(f.t, f.x, f.P, self.name, "centre")
        elif plots:
            track.last = self.scan(f, plots)
        else:
            f.predict(frame.t)
            track.last = Estimate(f.t, f.x, f.P, self.name, "centre")
        kinds = {m.sensor: m.kind for m in plots}
        return scores_hit(list(kinds.values()), track.confirmed, min(2, frame.sensors))

    @staticmethod
    def position_cov(track: Track) -> np.ndarray:
        return track.filter.P[:3, :3]

    def start(self, group, frame: Frame) -> Track:
        """A track from :meth:`Initiator.groups`' ``(first, more, x, P)``: its filter
        started at ``(x, P)`` at the time of ``first``, updated at once with ``more``."""
        first, more, x, P = group
        f = self.new_filter(x, P, first[0].t)
        last = Estimate(first[0].t, x, P, self.name, "centre")
        return Track(f, self.scan(f, list(more)) if more else last)


class MultiTargetMethod(GroupedMethod):
    """A centralised 3D method for many targets (module docstring); a streaming method.

    Args:
        name: the method's name (the estimates carry it).
        config: its ``[tracker]`` table without the association keys.
        pieces: how its scans become updates (:mod:`fusion.patent`).
        kinds: the measurement kinds it uses.
        association: the association keys.
    """

    def __init__(self, name: str, config: TrackerConfig, pieces, kinds, association: AssociationConfig):
        self.name = name
        self.kinds = frozenset(kinds)
        self.config = association
        motion = config.motion_model()
        self.n_x = motion.n_x
        self._grouper = TimeGrouper(config.pair_tol)
        updater = ScanUpdater(name, pieces, self.n_x, config.new_filter(motion, centralised=True))
        initiator = Initiator(self.n_x, config.priors(), association.gate_prob)
        if association.revisit_s is not None:  # rotating radars: a frame is a sweep
            self.tracker = SweepTracker(initiator, updater, association.table(),
                                        association.associator(confirmed_first=True), association.gate_prob,
                                        association.rule(), association.revisit_s, association.pair_window_s)
            return
        self.tracker = MultiTargetTracker(
            PlotHypothesiser(self.n_x, association.gate_prob),
            association.associator(weighted=True, confirmed_first=True),
            initiator,
            updater,
            association.table(),
            association.duplicate_watch(),
        )

    @classmethod
    def from_table(cls, name: str, pieces, kinds, table: dict) -> "MultiTargetMethod":
        """From a resolved ``[tracker]`` table with ``association``."""
        association, rest = AssociationConfig.split(table)
        if association is None:
            raise ValueError(f"{name}: many targets need 'association' in the tracker table")
        return cls(name, TrackerConfig.from_dict(rest), pieces, kinds, association)

    def __repr__(self) -> str:
        return f"MultiTargetMethod({self.name!r})"

    @property
    def table(self):
        return self.tracker.table

    @property
    def tracks(self) -> list[Track]:
        """The tracks (``filter``: each one's filter), in priority order."""
        return self.tracker.tracks

    def _group(self, frame: list[Measurement]) -> list[Estimate]:
        return [dataclasses.replace(tr.last, track=tr.id, existence=tr.existence, identity=tr.identity)
                for tr in self.tracker.frame(frame)]
