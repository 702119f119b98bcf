"""The names a command line gives, checked before any heavy import: a method's name
(:data:`fusion.topology.METHOD_TOPOLOGIES`, the registry's light table) and a scenario's
(a built-in's file, or a file the user names), and a ``--set`` key (one that some
method's ``[tracker]`` takes: :data:`fusion.topology.TRACKER_KEYS`).

Light on purpose, as :mod:`.options`: ``zfusion run --scenario patent-3d --method XYZ``
answers before numpy, scipy or Zenoh load. Whether a known method fits the scenario's
sensors, and whether a ``--set`` key is one its own ``[tracker]`` takes, is checked against
the loaded scenario (:mod:`services.request`), still before any process starts.
"""

from __future__ import annotations

import difflib
import importlib.util
import os
from pathlib import Path

from fusion.topology import METHOD_TOPOLOGIES, TRACKER_KEYS

from ..errors import UserError


def check_method(name: str | None) -> None:
    """``name`` (None: the scenario's default, checked with it) is a method of the registry."""
    if name is not None and name not in METHOD_TOPOLOGIES:
        raise UserError(f"unknown method {name!r}; known: {', '.join(METHOD_TOPOLOGIES)}")


def check_methods(names: list[str] | None) -> None:
    for name in names or []:
        check_method(name)


def check_settings(settings: list[tuple[str, object]] | None) -> None:
    """Every ``--set`` key is one that some method takes (a misspelt key answers at once)."""
    for key, _ in settings or []:
        if key not in TRACKER_KEYS:
            close = difflib.get_close_matches(key, sorted(TRACKER_KEYS), n=1, cutoff=0.75)
            hint = f"did you mean {close[0]!r}? " if close else ""
            raise UserError(f"unknown tracker config key {key!r} ({hint}known: {', '.join(sorted(TRACKER_KEYS))})")


def builtin_dir() -> Path:
    """The built-in scenarios' directory (``sensors_sim`` is located, not imported: its
    ``__init__`` loads numpy)."""
    spec = importlib.util.find_spec("sensors_sim")
    return Path(next(iter(spec.submodule_search_locations))) / "scenarios"


def builtin_scenarios() -> list[str]:
    """The built-in scenarios' names, from the package's directory."""
    return sorted(p.stem for p in builtin_dir().glob("*.toml"))


def check_scenario(ref: str | None) -> None:
    """``ref`` names a built-in scenario or a file there is (as the loader reads it: a
    path if it looks like one); what the file says is the loader's to check."""
    if ref is None:
        return
    looks_like_path = ref.endswith(".toml") or os.sep in ref or (os.altsep and os.altsep in ref) or os.path.exists(ref)
    if looks_like_path:
        if not os.path.isfile(ref):
            raise UserError(f"{ref}: cannot read scenario file: no such file")
        return
    names = builtin_scenarios()
    if ref not in names:
        raise UserError(f"unknown scenario {ref!r}: not a file, and not a built-in ({', '.join(names)})")
