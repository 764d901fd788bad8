"""spiel_edge/_kernel_cache.py and _shipped.py: the kernel cache never crashes a start, and a
wheel's prebuilt kernels load with no compile. Each case runs in a fresh interpreter (numba's
CPU and cache folders are chosen once per process) on a one-line kernel, or on the stream
decoder's two kernels for the prebuilt ones."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from spiel_edge import _jit, _kernel_layers, _shipped

TINY = """
from spiel_edge._jit import jit

@jit
def twice(x):
    return 2 * x + 1
"""

PROBE = """
import json, os, signal, sys
if os.environ.get("FSIZE"):  # a full disk: a write past this size fails (EFBIG)
    import resource
    signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    size = int(os.environ["FSIZE"])
    resource.setrlimit(resource.RLIMIT_FSIZE, (size, size))
warnings = []
from spiel_edge import _kernel_cache
_kernel_cache.listeners.append(lambda e, n, d: warnings.append(str(d)) if e == "warning" else None)
import tiny_kernels
value = tiny_kernels.twice(20)
print(json.dumps({"value": value, "counts": _kernel_cache.counts, "warnings": warnings,
                  "writable": tiny_kernels.twice._cache.writable}))
"""


def _probe(tmp_path: Path, **env) -> dict:
    if not env.pop("KEEP_SOURCE", None):
        (tmp_path / "tiny_kernels.py").write_text(TINY)
    full = {
        **os.environ,
        "PYTHONPATH": os.pathsep.join([str(tmp_path), *sys.path]),
        "NUMBA_CACHE_DIR": str(tmp_path / "cache"),
        **env,
    }
    out = subprocess.run(
        [sys.executable, "-c", PROBE], env=full, capture_output=True, text=True, timeout=300
    )
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout.strip().splitlines()[-1])


def _cache_files(tmp_path: Path, pattern: str) -> list[Path]:
    return sorted((tmp_path / "cache").rglob(pattern))


def test_jit_keeps_its_options_when_given_the_function():
    def f(x):
        return x + 1

    kernel = _jit.jit(f, boundscheck=True, inline="always")
    assert kernel.targetoptions["boundscheck"] is True
    assert kernel.targetoptions["inline"] == "always"
    assert kernel.targetoptions["nogil"] is True
    assert type(kernel._cache).__name__ == "KernelCache"
    decorated = _jit.jit(boundscheck=True)(f)
    assert decorated.targetoptions["boundscheck"] is True


def test_a_damaged_cache_file_is_compiled_again(tmp_path):
    first = _probe(tmp_path)
    assert first["value"] == 41 and first["counts"]["compiled"] == 1
    (data,) = _cache_files(tmp_path, "*.nbc")
    data.write_bytes(data.read_bytes()[:40])  # truncated, as a crash mid-write leaves it
    second = _probe(tmp_path)
    assert second["value"] == 41 and second["counts"]["compiled"] == 1
    assert any("unusable" in w for w in second["warnings"])
    third = _probe(tmp_path)  # the compile above rewrote it whole
    assert third["counts"] == {"hits": 1, "shipped_hits": 0, "compiled": 0}
    (index,) = _cache_files(tmp_path, "*.nbi")
    index.write_bytes(b"\x80\x04garbage")
    assert _probe(tmp_path)["value"] == 41
    assert _probe(tmp_path)["counts"]["hits"] == 1  # the index was written afresh


def test_a_flipped_bit_in_a_cached_kernel_is_found_before_it_runs(tmp_path):
    """Bytes changed inside a cache file's machine code (an SD card's bit rot) would run as
    they are (SIGILL, SIGSEGV): the file's seal no longer matches, the kernel compiles."""
    assert _probe(tmp_path)["counts"]["compiled"] == 1
    (data,) = _cache_files(tmp_path, "*.nbc")
    raw = bytearray(data.read_bytes())
    elf = raw.find(b"\x7fELF")
    assert elf > 0
    raw[elf + 200 : elf + 328] = bytes(range(128))
    data.write_bytes(bytes(raw))
    second = _probe(tmp_path)
    assert second["value"] == 41 and second["counts"]["compiled"] == 1
    assert any("SHA-256 does not match" in w for w in second["warnings"]), second
    assert _probe(tmp_path)["counts"]["hits"] == 1  # rewritten whole, sealed
    # a file numba itself wrote (no seal) is a quiet miss, then sealed
    for path in _cache_files(tmp_path, "*.nb*"):
        path.write_bytes(path.read_bytes()[: -(len(_kernel_layers.SEAL_TAG) + 32)])
    third = _probe(tmp_path)
    assert third["counts"]["compiled"] == 1 and not third["warnings"], third
    assert _probe(tmp_path)["counts"]["hits"] == 1


