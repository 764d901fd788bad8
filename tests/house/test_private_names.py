"""No module imports another module's ``_private`` name (issue 42 item 6): what one module
uses of another is public (numba kernels included: ``detect_kernel`` beside its wrapper
``detect``), so a reader sees from a name whether other modules depend on it. Private
*modules* (``spiel_edge._jit``) are imported by name and are not concerned."""

from __future__ import annotations

import ast
from pathlib import Path

from tests.house.imports import ROOT

# (importing file, module, name): each entry says why it cannot be public. Empty: keep it so.
ALLOWED: dict[tuple[str, str, str], str] = {}


def private_imports(text: str, path: str, root: Path = ROOT) -> list[tuple[str, str, str]]:
    found = []
    for node in ast.walk(ast.parse(text, path)):
        if not isinstance(node, ast.ImportFrom):
            continue
        if node.level:  # from .x import _y: relative to the importing file's package
            base = (root / path).parent.joinpath(*[".."] * (node.level - 1)).resolve()
            base = base.joinpath(*(node.module or "").split(".")) if node.module else base
            module = "." * node.level + (node.module or "")
        else:
            base, module = root.joinpath(*node.module.split(".")), node.module
        for alias in node.names:
            name = alias.name
            if not name.startswith("_") or name.startswith("__"):
                continue
            if (base / f"{name}.py").exists() or (base / name / "__init__.py").exists():
                continue  # a private module, imported by its name
            found.append((path, module, name))
    return found


def test_no_module_imports_another_modules_private_name():
    found = [
        hit
        for package in ("spiel_edge", "tools")
        for path in sorted((ROOT / package).rglob("*.py"))
        for hit in private_imports(path.read_text(), str(path.relative_to(ROOT)))
        if hit not in ALLOWED
    ]
    assert found == [], "make these public (or allow one here with the reason):\n" + "\n".join(
        f"{p}: from {m} import {n}" for p, m, n in found
    )


def test_the_check_sees_a_private_name_and_not_a_private_module():
    text = (
        "from spiel_edge.track.kalman import predict_kernel, _hidden\n"
        "from spiel_edge import _jit\n"
        "from .sibling import _relative\n"
        "from . import _abi\n"  # spiel_edge/_abi.py: a private module
    )
    assert private_imports(text, "spiel_edge/x.py") == [
        ("spiel_edge/x.py", "spiel_edge.track.kalman", "_hidden"),
        ("spiel_edge/x.py", ".sibling", "_relative"),
    ]


def test_allowed_entries_still_exist_and_say_why():
    for (path, module, name), why in ALLOWED.items():
        assert why.strip(), f"{path}: {name} is allowed without a reason"
        hits = private_imports((ROOT / path).read_text(), path)
        assert (path, module, name) in hits, f"{path} no longer imports {name}: drop it here"
