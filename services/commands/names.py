"""The names a command line gives, checked before any heavy import: a method's name
(:data:`fusion.topology.METHOD_TOPOLOGIES`, the registry's light table) and a scenario's
(a built-in's file, or a file the user names).

Light on purpose, as :mod:`.options`: ``zfusion run --scenario patent-3d --method XYZ``
answers before numpy, scipy or Zenoh load. Whether a known method fits the scenario's
sensors, and whether a ``--set`` key is one its ``[tracker]`` takes, is checked against
the loaded scenario (:mod:`services.request`), still before any process starts.
"""

from __future__ import annotations

import importlib.util
import os
from pathlib import Path

from fusion.topology import METHOD_TOPOLOGIES

from ..errors import UserError


def check_method(name: str | None) -> None:
    """``name`` (None: the scenario's default, checked with it) is a method of the registry."""
    if name is not None and name not in METHOD_TOPOLOGIES:
        raise UserError(f"unknown method {name!r}; known: {', '.join(METHOD_TOPOLOGIES)}")


def check_methods(names: list[str] | None) -> None:
    for name in names or []:
        check_method(name)


def builtin_scenarios() -> list[str]:
    """The built-in scenarios' names, from the package's directory (``sensors_sim`` is
    located, not imported: its ``__init__`` loads numpy)."""
    spec = importlib.util.find_spec("sensors_sim")
    folder = Path(next(iter(spec.submodule_search_locations))) / "scenarios"
    return sorted(p.stem for p in folder.glob("*.toml"))


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
