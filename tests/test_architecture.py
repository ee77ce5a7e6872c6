"""Architecture: the module import graph of jaxpose/ has no cycles.

Every module is parsed with ``ast`` (nothing is imported); every ``import`` and
``from ... import`` anywhere in it — module level, inside functions, under
``TYPE_CHECKING`` — is an edge, with relative imports resolved against the module's
package. ``from pkg import name`` points at the submodule ``pkg.name`` when one exists,
else at ``pkg``. Cycles are the strongly connected components with more than one module
(or a module importing itself).
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1] / "jaxpose"


def module_names(package_dir: Path) -> dict[str, tuple[Path, bool]]:
    """Dotted name → (file, is a package ``__init__``) for every module under the package."""
    out = {}
    for path in sorted(package_dir.rglob("*.py")):
        parts = list(path.relative_to(package_dir.parent).with_suffix("").parts)
        is_pkg = parts[-1] == "__init__"
        if is_pkg:
            parts = parts[:-1]
        out[".".join(parts)] = (path, is_pkg)
    return out


def import_graph(package_dir: Path) -> dict[str, set[str]]:
    """Module → the set of modules of the same package it imports (anywhere in its body)."""
    mods = module_names(package_dir)

    def resolve(name: str) -> str | None:
        while name and name not in mods:
            name = name.rpartition(".")[0]
        return name or None

    edges: dict[str, set[str]] = {m: set() for m in mods}
    for mod, (path, is_pkg) in mods.items():
        base = mod.split(".") if is_pkg else mod.split(".")[:-1]
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), str(path))):
            targets: list[str] = []
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                if node.level:
                    if node.level > len(base):
                        raise ValueError(f"{path}: relative import beyond the top package")
                    parent = base[: len(base) - node.level + 1]
                    full = ".".join(parent + ([node.module] if node.module else []))
                else:
                    full = node.module or ""
                targets = [
                    f"{full}.{a.name}" if f"{full}.{a.name}" in mods else full
                    for a in node.names
                ]
            for t in targets:
                r = resolve(t)
                if r is not None:
                    edges[mod].add(r)
    return edges


def cycles(edges: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components that are cycles (Tarjan, iterative), each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []
    counter = 0
    for root in sorted(edges):
        if root in index:
            continue
        work = [(root, iter(sorted(edges[root])))]
        index[root] = low[root] = counter
        counter += 1
        stack.append(root)
        on_stack.add(root)
        while work:
            v, it = work[-1]
            w = next(it, None)
            if w is not None:
                if w not in index:
                    index[w] = low[w] = counter
                    counter += 1
                    stack.append(w)
                    on_stack.add(w)
                    work.append((w, iter(sorted(edges[w]))))
                elif w in on_stack:
                    low[v] = min(low[v], index[w])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[v])
            if low[v] == index[v]:
                comp = []
                while True:
                    w = stack.pop()
                    on_stack.discard(w)
                    comp.append(w)
                    if w == v:
                        break
                if len(comp) > 1 or v in edges[v]:
                    found.append(sorted(comp))
    return sorted(found)


def test_no_import_cycles_in_jaxpose():
    edges = import_graph(ROOT)
    assert len(edges) > 50  # the walk really saw the package
    assert "jaxpose.graph._analysis" in edges["jaxpose.graph._problem"]
    assert cycles(edges) == []


def _write(root: Path, files: dict[str, str]) -> Path:
    for rel, text in files.items():
        p = root / rel
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text(text)
    return root / "pkg"


def test_detects_function_local_and_relative_cycles(tmp_path):
    pkg = _write(tmp_path, {
        "pkg/__init__.py": "",
        "pkg/sub/__init__.py": "from . import a\n",
        "pkg/sub/a.py": "from .b import f\n",
        "pkg/sub/b.py": "def f():\n    from ..c import g\n    return g\n",
        "pkg/c.py": "import os\n\ndef g():\n    import pkg.sub.a\n",
        "pkg/d.py": "from pkg.sub import a\n",
    })
    edges = import_graph(pkg)
    assert edges["pkg.sub.b"] == {"pkg.c"}
    assert edges["pkg.c"] == {"pkg.sub.a"}
    assert edges["pkg.d"] == {"pkg.sub.a"}
    assert cycles(edges) == [["pkg.c", "pkg.sub.a", "pkg.sub.b"]]


def test_acyclic_package_and_self_import(tmp_path):
    pkg = _write(tmp_path, {
        "pkg/__init__.py": "from .a import x\n",
        "pkg/a.py": "from .b import y\nx = y\n",
        "pkg/b.py": "y = 1\n",
    })
    assert cycles(import_graph(pkg)) == []
    (pkg / "b.py").write_text("def h():\n    from . import b\n")
    assert cycles(import_graph(pkg)) == [["pkg.b"]]


def test_relative_import_beyond_top_is_an_error(tmp_path):
    pkg = _write(tmp_path, {"pkg/__init__.py": "", "pkg/a.py": "from ... import z\n"})
    with pytest.raises(ValueError, match="beyond the top package"):
        import_graph(pkg)
