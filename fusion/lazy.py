"""A module loaded on first use: ``launcher = lazy("services.launcher")``.

The ``zfusion`` command line must come up fast (``--help``, an argument error): building
its parser imports only light modules, and a command's heavy modules (numpy, scipy,
Zenoh, Rerun) load when the command runs. A module that needs another only on one path
(the fuser's ``--json`` summary, which needs the scorer) names it the same way, so a
process does not pay for what it may never use. The name is declared at module level,
beside the imports, where ``tests/test_import_graph.py`` reads it as an edge of the
import graph like any import (cycles through it are caught).

The first attribute read imports the module by the ordinary import system
(:func:`importlib.import_module`) and the proxy reads through to it from then on. Not
:class:`importlib.util.LazyLoader`: that registers a not-yet-executed module in
``sys.modules`` for every other importer to trip over, and a Ctrl-C while it executes
left a half-run module there that later imports took for whole (an ``ImportError`` for a
name the module defines); the ordinary system removes a module whose import failed.
"""

from __future__ import annotations

import importlib
from types import ModuleType


class Lazy:
    """Stands for the module ``name`` until it is first used (module docstring)."""

    __slots__ = ("_name", "_module")

    def __init__(self, name: str):
        self._name = name
        self._module: ModuleType | None = None

    def __getattr__(self, attr: str):
        module = self._module
        if module is None:
            module = self._module = importlib.import_module(self._name)
        return getattr(module, attr)

    def __repr__(self) -> str:
        return f"<module {self._name!r} ({'loaded' if self._module is not None else 'not loaded yet'})>"


def lazy(name: str) -> Lazy:
    """The module ``name``, imported when one of its attributes is first read."""
    return Lazy(name)
