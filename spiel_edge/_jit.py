"""The project's numba flags in one place: every kernel is ``@jit``-compiled with them.

``cache=True`` writes compiled kernels next to the sources or to ``NUMBA_CACHE_DIR`` (the
service points that at a writable folder, so a read-only install still starts warm);
``nogil=True`` lets a caller run pipelines in threads. Importing this module installs the
lean loading of cached kernels (``_cache_load``): a warm start sets up no compiler.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from numba import njit

from spiel_edge import _cache_load

_cache_load.install()

FLAGS = {"cache": True, "nogil": True}


def jit(fn: Callable | None = None, **extra: Any) -> Any:
    """``@jit`` or ``@jit(inline="always")``: ``numba.njit`` with :data:`FLAGS`."""
    if fn is None:
        return njit(**FLAGS, **extra)
    return njit(**FLAGS)(fn)
