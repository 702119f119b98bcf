"""The association and track-management keys of ``[tracker]``: a table with
``association`` makes a method a many-target one (docs/algorithms.md, "Many targets")."""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import partial

from ..config import config_values
from .associators import ASSOCIATORS
from .table import DuplicateWatch, ManagementRule, TrackLogic, TrackTable

#: the ``association`` names
ASSOCIATIONS = tuple(ASSOCIATORS)


@dataclass(frozen=True)
class AssociationConfig:
    """The association and track-management keys of ``[tracker]`` (docs/algorithms.md, "Many targets")."""

    association: str = "gnn"
    gate_prob: float = 0.999
    confirm_m: int = 3
    confirm_n: int = 4
    delete_misses: int = 3
    max_pos_std: float = math.inf
    local_max_pos_std: float | None = None
    merge_frames: int = 3

    KEYS = ("association", "gate_prob", "confirm_m", "confirm_n", "delete_misses", "max_pos_std",
            "local_max_pos_std", "merge_frames")

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
        cfg.rule()  # M <= N, K >= 1
        cfg.duplicate_watch()  # F >= 0
        return cfg, config

    @property
    def local_pos_std_limit(self) -> float:
        """The ``max_pos_std`` of an HNV node's local tracks."""
        return self.max_pos_std if self.local_max_pos_std is None else self.local_max_pos_std

    def rule(self) -> ManagementRule:
        return ManagementRule(self.confirm_m, self.confirm_n, self.delete_misses, self.max_pos_std)

    def duplicate_watch(self) -> DuplicateWatch:
        return DuplicateWatch(self.merge_frames, self.gate_prob)

    def associator(self, **options):
        """The associator named by ``association`` (``options``: its own, e.g. GNN's ``confirmed_first``)."""
        return ASSOCIATORS[self.association](**options)

    def table(self, prefix: str = "T") -> TrackTable:
        """An empty track table under :meth:`rule`, ids ``prefix<n>``."""
        return TrackTable(partial(TrackLogic, self.rule()), prefix)
