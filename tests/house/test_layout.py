"""The house rules: no import cycle, short modules, a lazy command line, a formatted tree."""

from __future__ import annotations

import importlib
import pkgutil
import shutil
import subprocess
import sys

import pytest

import spiel_edge.cli as cli_package
from spiel_edge.cli import COMMANDS
from tests.house.imports import ROOT, cycles, import_graph, module_files

MAX_MODULE_LINES = 400


def test_no_import_cycle_counting_function_level_imports():
    graph = import_graph()
    assert "spiel_edge.runtime.loop" in graph and graph["spiel_edge.runtime.loop"]  # sanity
    assert cycles(graph) == []


def test_cycle_finder_finds_a_planted_cycle():
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}
    assert cycles(graph) == [["a", "b", "c"]]


def test_no_module_over_400_lines():
    long = {
        name: n
        for name, path in module_files().items()
        if (n := len(path.read_text().splitlines())) > MAX_MODULE_LINES
    }
    assert long == {}


def test_every_package_says_what_it_owns():
    for name, path in module_files().items():
        if path.name == "__init__.py":
            doc = importlib.import_module(name).__doc__ if name != "tools" else path.read_text()
            assert doc and doc.strip(), f"{name} has no docstring"


def test_every_command_module_is_listed_and_named_as_listed():
    modules = {m.name for m in pkgutil.iter_modules(cli_package.__path__) if m.name[0] != "_"}
    assert modules == set(COMMANDS)
    for name in COMMANDS:
        assert importlib.import_module(f"spiel_edge.cli.{name}").command.name == name


def test_help_loads_no_subcommand_and_no_numba():
    code = (
        "import sys\n"
        "from spiel_edge.cli import main\n"
        "assert main(['--help']) == 0\n"
        "heavy = [m for m in ('numba', 'onnxruntime', 'numpy', 'spiel_edge.cli.run') "
        "if m in sys.modules]\n"
        "print('loaded:' + ','.join(heavy))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip().splitlines()[-1] == "loaded:"
    assert "replay" in out.stdout


@pytest.mark.parametrize("args", [["check"], ["format", "--check"]])
def test_ruff(args):
    ruff = shutil.which("ruff") or str(ROOT / ".venv" / "bin" / "ruff")
    if not shutil.which(ruff):
        pytest.skip("ruff is not installed (pip install 'spiel-edge[test]')")
    paths = ["."]  # the code and the Python blocks in README.md and docs/
    done = subprocess.run([ruff, *args, *paths], cwd=ROOT, capture_output=True, text=True)
    assert done.returncode == 0, done.stdout + done.stderr
