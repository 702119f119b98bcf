"""The association and track-management keys of ``[tracker]``: a table with
``association`` makes a method a many-target one (docs/algorithms.md, "Many targets";
``jipda``'s keys: "JIPDA: association with track existence")."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from functools import partial

from ..config import config_values
from .associators import GNN
from .jipda import ExistenceLogic, ExistenceRule, JIPDA
from .table import DuplicateWatch, ManagementRule, TrackLogic, TrackTable

#: the ``association`` names: global nearest neighbour with M-of-N logic, JIPDA with existence logic
ASSOCIATIONS = ("gnn", "jipda")


@dataclass(frozen=True)
class AssociationConfig:
    """The association and track-management keys of ``[tracker]`` (docs/algorithms.md, "Many
    targets"). ``confirm_m``, ``confirm_n`` and ``delete_misses`` are GNN's track logic;
    ``p_detect``, ``p_survive`` and the ``existence_*`` thresholds JIPDA's."""

    association: str = "gnn"
    gate_prob: float = 0.999
    confirm_m: int = 3
    confirm_n: int = 4
    delete_misses: int = 3
    max_pos_std: float = math.inf
    local_max_pos_std: float | None = None
    merge_frames: int = 3
    p_detect: float = 0.9
    p_survive: float = ExistenceRule.p_survive
    existence_birth: float = ExistenceRule.existence_birth
    existence_confirm: float = ExistenceRule.existence_confirm
    existence_delete: float = ExistenceRule.existence_delete
    jpda_star: bool = False  # JIPDA keeps only the likeliest of permuted joint events (no coalescence)
    revisit_s: float | None = None  # rotating radars: frames are sweeps (fusion.tracking.sweep)
    pair_window_s: float = 0.0  # sweeps: a 2D radar and an angle plot this far apart still start a track

    KEYS = ("association", "gate_prob", "confirm_m", "confirm_n", "delete_misses", "max_pos_std",
            "local_max_pos_std", "merge_frames", "p_detect", "p_survive", "existence_birth", "existence_confirm",
            "existence_delete", "jpda_star", "revisit_s", "pair_window_s")

    @classmethod
    def split(cls, config: dict | None) -> tuple["AssociationConfig | None", dict]:
        """``(association config or None, the rest of the table)``: None when the table
        has no ``association`` key (one target: the method as it is)."""
        config = dict(config or {})
        mine = {k: config.pop(k) for k in cls.KEYS if k in config}
        if "association" not in mine:
            if mine:
                raise ValueError(f"tracker config keys {sorted(mine)} need 'association' (one of {ASSOCIATIONS})")
            return None, config
        values = config_values(cls, mine, "tracker config")
        for key in ("confirm_m", "confirm_n", "delete_misses", "merge_frames"):
            if key in values and (not float(values[key]).is_integer()):
                raise ValueError(f"tracker config {key!r} must be an integer, got {values[key]!r}")
            if key in values:
                values[key] = int(values[key])
        cfg = cls(**values)
        if cfg.association not in ASSOCIATIONS:
            raise ValueError(f"tracker config 'association' must be one of {ASSOCIATIONS}, got {cfg.association!r}")
        if not 0.0 < cfg.gate_prob < 1.0:
            raise ValueError(f"tracker config 'gate_prob' must lie in (0, 1), got {cfg.gate_prob}")
        if not cfg.max_pos_std > 0.0:
            raise ValueError(f"tracker config 'max_pos_std' must be > 0, got {cfg.max_pos_std}")
        if cfg.local_max_pos_std is not None and not cfg.local_max_pos_std > 0.0:
            raise ValueError(f"tracker config 'local_max_pos_std' must be > 0, got {cfg.local_max_pos_std}")
        if not 0.0 < cfg.p_detect <= 1.0:
            raise ValueError(f"tracker config 'p_detect' must lie in (0, 1], got {cfg.p_detect}")
        if cfg.revisit_s is not None and not cfg.revisit_s > 0.0:
            raise ValueError(f"tracker config 'revisit_s' must be > 0, got {cfg.revisit_s}")
        if not cfg.pair_window_s >= 0.0:
            raise ValueError(f"tracker config 'pair_window_s' must be >= 0, got {cfg.pair_window_s}")
        if cfg.pair_window_s and cfg.revisit_s is None:
            raise ValueError("tracker config 'pair_window_s' pairs plots across the frames of rotating radars: "
                             "it needs 'revisit_s'")
        cfg.rule()  # M <= N, K >= 1
        cfg.duplicate_watch()  # F >= 0
        try:
            cfg.existence_rule()
        except ValueError as e:
            raise ValueError(f"tracker config: {e}") from None
        return cfg, config

    @property
    def weighted(self) -> bool:
        """Whether the association answers weights (a PDA update), not an assignment."""
        return self.association == "jipda"

    @property
    def local_pos_std_limit(self) -> float:
        """The ``max_pos_std`` of an HNV node's local tracks."""
        return self.max_pos_std if self.local_max_pos_std is None else self.local_max_pos_std

    def rule(self) -> ManagementRule:
        return ManagementRule(self.confirm_m, self.confirm_n, self.delete_misses, self.max_pos_std)

    def existence_rule(self) -> ExistenceRule:
        return ExistenceRule(self.p_survive, self.existence_birth, self.existence_confirm, self.existence_delete)

    def duplicate_watch(self) -> DuplicateWatch:
        return DuplicateWatch(self.merge_frames, self.gate_prob)

    def associator(self, weighted: bool = False, **options):
        """The associator named by ``association`` (``options``: GNN's ``confirmed_first``).
        A caller that can apply only an assignment leaves ``weighted`` False, and a
        weighted association is then an error: the bearings-only trackers, for one."""
        if self.association == "gnn":
            return GNN(**options)
        if not weighted:
            raise ValueError(f"association {self.association!r} answers weights, which this method cannot use: "
                             f"use 'gnn' ('jipda' serves the centralised 3D methods and the local trackers of "
                             f"HNV and PHHNV)")
        return JIPDA(self.p_detect, self.gate_prob, jpda_star=self.jpda_star)

    def track_to_track(self) -> "AssociationConfig":
        """The configuration of a network's centre, which associates the nodes' tracks
        by track-to-track GNN with M-of-N logic whatever its nodes' association."""
        return dataclasses.replace(self, association="gnn")

    def table(self, prefix: str = "T") -> TrackTable:
        """An empty track table, ids ``prefix<n>``: under :meth:`rule` (GNN), or by
        existence under :meth:`existence_rule` (JIPDA)."""
        if self.association == "jipda":
            return TrackTable(partial(ExistenceLogic, self.existence_rule(), self.max_pos_std), prefix)
        return TrackTable(partial(TrackLogic, self.rule()), prefix)
