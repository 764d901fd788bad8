"""A first start on an empty cache speaks before numba is imported (spiel_edge.runtime.
cold_start); a cache holding the probe kernel, or a help request, says nothing early."""

from __future__ import annotations

import io
import os
import select
import signal
import subprocess
import sys
import time

from spiel_edge.runtime import cold_start


def test_an_empty_cache_is_known_cold_and_said(tmp_path, monkeypatch):
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path))
    monkeypatch.setenv("SPIEL_EDGE_HOST_KERNELS", "1")  # no prebuilt kernels in a checkout
    [folder] = cold_start.probe_folders()
    assert folder.parent == tmp_path and folder.name.startswith("protocol_")
    assert cold_start.has_no_kernels()
    out = io.StringIO()
    assert cold_start.say_if_cold("run", out)
    assert "no compiled kernels in the cache" in out.getvalue() and str(tmp_path) in out.getvalue()


def test_a_cache_holding_the_probe_kernel_is_left_to_numba(tmp_path, monkeypatch):
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path))
    [folder] = cold_start.probe_folders()
    folder.mkdir(parents=True)
    (folder / "_cobs_numba.encode-43.py311.nbi").write_bytes(b"index")
    assert not cold_start.has_no_kernels()
    out = io.StringIO()
    assert not cold_start.say_if_cold("run", out) and out.getvalue() == ""


def test_the_folder_is_numbas_own_choice():
    """The folder numba's cache itself uses for the probe kernel in this process."""
    from spiel_edge.protocol import _cobs_numba

    assert str(cold_start.probe_folders()[0]) == str(_cobs_numba.encode._cache._cache_path)


def _first_line(args: list[str], env: dict) -> tuple[float, str]:
    t0 = time.perf_counter()
    proc = subprocess.Popen(
        [sys.executable, "-m", "spiel_edge.cli", *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        env=env,
        start_new_session=True,
    )
    try:
        ready, _, _ = select.select([proc.stdout, proc.stderr], [], [], 60.0)
        line = ready[0].readline().decode() if ready else ""
        return time.perf_counter() - t0, line
    finally:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()


def test_run_on_an_empty_cache_says_so_first_and_help_does_not(tmp_path):
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path), "SPIEL_EDGE_HOST_KERNELS": "1"}
    _, line = _first_line(["run", "--port", "sim://", "--frames", "1"], env)
    assert line.startswith("spiel-edge run: no compiled kernels in the cache")
    _, line = _first_line(["run", "--help"], env)
    assert line.startswith("Usage: spiel-edge run")
