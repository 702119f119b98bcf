"""One registry of every estimation method, by its name (``SS``, ``HNV``, ``EKF``, ...).

The 3D methods of the patent live in :mod:`fusion.patent`, the bearings-only methods of
the theses in :mod:`fusion.df.methods`; both register factories ``make(config)``
returning an object with ``process`` / ``advance`` / ``finish`` (see those modules).
A ``[tracker]`` table with ``association`` makes the named method a many-target one, and
the method keeps its name: a centralised 3D method is wrapped in
:class:`fusion.mtt.MultiTargetMethod`, a DF method in
:class:`fusion.df.multi.MultiEmitterMethod` (many emitters: bearing association and ghost
rejection, each emitter localised by the named method); the methods split into nodes
and a centre — HNV, PHHNV, DDHNV, KF+TR and MKF+TR — associate in their own nodes and
centre (:mod:`fusion.network`, "Many targets") and get the table as it is.
"""

from __future__ import annotations

from typing import Any, Callable


def _registry() -> dict[str, Callable[[dict], Any]]:
    from .df.methods import DF_METHODS
    from .patent import PATENT_METHODS

    clash = set(PATENT_METHODS) & set(DF_METHODS)
    if clash:  # one name per concept
        raise RuntimeError(f"method names registered twice: {sorted(clash)}")
    return {**PATENT_METHODS, **DF_METHODS}


def method_names() -> list[str]:
    return list(_registry())


def make_method(name: str, config: dict | None = None) -> Any:
    reg = _registry()
    if name not in reg:
        raise ValueError(f"unknown method {name!r}; known: {', '.join(reg)}")
    from .mtt import AssociationConfig, MultiTargetMethod
    from .network import SPLITS, NetworkMethod

    association, rest = AssociationConfig.split(config)
    if association is not None and name in SPLITS:  # it associates in its own nodes and centre
        return NetworkMethod(name, dict(config or {}))
    if association is not None:
        from .df.methods import DF_METHODS
        from .df.multi import MultiEmitterMethod

        wrap = MultiEmitterMethod if name in DF_METHODS else MultiTargetMethod
        return wrap(name, lambda: reg[name](dict(rest)), association)
    return reg[name](dict(config or {}))
