"""The import graph of ``fusion/``: acyclic, and no import inside a function except of
an optional dependency.

Run as a script for the graph itself (``python tests/test_import_graph.py``): one line
per module with the project modules it imports, then the cycles and the function-local
imports, if any. Built with ``ast`` from the source, so nothing is imported to draw it.
"""

from __future__ import annotations

import ast
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = "fusion"
OPTIONAL = frozenset()  # third-party modules fusion/ may import lazily (none today)


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
    names = [prefix]
    if node.module is None or node.level:  # ``from . import kalman``: a submodule, perhaps
        names += [f"{prefix}.{a.name}" for a in node.names]
    return names


def import_graph(package: str = PACKAGE):
    """``(edges, local)``: module -> the project modules it imports (anywhere in it), and
    ``(module, line, imported)`` for every import inside a function or class body."""
    files = sorted((ROOT / package).rglob("*.py"))
    modules = {_module_name(p): p for p in files}
    edges: dict[str, set[str]] = {m: set() for m in modules}
    local: list[tuple[str, int, str]] = []
    for name, path in modules.items():
        tree = ast.parse(path.read_text(), str(path))
        top = set(map(id, tree.body))
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                targets = _resolve(name, path.name == "__init__.py", node)
            else:
                continue
            inner = [t for t in targets if t in modules]
            edges[name] |= {t for t in inner if t != name}
            if id(node) not in top and (inner or not all(t.split(".")[0] in OPTIONAL for t in targets)):
                local.append((name, node.lineno, ", ".join(inner or targets)))
    return edges, local


def cycles(edges: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components with more than one module (Tarjan)."""
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
    return out


def test_fusion_is_acyclic():
    edges, _ = import_graph()
    assert cycles(edges) == []


def test_no_function_local_imports_in_fusion():
    _, local = import_graph()
    assert local == []


def test_fusion_imports_nothing_of_the_project_outside_itself():
    for path in (ROOT / PACKAGE).rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and not node.level and node.module:
                assert node.module.split(".")[0] not in ("services", "sensors_sim", "schemas"), path
            if isinstance(node, ast.Import):
                assert all(a.name.split(".")[0] not in ("services", "sensors_sim", "schemas") for a in node.names), path


def test_the_graph_sees_a_cycle_and_a_local_import(tmp_path, monkeypatch):
    """The checks can fail: a package with a cycle closed by a late import."""
    pkg = tmp_path / "pkg"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    (pkg / "a.py").write_text("from .b import f\n")
    (pkg / "b.py").write_text("from . import a\n\ndef f():\n    from .a import f\n")
    monkeypatch.setattr(sys.modules[__name__], "ROOT", tmp_path)
    edges, local = import_graph("pkg")
    assert cycles(edges) == [["pkg.a", "pkg.b"]]
    assert local == [("pkg.b", 4, "pkg.a")]


if __name__ == "__main__":
    edges, local = import_graph(sys.argv[1] if len(sys.argv) > 1 else PACKAGE)
    for m in sorted(edges):
        print(f"{m}: {', '.join(sorted(edges[m])) or '-'}")
    found = cycles(edges)
    print(f"cycles: {len(found)}")
    for c in found:
        print("  " + " <-> ".join(c))
    print(f"function-local imports: {len(local)}")
    for m, line, what in local:
        print(f"  {m}:{line}: {what}")


def test_a_source_process_does_not_import_the_recording_sdk():
    """Every process parses the whole command line; a sensor, a tracker or the fuser must
    not pay for what only the recorder needs. Importing the Rerun SDK and scipy.stats at
    parse time made each source take 3.3 s instead of 1.5 s to start, so on two cores the
    sources of a run came up seconds after their start time and caught up in a burst."""
    import subprocess

    code = ("import sys; from services.cli import build_parser; build_parser(); "
            "import services.source, services.fuser, services.tracker; "
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
