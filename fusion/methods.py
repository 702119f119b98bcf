"""The registry of estimation methods: one record per method, by its name.

A :class:`MethodSpec` says everything the rest of the system asks about a method: its
family (``3d``, the patent's methods on 2D radars and angle sensors; ``df``, the
theses' bearings-only methods), its topology, the measurement kinds it uses, whether it
fuses tracks, what a scenario needs to run it, how to build it in-process, how it
splits into local nodes and a centre (the distributed ones), and how it tracks many
targets. The registry's order is the default order (the theses' tables, then the
patent's). The command line's choices, the evaluation's default methods and the
launcher's defaults read it; nothing else lists methods.

Many targets: a ``[tracker]`` table with ``association`` makes the named method a
many-target one and it keeps its name; its record says how (``many``): a centralised 3D
method is a :class:`fusion.mtt.MultiTargetMethod` (a filter per track, updated with the
method's scan update), a centralised DF method a :class:`fusion.df.multi.MultiEmitterMethod`
(an instance of it per emitter); the split methods associate in their own nodes and
centre (:mod:`fusion.network`).
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from functools import partial
from typing import Any, Callable, Mapping, Sequence

from .df.methods import DF_METHODS, DFConfig
from .df.multi import MultiEmitterMethod
from .measurement.kinds import KINDS, RAY, SPHERE, kinds_of
from .mtt import MultiTargetMethod
from .df.stations import station_split
from .network import NetworkMethod, Split, track_split
from .patent import KINDS_3D, TrackerConfig, centralised, pieces_hndd, pieces_lcdd, pieces_stacked
from .topology import METHOD_TOPOLOGIES, TOPOLOGIES, TRACKER_KEYS, scheme_of
from .tracking.config import AssociationConfig

FAMILIES = ("df", "3d")
BEARING = kinds_of("df")


@dataclass(frozen=True)
class MethodSpec:
    """One estimation method.

    Attributes:
        name: the method's name (``SS``, ``HNV``, ``EKF``, ...), as the estimates carry it.
        family: ``"3d"`` or ``"df"``.
        topology: one of :data:`TOPOLOGIES`.
        kinds: the measurement kinds it uses (of its family's; others are ignored).
        make: ``make(table) -> Method`` from a resolved ``[tracker]`` table (one target).
        fuses_tracks: its centre fuses local tracks (a ``fusion_rule`` applies).
        needs: kinds a scenario must have every one of (besides one of ``kinds``).
        colocated: needs a 2D radar and an angle sensor on one site (HNDD).
        fixed_stations: needs fixed DF stations (per-station bearing smoothers).
        split: its local node and centre (``None`` for a centralised method); with
            many targets a split method runs them (:class:`fusion.network.NetworkMethod`).
        many: ``many(table) -> Method`` from a resolved ``[tracker]`` table with
            ``association`` (many targets).
    """

    name: str
    family: str
    topology: str
    kinds: frozenset
    make: Callable[[dict], Any]
    fuses_tracks: bool = False
    needs: frozenset = frozenset()
    colocated: bool = False
    fixed_stations: bool = False
    split: Split | None = None
    many: Callable[[dict], Any] | None = None

    def __post_init__(self):
        if self.family not in FAMILIES or self.topology not in TOPOLOGIES:
            raise ValueError(f"{self.name}: family {self.family!r}, topology {self.topology!r}")
        if (self.split is None) != (self.topology == "centralised"):
            raise ValueError(f"{self.name}: a split method is one that is not centralised")

    def runs_on(self, kinds: set[str], fixed_stations: bool = True, colocated: bool = False) -> bool:
        """Whether a scenario whose sensors measure ``kinds`` can feed this method."""
        return (bool(self.kinds & kinds) and self.needs <= kinds and (colocated or not self.colocated)
                and (fixed_stations or not self.fixed_stations))


def _centralised(name: str, pieces, kinds=KINDS_3D, **facts) -> MethodSpec:
    return MethodSpec(name, "3d", "centralised", frozenset(kinds), partial(centralised, name, pieces, kinds),
                      many=partial(MultiTargetMethod.from_table, name, pieces, kinds), **facts)


def _track_split(name: str, topology: str) -> MethodSpec:
    split = track_split(name, scheme_of(topology))
    network = partial(NetworkMethod, split)
    return MethodSpec(name, "3d", topology, KINDS_3D, network, fuses_tracks=True, split=split, many=network)


def _df(name: str, split: Split | None = None) -> MethodSpec:
    """A DF method; in-process, a split one runs as one method (:data:`DF_METHODS`), which
    equals its nodes and centre wired back to back (with many emitters, as the nodes
    and centre themselves)."""
    if split is None:
        return MethodSpec(name, "df", "centralised", BEARING, DF_METHODS[name],
                          many=partial(MultiEmitterMethod.from_table, name, DF_METHODS[name]))
    return MethodSpec(name, "df", "distributed", BEARING, DF_METHODS[name], fixed_stations=True, split=split,
                      many=partial(NetworkMethod, split))


_PAIR = frozenset(k for k in KINDS_3D if KINDS[k].start in (RAY, SPHERE))  # a ray and a sphere (LCDD, HNDD)

METHODS: dict[str, MethodSpec] = {s.name: s for s in (
    # the theses' bearings-only methods
    *(_df(n) for n in ("EKF", "MEKF1", "MEKF2", "MEKF3", "MEKF4", "MEKF5", "IMM", "TORRIERI")),
    _df("KF+TR", station_split("KF+TR", cross_fed=False)),
    _df("MKF+TR", station_split("MKF+TR", cross_fed=True)),
    # the patent's single-sensor baselines and its six methods
    _centralised("RADAR2D", pieces_stacked, {"range_az"}),
    _centralised("ANGLE", pieces_stacked, {"azel"}),
    _centralised("RADAR3D", pieces_stacked, {"az_el_range"}),
    _centralised("LCDD", pieces_lcdd, needs=_PAIR),
    _centralised("HNDD", pieces_hndd, needs=_PAIR, colocated=True),
    _centralised("SS", pieces_stacked),
    _track_split("HNV", "distributed"),
    _track_split("PHHNV", "feedback"),
    _track_split("DDHNV", "two-stage"),
)}
if set(DF_METHODS) != {n for n, s in METHODS.items() if s.family == "df"}:
    raise RuntimeError("fusion.df.methods.DF_METHODS and the registry disagree")
if list(METHOD_TOPOLOGIES.items()) != [(n, s.topology) for n, s in METHODS.items()]:
    raise RuntimeError("fusion.topology.METHOD_TOPOLOGIES and the registry disagree")
if TRACKER_KEYS != ({f.name for f in fields(TrackerConfig)} | {f.name for f in fields(DFConfig)}
                     | set(AssociationConfig.KEYS)):
    raise RuntimeError("fusion.topology.TRACKER_KEYS and the methods' configurations disagree")
TRACK_FUSION_METHODS = tuple(s.name for s in METHODS.values() if s.fuses_tracks)
SPLIT_METHODS = tuple(s.name for s in METHODS.values() if s.split is not None)


def method_names() -> list[str]:
    return list(METHODS)


def spec(name: str) -> MethodSpec:
    try:
        return METHODS[name]
    except KeyError:
        raise ValueError(f"unknown method {name!r}; known: {', '.join(METHODS)}") from None


def split(name: str) -> Split:
    """The local node and centre of a distributed method."""
    s = METHODS.get(name)
    if s is None or s.split is None:
        raise ValueError(f"{name} is not a distributed method (distributed methods: {', '.join(SPLIT_METHODS)})")
    return s.split


def topology_default(topology: str, family: str) -> str | None:
    """The method a topology runs when none is named: the family's first in that topology."""
    return next((s.name for s in METHODS.values() if s.topology == topology and s.family == family), None)


def make_method(name: str, config: dict | None = None) -> Any:
    """Build method ``name`` from a resolved ``[tracker]`` table (:func:`method_config`)."""
    s = spec(name)
    association, _ = AssociationConfig.split(config)
    return (s.make if association is None else s.many)(dict(config or {}))


def method_config(table: Mapping[str, Any] | None, method: str | None,
                  overrides: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """The flat configuration one method runs with, from a scenario's ``[tracker]`` table.

    The table holds keys common to every method and, optionally, a sub-table
    ``methods`` of per-method tables whose keys replace the common ones for the methods
    it names: ``[tracker.methods.HNV]``, or ``[tracker.methods."LCDD,HNDD,SS"]`` for
    several at once. The consistent priors of a centralised filter are not those of a
    local tracker that cannot observe altitude (docs/consistency.md §8).
    ``overrides`` (the command line's ``--fusion-rule``, a sweep's parameter) replace both.
    ``method=None`` gives the common keys alone.

    A per-method table naming an unknown method, or a method named twice, is an error, so
    a typo cannot silently leave a method on the common values.
    """
    table = dict(table or {})
    per_method = table.pop("methods", {})
    if not isinstance(per_method, Mapping):
        raise ValueError(f"tracker config 'methods' must be a table of per-method tables, got {per_method!r}")
    known = method_names()
    by_method: dict[str, Mapping[str, Any]] = {}
    for key, sub in per_method.items():
        if not isinstance(sub, Mapping):
            raise ValueError(f"tracker config 'methods.{key}' must be a table, got {sub!r}")
        for name in (n.strip() for n in key.split(",")):
            if name not in known:
                raise ValueError(f"tracker config 'methods' names unknown method {name!r} (known: {', '.join(known)})")
            if name in by_method:
                raise ValueError(f"tracker config 'methods' gives method {name!r} two tables")
            by_method[name] = sub
    return {**table, **(by_method.get(method, {}) if method else {}), **(overrides or {})}


def track_fusion_rule(table: dict | None, methods: Sequence[str]) -> str | None:
    """The track-fusion rule the named methods run with, for reports: ``None`` if none of
    them fuses tracks, ``"HNV: bar-shalom-campo, PHHNV: info"`` if per-method tables differ."""
    rules = {m: method_config(table, m).get("fusion_rule", TrackerConfig.fusion_rule)
             for m in methods if m in TRACK_FUSION_METHODS}
    if len(set(rules.values())) > 1:
        return ", ".join(f"{m}: {r}" for m, r in rules.items())
    return next(iter(rules.values()), None)
