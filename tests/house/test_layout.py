"""The house rules: no import cycle, a lazy command line, a formatted tree, and the docs that
map the tree (docs/pipeline.md's stage table, the README's layout) kept in step with it.

A module's size follows its concept: there is no line cap."""

from __future__ import annotations

import importlib
import pkgutil
import re
import shutil
import subprocess
import sys

import pytest

import spiel_edge.cli as cli_package
from spiel_edge.cli import COMMANDS
from tests.house.imports import ROOT, cycles, import_graph, module_files


def test_no_import_cycle_counting_function_level_imports():
    graph = import_graph()
    assert "spiel_edge.runtime.loop" in graph and graph["spiel_edge.runtime.loop"]  # sanity
    assert cycles(graph) == []


def test_cycle_finder_finds_a_planted_cycle():
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}
    assert cycles(graph) == [["a", "b", "c"]]


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


def test_the_pipeline_pages_stage_table_names_every_module():
    text = (ROOT / "docs" / "pipeline.md").read_text()
    section = text[text.index("## Stages") : text.index("### The compiled path")]
    table = "\n".join(line for line in section.splitlines() if line.startswith("|"))
    pipeline = ROOT / "spiel_edge" / "pipeline"
    modules = {
        path.relative_to(pipeline).as_posix()
        for path in pipeline.rglob("*.py")
        if path.name != "__init__.py"
    }
    named = set(re.findall(r"`([\w/]+\.py)`", table))
    assert modules - named == set(), "modules of pipeline/ missing from docs/pipeline.md"
    assert named - modules == set(), "docs/pipeline.md names modules that do not exist"


def test_the_readmes_layout_matches_the_tree():
    text = (ROOT / "README.md").read_text()
    block = re.search(r"## Layout.*?\n```\n(.*?)```", text, re.S).group(1)
    named = set(re.findall(r"((?:spiel_edge|firmware_protocol|tools)/[\w/.]*)", block))
    for path in named:
        assert (ROOT / path).exists(), f"the README's layout names {path}, which does not exist"
    folders = [
        p.relative_to(ROOT).as_posix() + "/"
        for parent in ("spiel_edge", "spiel_edge/pipeline", "tools")
        for p in sorted((ROOT / parent).iterdir())
        if p.is_dir() and (p / "__init__.py").exists()
    ]
    missing = [f for f in folders if not any(n.startswith(f) for n in named)]
    assert missing == [], f"the README's layout does not name {missing}"
