"""A first start known without importing numba: no compiled copy of any kernel anywhere.

To find out that a kernel must compile, a command imports numba and the pipeline and asks the
kernel cache (``first_start.prepare_for_run``): about a second on a quiet core, several on a
loaded Pi, all of it silent. Before that, :func:`say_if_cold` looks for the index file of the
first kernel every streaming command needs (the stream decoder's COBS encoder) where numba
would read it (``NUMBA_CACHE_DIR``, else beside the source when that is writable, else the
user's cache; a release wheel's prebuilt kernels are the cache's to judge). When it is not
there, no kernel was ever compiled into this cache, and the command says so at once; the
details (how many, about how long) follow from the kernel cache. When one is found, nothing is said here: whether it still fits (numba's
version, the source's hash) only the cache can tell.

This module imports neither numba nor numpy.
"""

from __future__ import annotations

import hashlib
import os
import sys
from pathlib import Path
from typing import TextIO

from spiel_edge import _shipped

PROBE_SOURCE = Path(__file__).resolve().parents[1] / "protocol" / "_cobs_numba.py"
PROBE_PATTERN = "_cobs_numba.encode-*.nbi"  # numba's index file: <qualname>-<line>.pyXY.nbi
TIERED = ("run", "replay", "evaluate", "calibrate")  # a tiered start (runtime/tiered.py)
WHAT_WAITS = {"run": "the board is opened", "replay": "the first file is read"}


def _numba_subpath(source: Path) -> str:
    """numba's folder name for a source inside a cache root (caching._CacheLocator)."""
    folder = os.path.dirname(os.path.abspath(source))
    return "_".join([os.path.split(folder)[-1], hashlib.sha1(folder.encode()).hexdigest()])


def _writable(folder: Path) -> bool:
    probe = folder if folder.exists() else folder.parent
    return os.access(probe, os.W_OK | os.X_OK)


def probe_folders(source: Path = PROBE_SOURCE) -> list[Path]:
    """The folder numba's locators would read the probe kernel from: the first that applies
    (NUMBA_CACHE_DIR; else beside the source when writable; else the user's cache)."""
    subpath = _numba_subpath(source)
    if os.environ.get("NUMBA_CACHE_DIR"):
        return [Path(os.environ["NUMBA_CACHE_DIR"]) / subpath]
    in_tree = source.parent / "__pycache__"
    if _writable(in_tree):
        return [in_tree]
    xdg = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return [Path(xdg) / "numba" / subpath]


def has_no_kernels(source: Path = PROBE_SOURCE, pattern: str = PROBE_PATTERN) -> bool:
    """True when no cache this process could read holds the probe kernel at all."""
    _shipped.select_cpu()
    if _shipped.status()["active"]:
        return False  # a release wheel's prebuilt kernels: the cache decides
    for folder in probe_folders(source):
        try:
            if any(folder.glob(pattern)):
                return False
        except OSError:
            continue  # an unreadable folder holds nothing this process can load
    return True


def say_if_cold(command: str, stream: TextIO | None = None) -> bool:
    """Say at once that kernels must compile when no cache holds any; True if it said so."""
    if not has_no_kernels():
        return False
    stream = stream or sys.stderr
    tiered = command in TIERED and os.environ.get("SPIEL_EDGE_TIERED", "1") != "0"
    then = (
        "they compile in the background while the interpreted ones run"
        if tiered
        else f"they compile now, before {WHAT_WAITS.get(command, 'it starts')}"
    )
    print(
        f"spiel-edge {command}: no compiled kernels in the cache ({probe_folders()[0].parent}): "
        f"{then}; counting them...",
        file=stream,
        flush=True,
    )
    return True
