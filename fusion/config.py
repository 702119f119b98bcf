"""Reading a ``[tracker]`` table into a configuration dataclass, shared by every family
of methods (:class:`fusion.patent.TrackerConfig`, :class:`fusion.df.methods.DFConfig`);
the per-method tables are resolved by :func:`fusion.methods.method_config`."""

from __future__ import annotations

import difflib
from dataclasses import fields
from typing import Any, Mapping

import numpy as np


def config_values(cls: type, config: Mapping[str, Any] | None, what: str,
                  string_options: Mapping[str, tuple[str, ...]] | None = None) -> dict[str, Any]:
    """The table's values, type-checked against the dataclass ``cls``.

    Unknown keys are an error. A field whose default is a string takes a string, one
    whose default is a bool a bool; any other field takes a finite number (not a bool),
    or, for a field named in ``string_options``, one of the strings listed there. Range
    checks are the class's.
    ``what`` names the table in the errors (e.g. ``"tracker config"``).
    """
    config = dict(config or {})
    string_options = dict(string_options or {})
    known = {f.name: f for f in fields(cls)}
    for key in config:
        if key not in known:
            close = difflib.get_close_matches(str(key), sorted(known), n=1, cutoff=0.75)
            hint = f"did you mean {close[0]!r}? " if close else ""
            raise ValueError(f"unknown {what} key {key!r} ({hint}known: {', '.join(sorted(known))})")
    values = {}
    for key, value in config.items():
        if isinstance(known[key].default, str):
            if not isinstance(value, str):
                raise ValueError(f"{what} {key!r} must be a string, got {value!r}")
        elif isinstance(known[key].default, bool):
            if not isinstance(value, bool):
                raise ValueError(f"{what} {key!r} must be true or false, got {value!r}")
        elif key in string_options and isinstance(value, str):
            if value not in string_options[key]:
                raise ValueError(f"{what} {key!r} must be a positive number or one of {string_options[key]}, "
                                 f"got {value!r}")
        elif isinstance(value, bool) or not isinstance(value, (int, float)) or not np.isfinite(value):
            raise ValueError(f"{what} {key!r} must be a finite number, got {value!r}")
        values[key] = value
    return values
