"""numba behind one version gate (issue 42, item 1): every numba internal the kernel cache and
the lean loader rely on is in ``_numba_gate.RELIED_ON`` (or ``INSTANCE``); a rename of any of
them is found at import, and both layers then stand aside for numba's own njit(cache=True),
with one warning, and the commands still work."""

from __future__ import annotations

import importlib
import json
import os
import subprocess
import sys
import textwrap

import pytest

from spiel_edge import _numba_gate


@pytest.fixture(autouse=True)
def _fresh_verdict():
    _numba_gate.problem.cache_clear()
    yield
    _numba_gate.problem.cache_clear()


def _owner(module_name: str, dotted: str):
    obj = importlib.import_module(module_name)
    *path, last = dotted.split(".")
    for part in path:
        obj = getattr(obj, part)
    return obj, last


def test_the_installed_numba_passes_the_gate():
    assert _numba_gate.problem() == ""  # CI runs the tested versions (pyproject.toml bounds)


@pytest.mark.parametrize("module_name,dotted", _numba_gate.RELIED_ON)
def test_a_rename_of_each_internal_is_found(monkeypatch, module_name, dotted):
    owner, last = _owner(module_name, dotted)
    if not isinstance(owner, type) and last not in vars(owner):  # an instance's method
        owner = type(owner)
    if isinstance(owner, type):  # inherited: hidden wherever the classes define it
        for cls in type.mro(owner):
            if last in vars(cls):
                monkeypatch.delattr(cls, last)
    else:
        monkeypatch.delattr(owner, last)
    assert dotted.split(".")[-1] in _numba_gate.problem()


@pytest.mark.parametrize(
    "owner,name", [(o, n) for o, names in _numba_gate.INSTANCE.items() for n in names]
)
def test_a_rename_of_each_instance_attribute_is_found(monkeypatch, owner, name):
    def hidden(obj):
        class Renamed:
            def __getattr__(self, attr):
                if attr == name:
                    raise AttributeError(attr)
                return getattr(obj, attr)

        return Renamed()

    # the probe objects of _instance_problem, each seen without ``name``
    original = _numba_gate._instance_problem

    def probe_without():
        from numba import njit
        from numba.core import caching

        cache = caching.FunctionCache(_numba_gate._probe)
        objects = {
            "FunctionCache": cache,
            "FunctionCache._impl": cache._impl,
            "IndexDataCacheFile": cache._cache_file,
            "Dispatcher": njit(_numba_gate._probe),
        }
        objects[owner] = hidden(objects[owner])
        for o, names in _numba_gate.INSTANCE.items():
            for n in names:
                if not hasattr(objects[o], n):
                    return f"{o} instances have no {n}"
        return ""

    assert original() == ""
    monkeypatch.setattr(_numba_gate, "_instance_problem", probe_without)
    assert name in _numba_gate.problem()


def test_a_version_outside_the_tested_range_is_refused(monkeypatch):
    monkeypatch.setitem(_numba_gate.TESTED, "numba", ((0, 1),))
    assert "outside the tested range" in _numba_gate.problem()


# A faithful rename in a fresh interpreter: the attribute moves to a new name and every numba
# function that used the old name uses the new one (its bytecode's names rewritten), so numba
# itself keeps working while spiel-edge's view of it breaks, as after an upgrade.
RENAME = textwrap.dedent(
    """
    import importlib, sys, types

    def rename(module_name, dotted):
        owner = importlib.import_module(module_name)
        *path, old = dotted.split(".")
        for part in path:
            owner = getattr(owner, part)
        new = old + "_renamed"
        if isinstance(owner, type):  # where it is defined
            owner = next(c for c in owner.__mro__ if old in vars(c))
        setattr(owner, new, vars(owner)[old] if isinstance(owner, type) else getattr(owner, old))
        delattr(owner, old)

        def fix(code):
            consts = tuple(fix(c) if isinstance(c, types.CodeType) else c for c in code.co_consts)
            names = tuple(new if n == old else n for n in code.co_names)
            return code.replace(co_names=names, co_consts=consts)

        for name, module in list(sys.modules.items()):
            if not name.startswith("numba") or module is None:
                continue
            for value in list(vars(module).values()):
                functions = []
                if isinstance(value, types.FunctionType):
                    functions.append(value)
                elif isinstance(value, type):
                    for member in vars(value).values():
                        member = getattr(member, "__func__", member)
                        if isinstance(member, property):
                            functions += [f for f in (member.fget, member.fset) if f]
                        elif isinstance(member, types.FunctionType):
                            functions.append(member)
                for f in functions:
                    if f.__module__ and f.__module__.startswith("numba"):
                        f.__code__ = fix(f.__code__)

    import numba.core.caching, numba.core.codegen, numba.core.cpu
    import numba.core.runtime.nrtdynmod
    rename(MODULE, DOTTED)
    from spiel_edge.cli import main
    sys.argv = ["spiel-edge", "run", "--port", "sim://", "--frames", "3", "--no-track"]
    main()
    """
)


def _run(env_extra: dict, module_name: str | None = None, dotted: str | None = None):
    env = {**os.environ, **env_extra}
    code = RENAME.replace("MODULE", repr(module_name)).replace("DOTTED", repr(dotted))
    if module_name is None:
        code = code.replace("rename(None, None)", "pass")
    out = subprocess.run(
        [sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=300
    )
    records = [json.loads(line) for line in out.stdout.splitlines() if line.startswith("{")]
    return out, [r["position_mm"] for r in records]


@pytest.mark.parametrize(
    "module_name,dotted",
    [  # the three an upgrade simulation broke before the gate (issue 42), and one per layer
        ("numba.core.caching", "_CacheLocator"),
        ("numba.core.caching", "FunctionCache._index_key"),
        ("numba.core.caching", "IndexDataCacheFile._dump"),
        ("numba.core.codegen", "JITCodeLibrary._set_compiled_object"),
    ],
)
def test_commands_still_work_after_a_rename(module_name, dotted):
    assert (module_name, dotted) in _numba_gate.RELIED_ON
    base, want = _run({}, None, None)
    assert base.returncode == 0, base.stderr
    out, got = _run({}, module_name, dotted)
    assert out.returncode == 0, out.stderr[-2000:]
    assert got == want and len(got) == 3
    warnings = [line for line in out.stderr.splitlines() if "numba's own cache" in line]
    assert len(warnings) == 1 and dotted.split(".")[-1] in warnings[0]