def test_a_kernel_whose_source_file_changed_compiles_again(tmp_path):
    """A module constant the kernel reads is frozen into its machine code, and its bytecode
    does not change with it: the cached kernel of the file as it was must not run."""
    changed = TINY.replace("return 2 * x + 1", "return 2 * x + ONE") + "\nONE = 2\n"
    source = tmp_path / "tiny_kernels.py"
    source.write_text(changed.replace("ONE = 2", "ONE = 1"))
    assert _probe(tmp_path, KEEP_SOURCE="1")["value"] == 41
    assert _probe(tmp_path, KEEP_SOURCE="1")["counts"]["hits"] == 1  # kept, and found
    source.write_text(changed)  # the same size, the same bytecode: only the constant differs
    os.utime(source, (source.stat().st_atime, source.stat().st_mtime + 5))
    result = _probe(tmp_path, KEEP_SOURCE="1")
    assert result["value"] == 42 and result["counts"]["compiled"] == 1


def test_a_damaged_sealed_index_is_started_afresh_when_saving(tmp_path):
    """An index whose seal does not match (bit rot) is a miss, and the save that follows
    writes a new index instead of failing on the old one."""
    assert _probe(tmp_path)["counts"]["compiled"] == 1
    (index,) = _cache_files(tmp_path, "*.nbi")
    index.write_bytes(b"not what was sealed" + _kernel_layers.SEAL_TAG + bytes(32))
    second = _probe(tmp_path)
    assert second["value"] == 41 and second["counts"]["compiled"] == 1
    assert not any("not saved" in w for w in second["warnings"]), second
    assert _probe(tmp_path)["counts"]["hits"] == 1


def test_no_writable_folder_compiles_in_memory_and_says_so(tmp_path):
    """numba raises at import when no folder is writable; the kernel cache compiles and
    says once that nothing is kept (NUMBA_CACHE_DIR, __pycache__ and the user's cache
    folder all under a plain file: not even root can create them)."""
    blocker = tmp_path / "file"
    blocker.write_text("")
    (tmp_path / "__pycache__").write_text("")
    env = {"NUMBA_CACHE_DIR": str(blocker / "c"), "XDG_CACHE_HOME": str(blocker / "x")}
    env["HOME"] = str(blocker / "home")
    result = _probe(tmp_path, **env)
    assert result["value"] == 41 and result["writable"] is False
    assert any("not kept" in w for w in result["warnings"])


def test_an_unusable_numba_cache_dir_is_said_not_ignored(tmp_path, monkeypatch):
    """numba quietly falls back to __pycache__ when NUMBA_CACHE_DIR cannot be written: the
    run says where the kernels go instead, and doctor fails the check."""
    blocker = tmp_path / "a-file"
    blocker.write_text("")
    result = _probe(tmp_path, NUMBA_CACHE_DIR=str(blocker))
    assert result["value"] == 41
    assert any(f"NUMBA_CACHE_DIR {blocker} is not a folder" in w for w in result["warnings"])
    from numba.core import config

    from spiel_edge.service.doctor import check_numba_cache_dir

    monkeypatch.setattr(config, "CACHE_DIR", str(blocker / "sub"))
    check = check_numba_cache_dir(tmp_path)
    assert not check.ok and "NUMBA_CACHE_DIR" in check.detail, check


def test_a_full_disk_while_saving_leaves_the_kernel_running(tmp_path):
    result = _probe(tmp_path, FSIZE="200")
    assert result["value"] == 41 and result["counts"]["compiled"] == 1
    assert any("not saved" in w for w in result["warnings"])
    assert not _cache_files(tmp_path, "*.tmp.*")  # no half-written file left behind
    assert _probe(tmp_path)["value"] == 41  # and the next start compiles or loads: no crash


STREAM = """
import json, os, sys
import numpy as np
from spiel_edge import _kernel_cache, _shipped
from spiel_edge.protocol import cobs
warnings = []
_kernel_cache.listeners.append(lambda e, n, d: warnings.append(str(d)) if e == "warning" else None)
error = None
try:
    cobs.warm_up()
    payload = np.arange(600, dtype=np.uint16).tobytes()
    assert cobs.decode(cobs.encode(payload)) == payload
except _kernel_cache.CompileNeeded as exc:
    error = str(exc)
print(json.dumps({"status": _shipped.status(), "counts": _kernel_cache.counts, "error": error,
                  "cpu": os.environ.get("NUMBA_CPU_NAME"), "warnings": warnings}))
"""


