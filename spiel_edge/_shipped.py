"""Kernels shipped in a release wheel: where they are, whether they fit, and the CPU they need.

A wheel built by ``tools/release/build_wheels.py`` carries numba's cache files for every kernel
in ``spiel_edge/_kernels/``, compiled for a generic CPU of its architecture (``NUMBA_CPU_NAME=
generic``: no instruction beyond the architecture's baseline), with ``manifest.json`` naming
the Python, machine, numba and llvmlite they were built with and a SHA-256 of every file.

:func:`select_cpu` runs when ``spiel_edge._jit`` is imported, before it imports numba: when
the shipped kernels fit this interpreter it sets ``NUMBA_CPU_NAME=generic``, so numba looks
them up (its cache key holds the CPU name) and compiles whatever is missing for the same CPU.
An sdist or editable install has no ``_kernels/`` and compiles for the host's CPU as before.
``SPIEL_EDGE_HOST_KERNELS=1`` (or a ``NUMBA_CPU_NAME`` of one's own) opts out: kernels are
compiled for this host's CPU into the user's or the service's cache (docs/aarch64.md).

This module imports neither numba nor numpy: it runs at every ``import spiel_edge``.
"""

from __future__ import annotations

import hashlib
import json
import os
import platform
import sys
from pathlib import Path

ENV_HOST = "SPIEL_EDGE_HOST_KERNELS"  # "1": compile for this host's CPU, ignore shipped kernels
ENV_BUILD = "SPIEL_EDGE_KERNELS_OUT"  # release builds: compile every kernel into this folder
ENV_FOLDER = "SPIEL_EDGE_KERNELS_DIR"  # prebuilt kernels elsewhere (a distribution's package)
FOLDER = Path(os.environ.get(ENV_FOLDER) or Path(__file__).resolve().parent / "_kernels")
SOURCE_ROOT = Path(__file__).resolve().parent.parent  # the folder holding spiel_edge/
MANIFEST = "manifest.json"
CPU_NAME = "generic"

_state: dict = {"active": False, "reason": "not checked", "manifest": None}


def select_cpu() -> bool:
    """Choose the generic CPU when shipped kernels fit this process; True when they are used.
    Idempotent; the reason is in :func:`status`."""
    if _state["reason"] != "not checked":
        return _state["active"]
    if os.environ.get(ENV_BUILD):
        os.environ["NUMBA_CPU_NAME"] = CPU_NAME  # the release build compiles for the generic CPU
        return _set(False, "building shipped kernels")
    manifest = _read_manifest()
    if manifest is None:
        return _set(False, "this install carries no prebuilt kernels (sdist or checkout)")
    if os.environ.get(ENV_HOST, "0") not in ("", "0"):
        return _set(False, f"{ENV_HOST} is set: kernels are compiled for this CPU")
    misfit = mismatch(manifest)
    if misfit:
        return _set(False, f"the prebuilt kernels do not fit: {misfit}")
    chosen = os.environ.get("NUMBA_CPU_NAME")
    if chosen is not None and chosen.lower() != CPU_NAME:
        return _set(False, f"NUMBA_CPU_NAME={chosen} is set: kernels are compiled for it")
    if "numba" in sys.modules and chosen is None:
        return _set(False, "numba was imported before spiel_edge._jit: kernels are compiled")
    os.environ["NUMBA_CPU_NAME"] = CPU_NAME
    _state["manifest"] = manifest
    return _set(True, f"prebuilt kernels for a generic {manifest['machine']} CPU")


def status() -> dict:
    """Whether shipped kernels are used, and why (or why not)."""
    return {"active": _state["active"], "reason": _state["reason"], "folder": str(FOLDER)}


def _set(active: bool, reason: str) -> bool:
    _state["active"], _state["reason"] = active, reason
    return active


def _read_manifest() -> dict | None:
    try:
        manifest = json.loads((FOLDER / MANIFEST).read_text())
    except (OSError, ValueError):
        return None
    return manifest if isinstance(manifest, dict) and "files" in manifest else None


def identity() -> dict:
    """What shipped kernels must have been built with to load here."""
    return {
        "python": sys.implementation.cache_tag,
        "machine": platform.machine(),
        "numba": _dist_version("numba"),
        "llvmlite": _dist_version("llvmlite"),
    }


def mismatch(manifest: dict) -> str:
    """'' when ``manifest`` was built for this interpreter, else what differs."""
    here = identity()
    return "; ".join(
        f"built for {key} {manifest.get(key)}, this is {value}"
        for key, value in here.items()
        if manifest.get(key) != value
    )


def _dist_version(name: str) -> str | None:
    from importlib import metadata

    try:
        return metadata.version(name)
    except metadata.PackageNotFoundError:
        return None


def index_folder(py_file: str) -> Path | None:
    """The shipped folder of the kernels defined in ``py_file`` (None: not ours, or none)."""
    if not _state["active"]:
        return None
    return relative_folder(FOLDER, py_file)


def relative_folder(base: Path, py_file: str) -> Path | None:
    """``base`` / the folder of ``py_file`` relative to the folder holding the packages."""
    try:
        return Path(base) / Path(py_file).resolve().parent.relative_to(SOURCE_ROOT)
    except ValueError:
        return None


def file_digest(path: Path) -> str | None:
    """The manifest's SHA-256 of a shipped file (None when the manifest does not list it)."""
    manifest = _state["manifest"] or {}
    try:
        return manifest["files"].get(path.relative_to(FOLDER).as_posix())
    except ValueError:
        return None


def sha256(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()
