"""Layering of omnidl's packages: library packages import only downward, and no package cycle exists.

Every module under ``omnidl/`` is parsed with ``ast``; every ``import`` counts, including lazy imports
inside functions, ``TYPE_CHECKING`` blocks and relative imports. A library package may import packages
of a lower rank (``RANKS``), never one of its own rank or a higher one; the applications wing
(``omnidl/apps``) may import anything and nothing imports it. A top-level package or module missing from
``RANKS`` fails too: give it a floor, or move it into ``apps``.
"""
from __future__ import annotations

import ast
from collections import defaultdict
from pathlib import Path
from typing import NamedTuple

import pytest

ROOT = Path(__file__).resolve().parents[1] / "omnidl"

#: floor of every library package of omnidl (see docs/design.md#floors-of-the-package)
RANKS = {
    "utils": 0, "classes": 0, "ops": 0,
    "cameras": 1,
    "geometry": 2,
    "nn": 3, "viz": 3,
    "models": 4, "losses": 4, "metrics": 4, "synth": 4,
    "data": 5,
    "postprocess": 6,
    "engine": 7,
    "search": 8,
}
APPS = "apps"


class Edge(NamedTuple):
    """One import: ``source`` package imports ``target`` (module ``module``) at ``file:line``."""

    source: str
    target: str
    module: str
    file: str
    line: int

    def __str__(self) -> str:
        return f"{self.file}:{self.line} -> {self.module}"


def _module_name(path: Path, root: Path) -> tuple[str, bool]:
    """Dotted module name of ``path`` under ``root`` (``root.name`` first) and whether it is a package."""
    parts = list(path.relative_to(root.parent).with_suffix("").parts)
    is_pkg = parts[-1] == "__init__"
    if is_pkg:
        parts = parts[:-1]
    return ".".join(parts), is_pkg


def _imported_modules(tree: ast.AST, module: str, is_pkg: bool) -> list[tuple[str, int]]:
    """Absolute names of every module an AST imports (``from X import name`` also yields ``X.name``)."""
    package = module if is_pkg else module.rpartition(".")[0]
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found += [(a.name, node.lineno) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")
                anchor = anchor[:len(anchor) - (node.level - 1)]
                base = ".".join(anchor + ([base] if base else []))
            found.append((base, node.lineno))
            found += [(f"{base}.{a.name}", node.lineno) for a in node.names if a.name != "*"]
    return found


def import_edges(root: Path = ROOT) -> list[Edge]:
    """Every import between different top-level parts of the package at ``root`` (e.g. ``omnidl/``)."""
    top = root.name
    edges = []
    for path in sorted(root.rglob("*.py")):
        module, is_pkg = _module_name(path, root)
        parts = module.split(".")
        if len(parts) < 2:  # the package's own __init__
            continue
        source = parts[1]
        tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
        seen = set()
        for name, line in _imported_modules(tree, module, is_pkg):
            target_parts = name.split(".")
            if len(target_parts) < 2 or target_parts[0] != top:
                continue
            target = target_parts[1]
            if target == source or (target, line) in seen:
                continue
            if not ((root / target).is_dir() or (root / f"{target}.py").is_file()):
                continue  # ``from omnidl.x import name`` also yields ``omnidl.x.name``: keep real parts only
            seen.add((target, line))
            edges.append(Edge(source, target, name, str(path.relative_to(root.parent)), line))
    return edges


def layering_violations(edges: list[Edge], ranks: dict[str, int] = RANKS) -> list[str]:
    """Messages for imports that go up, sideways (same rank) or into ``apps``, and for unranked packages."""
    out = []
    for e in edges:
        if e.target == APPS:
            out.append(f"{e}: nothing imports the applications wing ({e.source} -> apps)")
        elif e.source == APPS:
            continue
        elif e.source not in ranks or e.target not in ranks:
            unranked = e.source if e.source not in ranks else e.target
            out.append(f"{e}: package '{unranked}' has no floor (add it to RANKS or move it into apps)")
        elif ranks[e.target] >= ranks[e.source]:
            out.append(f"{e}: {e.source} (floor {ranks[e.source]}) imports {e.target} (floor {ranks[e.target]})")
    return out


def package_cycles(edges: list[Edge]) -> list[list[str]]:
    """Strongly connected groups of more than one package (Tarjan), each sorted; sorted list."""
    graph: dict[str, set[str]] = defaultdict(set)
    for e in edges:
        graph[e.source].add(e.target)
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    groups = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            group = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                group.append(w)
                if w == v:
                    break
            if len(group) > 1:
                groups.append(sorted(group))

    for v in sorted(set(graph) | {t for ts in graph.values() for t in ts}):
        if v not in index:
            visit(v)
    return sorted(groups)


EDGES = import_edges()
PACKAGES = sorted({p.name for p in ROOT.iterdir() if p.is_dir() and (p / "__init__.py").is_file()}
                  | {p.stem for p in ROOT.glob("*.py") if p.stem != "__init__"})


@pytest.mark.parametrize("package", PACKAGES)
def test_package_imports_only_downward(package):
    bad = layering_violations([e for e in EDGES if e.source == package or (e.target == package == APPS)])
    assert not bad, f"{len(bad)} import(s) break the layering:\n" + "\n".join(bad)


def test_no_import_cycle_between_packages():
    cycles = package_cycles(EDGES)
    detail = []
    for group in cycles:
        detail += [f"  {e} ({e.source} -> {e.target})" for e in EDGES if e.source in group and e.target in group]
    assert not cycles, f"package import cycles {cycles}:\n" + "\n".join(detail)


def test_checker_catches_upward_lazy_relative_and_apps_imports(tmp_path):
    pkg = tmp_path / "omnidl"
    for name in ("cameras", "geometry", "apps", "fisheye"):
        (pkg / name).mkdir(parents=True)
        (pkg / name / "__init__.py").write_text("")
    (pkg / "__init__.py").write_text("")
    (pkg / "classes.py").write_text("")
    (pkg / "cameras" / "base.py").write_text(
        "import math\nfrom omnidl import classes\n\ndef f():\n    from ..geometry import warp\n")
    (pkg / "geometry" / "warp.py").write_text("from omnidl.cameras.base import f\nimport omnidl.apps.cli\n")
    (pkg / "apps" / "cli.py").write_text("from omnidl.geometry.warp import x\nfrom omnidl.cameras import base\n")
    (pkg / "fisheye" / "run.py").write_text("from . import helpers\nfrom ..cameras import base\n")
    edges = import_edges(pkg)
    bad = layering_violations(edges)
    assert bad == ["omnidl/cameras/base.py:5 -> omnidl.geometry: cameras (floor 1) imports geometry (floor 2)",
                   "omnidl/fisheye/run.py:2 -> omnidl.cameras: package 'fisheye' has no floor "
                   "(add it to RANKS or move it into apps)",
                   "omnidl/geometry/warp.py:2 -> omnidl.apps.cli: nothing imports the applications wing "
                   "(geometry -> apps)"]
    assert package_cycles(edges) == [["apps", "cameras", "geometry"]]
