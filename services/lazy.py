"""A module loaded on first use: ``launcher = lazy("services.launcher")``.

The ``zfusion`` command line must come up fast (``--help``, an argument error): building
its parser imports only light modules, and a command's heavy modules (numpy, scipy,
Zenoh, Rerun) load when the command runs. A module that needs another only on one path
(the fuser's ``--json`` summary, which needs the scorer) names it the same way, so a
process does not pay for what it may never use. The name is declared at module level,
beside the imports, where ``tests/test_import_graph.py`` reads it as an edge of the
import graph like any import (cycles through it are caught).

This is the standard library's own recipe (:class:`importlib.util.LazyLoader`, "Implementing
lazy imports" in the :mod:`importlib` documentation): the module object is created and
registered at once, and executed on its first attribute access. A module already
imported is returned as it is.
"""

from __future__ import annotations

import importlib.util
import sys
from types import ModuleType


def lazy(name: str) -> ModuleType:
    """The module ``name``, executed when one of its attributes is first read."""
    module = sys.modules.get(name)
    if module is not None:
        return module
    spec = importlib.util.find_spec(name)
    if spec is None or spec.loader is None:
        raise ImportError(f"no module named {name!r}", name=name)
    loader = importlib.util.LazyLoader(spec.loader)
    spec.loader = loader
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    loader.exec_module(module)
    return module
