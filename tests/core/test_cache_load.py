"""spiel_edge/_cache_load.py: the runtime file format, and numba's own path for other code.
The warm start itself (no LLVM pass, same records) is checked after warm-up in
test_numba_cache.py, which already pays for a cold cache."""

import json
import os
import subprocess
import sys

import pytest

from spiel_edge import _cache_load


def test_runtime_blob_round_trips_and_refuses_damage():
    parts = (b"nrt", bytes(range(256)) * 3, b"")
    blob = _cache_load._pack(parts)
    assert _cache_load._unpack(blob) == parts
    for bad in (blob[:-1], blob[:10], b"x" + blob[1:], blob[:-1] + bytes([blob[-1] ^ 1])):
        with pytest.raises(ValueError):
            _cache_load._unpack(bad)
    with pytest.raises(ValueError, match="parts"):
        _cache_load._unpack(_cache_load._pack(parts[:2]))


def test_lean_loading_is_on_for_this_numba_and_can_be_switched_off():
    import numba

    assert _cache_load.install() == (
        _cache_load._version(numba.__version__) in _cache_load.SUPPORTED
    )
    code = "from spiel_edge import _cache_load; print(_cache_load.install())"
    env = {**os.environ, _cache_load.ENV_SWITCH: "0"}
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True)
    assert out.stdout.strip() == "False"
    assert _cache_load._version("0.68.1") == (0, 68) and _cache_load._version("dev") == (0, 0)


FOREIGN = """
import numpy as np
from numba import njit

@njit(cache=True)
def total(n):
    return np.zeros(n).sum() + n
"""


def test_other_packages_cached_functions_keep_numbas_own_loading(tmp_path):
    """Only this project's kernels skip the context refresh: another package's cached
    function loads the stock way (it imports the lowering registries) in a process where
    spiel_edge is imported."""
    (tmp_path / "foreign_kernels.py").write_text(FOREIGN)
    code = (
        "import json, sys; import spiel_edge._jit; import foreign_kernels as f; "
        "print(json.dumps([f.total(3), 'numba.np.arraymath' in sys.modules, "
        "sum(f.total.stats.cache_hits.values())]))"
    )
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "cache"), "PYTHONPATH": str(tmp_path)}
    runs = []
    for _ in range(2):
        out = subprocess.run(
            [sys.executable, "-c", code], env=env, capture_output=True, text=True, cwd=tmp_path
        )
        assert out.returncode == 0, out.stderr
        runs.append(json.loads(out.stdout.strip().splitlines()[-1]))
    assert runs[0] == [3.0, True, 0]  # compiled
    assert runs[1] == [3.0, True, 1]  # loaded from the cache, registries imported as numba does


def test_the_versions_and_internals_it_relies_on_are_checked(monkeypatch):
    from importlib import metadata

    from spiel_edge import _numba_gate

    supported = all(
        _numba_gate._version(metadata.version(d)) in t for d, t in _numba_gate.TESTED.items()
    )
    _numba_gate.problem.cache_clear()
    assert (_cache_load.unsupported() == "") == supported
    monkeypatch.setitem(_numba_gate.TESTED, "llvmlite", ((0, 1),))
    _numba_gate.problem.cache_clear()
    assert _cache_load.unsupported().startswith("llvmlite")
    monkeypatch.setitem(_numba_gate.TESTED, "llvmlite", ((0, 50),))
    missing = (("numba.core.caching", "FunctionCache.no_such_method"),)
    monkeypatch.setattr(_numba_gate, "RELIED_ON", missing)
    _numba_gate.problem.cache_clear()
    if supported:
        assert "FunctionCache.no_such_method" in _cache_load.unsupported()
    monkeypatch.undo()
    _numba_gate.problem.cache_clear()
