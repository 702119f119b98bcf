"""Reading a ``[tracker]`` table into a configuration dataclass, shared by every family
of methods (:class:`fusion.patent.TrackerConfig`, :class:`fusion.df.methods.DFConfig`)."""

from __future__ import annotations

from dataclasses import fields
from typing import Any, Mapping

import numpy as np


def config_values(cls: type, config: Mapping[str, Any] | None, what: str,
                  string_options: Mapping[str, tuple[str, ...]] | None = None) -> dict[str, Any]:
    """The table's values, type-checked against the dataclass ``cls``.

    Unknown keys are an error. A field whose default is a string takes a string; any
    other field takes a finite number (not a bool), or, for a field named in
    ``string_options``, one of the strings listed there. Range checks are the class's.
    ``what`` names the table in the errors (e.g. ``"tracker config"``).
    """
    config = dict(config or {})
    string_options = dict(string_options or {})
    known = {f.name: f for f in fields(cls)}
    for key in config:
        if key not in known:
            raise ValueError(f"unknown {what} key {key!r} (known: {', '.join(sorted(known))})")
    values = {}
    for key, value in config.items():
        if isinstance(known[key].default, str):
            if not isinstance(value, str):
                raise ValueError(f"{what} {key!r} must be a string, got {value!r}")
        elif key in string_options and isinstance(value, str):
            if value not in string_options[key]:
                raise ValueError(f"{what} {key!r} must be a positive number or one of {string_options[key]}, "
                                 f"got {value!r}")
        elif isinstance(value, bool) or not isinstance(value, (int, float)) or not np.isfinite(value):
            raise ValueError(f"{what} {key!r} must be a finite number, got {value!r}")
        values[key] = value
    return values


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
    from .methods import method_names  # late: the registry imports the method modules, which import this one

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