def _stream(env: dict) -> dict:
    full = {k: v for k, v in os.environ.items() if not k.startswith(("NUMBA_CPU", "SPIEL_EDGE"))}
    out = subprocess.run(
        [sys.executable, "-c", STREAM],
        env={**full, **env},
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_prebuilt_kernels_load_from_a_read_only_folder_with_no_compile(tmp_path):
    from tools.release.build_wheels import manifest

    ship = tmp_path / "ship"
    build = _stream({_shipped.ENV_BUILD: str(ship), "NUMBA_CACHE_DIR": str(tmp_path / "c0")})
    # the stream decoder's kernels: encode, decode, decode_pieces
    assert build["counts"]["compiled"] == 3 and build["cpu"] == "generic"
    assert not list((tmp_path / "c0").rglob("*.nbi"))  # the build writes only the kernels'
    ident = _shipped.identity()
    (ship / "manifest.json").write_text(json.dumps(manifest(ship, ident)))
    for p in ship.rglob("*"):
        p.chmod(0o555 if p.is_dir() else 0o444)
    user = tmp_path / "user"
    env = {
        _shipped.ENV_FOLDER: str(ship),
        "NUMBA_CACHE_DIR": str(user),
        "SPIEL_EDGE_NO_COMPILE": "1",
    }
    run = _stream(env)
    assert run["error"] is None and run["status"]["active"] and run["cpu"] == "generic"
    assert run["counts"] == {"hits": 3, "shipped_hits": 3, "compiled": 0}
    # nothing written: not a kernel, not numba's runtime module (shipped too: no LLVM compile)
    assert list(ship.glob("spiel_edge-nrt-*.nbo"))
    assert not [p for p in user.rglob("*") if p.is_file()]
    # host-tuned kernels asked for: the prebuilt ones are left alone
    host = _stream({**env, _shipped.ENV_HOST: "1"})
    assert not host["status"]["active"] and host["cpu"] is None
    assert host["error"] and "no compiled copy" in host["error"]
    # a damaged prebuilt file: refused against the manifest, so the kernel would compile
    (data, *_) = sorted(ship.rglob("*.nbc"))
    data.chmod(0o644)
    # its last byte flipped (the bytes vary per build: a last byte set to 0 was already 0, the
    # file unchanged, about one build in 256)
    raw = data.read_bytes()
    data.write_bytes(raw[:-1] + bytes([raw[-1] ^ 0xFF]))
    damaged = _stream(env)
    assert damaged["error"] and any("manifest" in w for w in damaged["warnings"])
    # an intact file the manifest does not list: refused too (checked, not trusted)
    data.write_bytes(raw)
    listed = json.loads((ship / "manifest.json").read_text())
    del listed["files"][data.relative_to(ship).as_posix()]
    (ship / "manifest.json").chmod(0o644)
    (ship / "manifest.json").write_text(json.dumps(listed))
    unlisted = _stream(env)
    assert unlisted["error"] and any("manifest" in w for w in unlisted["warnings"])


def test_prebuilt_kernels_for_another_numba_are_not_used(tmp_path):
    ident = {**_shipped.identity(), "numba": "0.1.0"}
    assert "built for numba 0.1.0" in _shipped.mismatch(ident)
    assert _shipped.mismatch(_shipped.identity()) == ""
    (tmp_path / "manifest.json").write_text(json.dumps({**ident, "files": {}}))
    result = _stream(
        {
            _shipped.ENV_FOLDER: str(tmp_path),
            "SPIEL_EDGE_NO_COMPILE": "1",
            "NUMBA_CACHE_DIR": str(tmp_path / "c"),
        }
    )
    assert not result["status"]["active"] and "numba 0.1.0" in result["status"]["reason"]
    assert result["cpu"] is None and result["error"]  # the host's CPU: it would compile


@pytest.mark.parametrize("value", ["", "not json", "[]"])
def test_a_broken_manifest_means_no_prebuilt_kernels(tmp_path, value):
    (tmp_path / "manifest.json").write_text(value)
    code = "import json, spiel_edge._shipped as s; print(json.dumps(s.status()))"
    env = {**os.environ, _shipped.ENV_FOLDER: str(tmp_path)}
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True)
    assert not json.loads(out.stdout)["active"]
