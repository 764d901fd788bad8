"""The project's internal import graph, function-level imports included (ast, no import)."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
PACKAGES = ("spiel_edge", "tools")


def module_files() -> dict[str, Path]:
    files = {}
    for package in PACKAGES:
        for path in sorted((ROOT / package).rglob("*.py")):
            parts = path.relative_to(ROOT).with_suffix("").parts
            name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
            files[name] = path
    return files


def import_graph() -> dict[str, set[str]]:
    """module -> the internal modules it imports anywhere in its text."""
    files = module_files()
    graph: dict[str, set[str]] = {}
    for name, path in files.items():
        is_package = path.name == "__init__.py"
        edges = set()
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            edges.update(t for t in _targets(node, name, is_package, files) if t != name)
        graph[name] = edges
    return graph


def _targets(node: ast.AST, module: str, is_package: bool, files: dict) -> list[str]:
    if isinstance(node, ast.Import):
        return [alias.name for alias in node.names if alias.name in files]
    if not isinstance(node, ast.ImportFrom):
        return []
    base = node.module or ""
    if node.level:
        parent = module.split(".")
        parent = parent if is_package else parent[:-1]
        parent = parent[: len(parent) - (node.level - 1)]
        base = ".".join([*parent, base] if base else parent)
    # "from pkg import sub" depends on the submodule when it is one, else on pkg itself
    subs = [f"{base}.{alias.name}" for alias in node.names]
    found = [s for s in subs if s in files]
    if len(found) < len(subs) and base in files:
        found.append(base)
    return found


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

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
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


def package_of(module: str) -> str | None:
    """spiel_edge.X.Y -> "X" (a top-level module is its own package; the root is "__init__");
    None outside spiel_edge."""
    parts = module.split(".")
    if parts[0] != "spiel_edge":
        return None
    return parts[1] if len(parts) > 1 else "__init__"


def package_graph(graph: dict[str, set[str]]) -> dict[str, dict[str, set[tuple[str, str]]]]:
    """package -> {package it imports: the (module, module) imports that make the arrow}."""
    found: dict[str, dict[str, set[tuple[str, str]]]] = {}
    for module, targets in graph.items():
        a = package_of(module)
        if a is None:
            continue
        arrows = found.setdefault(a, {})
        for target in targets:
            b = package_of(target)
            if b is not None and b != a:
                arrows.setdefault(b, set()).add((module, target))
    return found
