"""numba's cache for this project's kernels, in two layers and never a crash.

This module holds what needs no numba internal (compile reports, the "not compiled" probe,
the cache folder's check); the numba subclasses are in ``spiel_edge._kernel_layers``,
imported only when ``spiel_edge._numba_gate`` passes. Each ``spiel_edge._jit.jit`` kernel (and
the stream decoder's) gets a ``_kernel_layers.KernelCache``, a
``numba.core.caching.FunctionCache`` that

- looks a kernel up first in the prebuilt kernels of a release wheel (``spiel_edge/_kernels``,
  read-only, each file checked against the manifest's SHA-256 before numba reads it:
  ``spiel_edge._shipped``), then in numba's own cache (beside the sources, NUMBA_CACHE_DIR or
  the user's cache folder), where it saves what it compiles;
- seals every file it writes with a SHA-256 of its content and checks it before numba reads
  it: a flipped bit in a kernel's machine code would otherwise run (SIGILL, SIGSEGV);
- treats an unreadable, damaged or foreign cache file as a miss (the kernel compiles; numba
  itself would raise), and a failed save (read-only folder, full disk) as a warning (the
  kernel runs from memory; numba would raise); a file written without a seal (by numba
  itself, or before seals) is a miss without a warning;
- works without any writable folder (numba raises at import): kernels compile each start,
  said once;
- tells :data:`listeners` when a kernel starts and ends compiling (``spiel_edge.runtime.
  compile_progress`` shows it).

Cache keys are numba's: the signature, the CPU name and features, the bytecode's hash; the
index carries numba's version and the source file's hash, so a kernel whose source or numba
changed compiles again, wherever its files come from.
"""

from __future__ import annotations

import contextlib
import functools
import logging
import os
import tempfile
from collections.abc import Callable

from spiel_edge.errors import SpielError

log = logging.getLogger(__name__)

# listeners(event, name, detail): event "compile" (detail: the signature) before a kernel
# compiles, "compiled" (detail: seconds) after; "warning" (detail: the message) once per cause
listeners: list[Callable[[str, str, object], None]] = []
_warned: set[str] = set()
counts = {"hits": 0, "shipped_hits": 0, "compiled": 0}
ENV_FORBID = "SPIEL_EDGE_NO_COMPILE"  # "1": a kernel missing from every cache is an error
forbid = {"on": False}


class CompileNeeded(SpielError):
    """A kernel has no compiled copy in any cache, where compiling was not allowed."""

    def __init__(self, name: str) -> None:
        super().__init__(f"kernel {name} has no compiled copy for this CPU in any cache")
        self.name = name


@contextlib.contextmanager
def no_compile():
    """Within: a kernel that would compile raises :class:`CompileNeeded` instead (the caller
    finds out cheaply whether everything is cached, and compiles elsewhere if not)."""
    before, forbid["on"] = forbid["on"], True
    try:
        yield
    finally:
        forbid["on"] = before


def emit(event: str, name: str, detail: object) -> None:
    for listener in list(listeners):
        try:
            listener(event, name, detail)
        except Exception as exc:  # a display must never stop a compilation
            log.debug("compile listener failed: %s", exc)


def warn_once(key: str, message: str) -> None:
    if key in _warned:
        return
    _warned.add(key)
    # a display listening (compile progress, a warm-up child's relay) says it: once, not again
    # through the log
    (log.debug if listeners else log.warning)("%s", message)
    emit("warning", key, message)


def cache_dir_problem() -> str | None:
    """Why NUMBA_CACHE_DIR, when set, is not a folder numba can keep kernels in (numba then
    falls back to the sources' __pycache__ without a word); None when it is, or is not set."""
    from numba.core import config

    folder = config.CACHE_DIR
    if not folder:
        return None
    try:
        os.makedirs(folder, exist_ok=True)
        with tempfile.TemporaryFile(dir=folder):
            pass
    except OSError as exc:
        reason = exc.strerror or type(exc).__name__
        return f"NUMBA_CACHE_DIR {folder} is not a folder this user can write ({reason})"
    return None


@functools.cache
def cache_dir_problem_once() -> str | None:
    """:func:`cache_dir_problem`, looked at once per process (not per kernel)."""
    return cache_dir_problem()
