"""The import graph of the project's packages (``fusion/``, ``schemas/``, ``sensors_sim/``,
``services/``): acyclic, layered, and no import inside a function except of an optional
dependency.

* Acyclic: no two modules import each other, directly or through others, across all four
  packages (a package's ``__init__`` re-exporting its own modules is no cycle).
* Layered (docs/design.md, "Dependency direction"): ``fusion`` imports none of the
  others; ``schemas`` imports ``fusion``; ``sensors_sim`` imports ``fusion`` and
  ``schemas``; ``services`` may import all three.
* No function-local imports: every import is at module level (a module-level ``try`` or
  ``if`` counts), except of the optional dependencies :data:`OPTIONAL` (Rerun, matplotlib),
  which only their one feature needs.
* A module loaded on first use (``fusion.lazy.lazy("services.launcher")``, at module
  level: the command line reaches a command's heavy modules only when it runs) is an
  edge like any import, so the checks see it.

Run as a script for the graph itself (``python tests/test_import_graph.py [PACKAGE...]``):
per package, one line per module with the project modules it imports, then the cycles
and the function-local imports, if any. Built with ``ast`` from the source, so nothing
is imported to draw it.
"""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("fusion", "schemas", "sensors_sim", "services")
# What each package may import of the others (the layering); a package always imports itself.
MAY_IMPORT = {"fusion": set(), "schemas": {"fusion"}, "sensors_sim": {"fusion", "schemas"},
              "services": {"fusion", "schemas", "sensors_sim"}}
OPTIONAL = frozenset({"rerun", "matplotlib"})  # third-party modules that may be imported where they are used
LAZY = "lazy"  # fusion.lazy.lazy("module"): an import on first use, an edge of the graph


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _resolve(module: str, is_package: bool, node: ast.ImportFrom) -> list[str]:
    """The absolute names an ``from ... import ...`` statement brings in."""
    if node.level:
        base = module.split(".") if is_package else module.split(".")[:-1]
        base = base[: len(base) - (node.level - 1)]
        prefix = ".".join(base + ([node.module] if node.module else []))
    else:
        prefix = node.module or ""
    return [prefix] + [f"{prefix}.{a.name}" for a in node.names]


def _imports(tree: ast.Module, module: str, is_package: bool):
    """``(statement, names, in_function)`` of every import and :data:`LAZY` call of a module."""
    def walk(node: ast.AST, in_function: bool):
        for child in ast.iter_child_nodes(node):
            inner = in_function or isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda,
                                                      ast.ClassDef))
            if isinstance(child, ast.Import):
                yield child, [a.name for a in child.names], in_function
            elif isinstance(child, ast.ImportFrom) and child.module != "__future__":
                yield child, _resolve(module, is_package, child), in_function
            elif (isinstance(child, ast.Call) and isinstance(child.func, ast.Name) and child.func.id == LAZY
                  and child.args and isinstance(child.args[0], ast.Constant) and isinstance(child.args[0].value, str)):
                yield child, [child.args[0].value], in_function
            yield from walk(child, inner)

    yield from walk(tree, False)


def import_graph(packages=PACKAGES):
    """``(edges, local)``: module -> the project modules it imports (anywhere in it), and
    ``(module, line, imported)`` for every import inside a function or class body that is
    not of an optional dependency."""
    if isinstance(packages, str):
        packages = (packages,)
    files = sorted(p for pkg in packages for p in (ROOT / pkg).rglob("*.py"))
    modules = {_module_name(p): p for p in files}
    edges: dict[str, set[str]] = {m: set() for m in modules}
    local: list[tuple[str, int, str]] = []
    for name, path in modules.items():
        tree = ast.parse(path.read_text(), str(path))
        for node, targets, in_function in _imports(tree, name, path.name == "__init__.py"):
            inner = [t for t in targets if t in modules]
            edges[name] |= {t for t in inner if t != name}
            optional = all(t.split(".")[0] in OPTIONAL for t in targets)
            if in_function and (inner or not optional):
                local.append((name, node.lineno, ", ".join(inner or targets[:1])))
    return edges, local


