"""The project's numba flags in one place: every kernel is ``@jit``-compiled with them.

Kernels are cached (``cache=True`` in effect) by ``_kernel_layers.KernelCache``: the prebuilt
kernels of a release wheel first, then numba's own cache (beside the sources, or
``NUMBA_CACHE_DIR``, which the service points at a writable folder, or the user's cache
folder), where what compiles is saved; a damaged file or a failed save never stops a kernel.
``nogil=True`` lets a caller run pipelines in threads. Importing this module installs the
lean loading of cached kernels (``_cache_load``): a warm start sets up no compiler.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from spiel_edge import _shipped

_shipped.select_cpu()  # before numba reads NUMBA_CPU_NAME: a wheel's prebuilt kernels

from numba import njit  # noqa: E402

from spiel_edge import _cache_load, _numba_gate, _tiers  # noqa: E402

GATED = _numba_gate.ok()  # numba's internals as tested: the project's cache layers
if GATED:
    from spiel_edge import _kernel_layers

    _cache_load.install()

FLAGS = {"nogil": True}  # and cached: see :func:`jit`


def jit(fn: Callable | None = None, **extra: Any) -> Any:
    """``@jit``, ``@jit(inline="always")`` or ``jit(fn, **options)``: ``numba.njit`` with
    :data:`FLAGS` and ``extra``, cached by :class:`~spiel_edge._kernel_layers.KernelCache`
    (outside numba's tested range: numba's own ``njit(cache=True)``, one warning)."""

    def wrap(py_func: Callable) -> Any:
        if not GATED:
            _numba_gate.warn_once()
            return njit(cache=True, **{**FLAGS, **extra})(py_func)
        dispatcher = njit(**{**FLAGS, **extra})(py_func)
        dispatcher._cache = _kernel_layers.make(py_func)  # what enable_caching() would set
        _tiers.register(dispatcher)  # its interpreted twin, when a tiered start needs one
        return dispatcher

    return wrap if fn is None else wrap(fn)