def cycles(edges: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components with more than one module (Tarjan), leaving out
    a package and its own modules (``pkg/__init__`` re-exporting ``pkg.x``, which imports
    ``pkg`` for a sibling: Python's ordinary package layout, not a design cycle)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    out: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in sorted(edges[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in sorted(edges):
        if v not in index:
            visit(v)
    return [c for c in out if not _package_and_its_own(c, edges)]


def _package_and_its_own(component: list[str], edges: dict[str, set[str]]) -> bool:
    """A component that is a package and modules of it that import only the package
    itself within the component (for a name it re-exports)."""
    packages = [m for m in component if any(o.startswith(m + ".") for o in component)]
    if len(packages) != 1:
        return False
    pkg = packages[0]
    rest = [m for m in component if m != pkg]
    return all(m.startswith(pkg + ".") and not (edges[m] & set(rest)) for m in rest)


def layering(edges: dict[str, set[str]]) -> list[str]:
    """The imports that break :data:`MAY_IMPORT`: ``"a.b -> c.d"``."""
    out = []
    for m, targets in edges.items():
        pkg = m.split(".")[0]
        out += [f"{m} -> {t}" for t in sorted(targets)
                if t.split(".")[0] != pkg and t.split(".")[0] not in MAY_IMPORT.get(pkg, set())]
    return out


def test_the_packages_are_acyclic():
    edges, _ = import_graph()
    assert cycles(edges) == []


def test_no_function_local_imports():
    _, local = import_graph()
    assert local == []


def test_the_packages_are_layered():
    edges, _ = import_graph()
    assert layering(edges) == []


def test_the_graph_sees_cycles_local_imports_and_lazy_edges(tmp_path, monkeypatch):
    """The checks can fail: a cycle closed by a late import, one closed by a lazy module,
    and a package that imports a package above it."""
    for pkg in ("pkg", "low"):
        (tmp_path / pkg).mkdir()
        (tmp_path / pkg / "__init__.py").write_text("")
    (tmp_path / "pkg" / "a.py").write_text("from .b import f\n")
    (tmp_path / "pkg" / "b.py").write_text("import json\n\ndef f():\n    from .a import f\n    import rerun\n")
    (tmp_path / "pkg" / "c.py").write_text("from fusion.lazy import lazy\n\nd = lazy('pkg.d')\n")
    (tmp_path / "pkg" / "d.py").write_text("from . import c\n")
    (tmp_path / "low" / "x.py").write_text("import pkg.a\n\ndef g():\n    import json\n")
    monkeypatch.setattr(sys.modules[__name__], "ROOT", tmp_path)
    monkeypatch.setitem(MAY_IMPORT, "low", set())
    monkeypatch.setitem(MAY_IMPORT, "pkg", {"low"})
    edges, local = import_graph(("pkg", "low"))
    assert cycles(edges) == [["pkg.a", "pkg.b"], ["pkg.c", "pkg.d"]]
    assert local == [("low.x", 4, "json"), ("pkg.b", 4, "pkg.a")]  # rerun is optional
    assert layering(edges) == ["low.x -> pkg.a"]


def test_a_package_reexporting_its_modules_is_no_cycle(tmp_path, monkeypatch):
    (tmp_path / "pkg").mkdir()
    (tmp_path / "pkg" / "__init__.py").write_text("from .a import f\nfrom .b import g\n")
    (tmp_path / "pkg" / "a.py").write_text("def f():\n    pass\n")
    (tmp_path / "pkg" / "b.py").write_text("from pkg import f\n")  # a sibling's name, through the package
    monkeypatch.setattr(sys.modules[__name__], "ROOT", tmp_path)
    edges, _ = import_graph("pkg")
    assert cycles(edges) == []
    (tmp_path / "pkg" / "a.py").write_text("from .b import g\n\ndef f():\n    pass\n")  # now a real one
    edges, _ = import_graph("pkg")
    assert cycles(edges) == [["pkg", "pkg.a", "pkg.b"]]


def test_the_command_line_is_built_from_light_modules():
    """``zfusion --help`` and an argument error must be fast: building the parser imports
    none of numpy, scipy, Zenoh, Rerun or matplotlib (a command's heavy modules load when
    it runs); and a sensor, a tracker or the fuser must not pay for what only the
    recorder and the scorer need (importing the Rerun SDK and scipy.stats made each
    source take 3.3 s instead of 1.5 s to start, so on two cores the sources of a run
    came up seconds after their start time and caught up in a burst)."""
    heavy = ("numpy", "scipy", "zenoh", "rerun", "matplotlib")
    code = ("import sys; from services.cli import build_parser; build_parser(); "
            f"print(sorted(m for m in {heavy!r} if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]", out.stdout
    code = ("import sys; import services.source, services.fuser, services.tracker; "
            "print(sorted(m for m in ('rerun', 'scipy.stats', 'matplotlib') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]", out.stdout


def test_no_test_module_imports_another():
    """Shared helpers live in the support modules (``tests/_*.py``) and fixtures in
    ``conftest.py``: a test module imported by another would run its tests' imports and
    fixtures twice, and a helper would be found only by knowing which test holds it."""
    tests = ROOT / "tests"
    offenders = []
    for path in sorted(tests.rglob("test_*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            names = [a.name for a in node.names] if isinstance(node, ast.Import) else \
                [node.module or ""] if isinstance(node, ast.ImportFrom) and not node.level else []
            offenders += [f"{path.name}: {n}" for n in names if any(part.startswith("test_") for part in n.split("."))]
    assert not offenders, offenders


def main(packages: list[str]) -> int:
    edges, local = import_graph()
    for pkg in packages:
        mods = sorted(m for m in edges if m.split(".")[0] == pkg)
        print(f"== {pkg}: {len(mods)} modules, {sum(len(edges[m]) for m in mods)} imports of project modules")
        for m in mods:
            print(f"{m}: {', '.join(sorted(edges[m])) or '-'}")
    found = cycles(edges)
    print(f"cycles: {len(found)}")
    for c in found:
        print("  " + " <-> ".join(c))
    print(f"function-local imports: {len(local)}")
    for m, line, what in local:
        print(f"  {m}:{line}: {what}")
    broken = layering(edges)
    print(f"imports against the layering: {len(broken)}")
    for b in broken:
        print(f"  {b}")
    return 1 if found or local or broken else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:] or list(PACKAGES)))
