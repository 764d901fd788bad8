"""The one list of numba's internals this project relies on, checked once at import.

Two layers reach below numba's public API: the kernel cache (``_kernel_cache`` and its numba
subclasses in ``_kernel_layers``: prebuilt kernels, sealed cache files, compile reports, the
"not compiled" probe of a tiered start) and the lean loading of cached kernels
(``_cache_load``). Both were checked against :data:`TESTED` (tests/core/test_numba_gate.py
runs the suite's kernel-cache tests on the installed versions). :func:`problem` says what is
off: another numba or llvmlite version, or any name of :data:`RELIED_ON` missing or renamed.
Then both layers stand aside: ``spiel_edge._jit`` decorates every kernel with numba's own
``njit(cache=True)`` (numba's cache, its own loading; no prebuilt kernels, no tiered start),
and one warning says why. ``SPIEL_EDGE_NUMBA_GATE=off`` forces that fallback (tests).

This module imports numba only inside :func:`problem`.
"""

from __future__ import annotations

import functools
import importlib
import logging
import os

log = logging.getLogger(__name__)

ENV = "SPIEL_EDGE_NUMBA_GATE"  # "off": numba's own njit(cache=True), as if a check failed
TESTED = {"numba": ((0, 68),), "llvmlite": ((0, 50),)}  # (major, minor) pairs CI runs

# (module, dotted attribute): classes and functions, looked up on the module
_CACHING = "numba.core.caching"
_CODEGEN = "numba.core.codegen"
RELIED_ON: tuple[tuple[str, str], ...] = (
    # the kernel cache: numba's cache classes it subclasses and the members it uses
    (_CACHING, "FunctionCache"),
    (_CACHING, "FunctionCache._index_key"),
    (_CACHING, "FunctionCache._load_overload"),
    (_CACHING, "FunctionCache._save_overload"),
    (_CACHING, "FunctionCache.save_overload"),
    (_CACHING, "FunctionCache.load_overload"),
    (_CACHING, "FunctionCache._guard_against_spurious_io_errors"),
    (_CACHING, "_CacheLocator"),
    (_CACHING, "_CacheLocator.ensure_cache_path"),
    (_CACHING, "_CacheLocator.get_source_stamp"),
    (_CACHING, "_SourceFileBackedLocatorMixin"),
    (_CACHING, "CacheImpl._locator_classes"),
    (_CACHING, "CompileResultCacheImpl"),
    (_CACHING, "CompileResultCacheImpl.rebuild"),
    (_CACHING, "IndexDataCacheFile"),
    (_CACHING, "IndexDataCacheFile._load_index"),
    (_CACHING, "IndexDataCacheFile._save_index"),
    (_CACHING, "IndexDataCacheFile._load_data"),
    (_CACHING, "IndexDataCacheFile._save_data"),
    (_CACHING, "IndexDataCacheFile._dump"),
    (_CACHING, "IndexDataCacheFile._open_for_write"),
    (_CACHING, "IndexDataCacheFile._data_path"),
    (_CACHING, "IndexDataCacheFile.flush"),
    (_CACHING, "IndexDataCacheFile.load"),
    (_CACHING, "NullCache"),
    ("numba.core.config", "CACHE_DIR"),
    ("numba.core.registry", "cpu_target"),
    ("numba.core.types", "Omitted"),
    # the lean loading of cached kernels
    ("numba.core.runtime.nrt", "rtsys.initialize"),
    ("numba.core.runtime.nrtdynmod", "compile_nrt_functions"),
    ("numba.core.runtime.nrtdynmod", "create_nrt_module"),
    (_CODEGEN, "JITCPUCodegen.unserialize_library"),
    (_CODEGEN, "JITCPUCodegen.magic_tuple"),
    (_CODEGEN, "JITCPUCodegen.create_library"),
    (_CODEGEN, "JITCodeLibrary._set_compiled_object"),
    (_CODEGEN, "JITCodeLibrary._finalize_final_module"),
    (_CODEGEN, "JITCodeLibrary._ensure_finalized"),
    (_CODEGEN, "JITCodeLibrary.serialize_using_object_code"),
    (_CODEGEN, "JITCodeLibrary.enable_object_caching"),
    (_CODEGEN, "JITCodeLibrary.add_ir_module"),
    (_CODEGEN, "JITCodeLibrary.get_pointer_to_function"),
    (_CODEGEN, "JitEngine._load_defined_symbols"),
    (_CODEGEN, "JitEngine.get_function_address"),
    ("numba.core.cpu", "CPUContext.refresh"),
)
# attributes numba sets on instances (looked up on a probe object, see _instance_problem)
INSTANCE = {
    "FunctionCache": ("_impl", "_cache_path", "_cache_file", "_enabled", "_py_func"),
    "FunctionCache._impl": ("filename_base", "locator"),
    "IndexDataCacheFile": ("_index_path", "_version", "_source_stamp"),
    "Dispatcher": ("py_func", "targetoptions", "stats", "typeof_pyval", "compile", "_cache"),
}


def _version(text: str) -> tuple[int, int]:
    try:
        major, minor = text.split(".")[:2]
        return int(major), int(minor)
    except ValueError:
        return (0, 0)


def _lookup(module_name: str, dotted: str) -> None:
    obj = importlib.import_module(module_name)
    for part in dotted.split("."):
        obj = getattr(obj, part)


def _probe() -> None:  # not a kernel: the object the instance checks look at
    """A function for the probe objects of :func:`_instance_problem`."""


def _instance_problem() -> str:
    from numba import njit
    from numba.core import caching

    cache = caching.FunctionCache(_probe)
    objects = {
        "FunctionCache": cache,
        "FunctionCache._impl": cache._impl,
        "IndexDataCacheFile": cache._cache_file,
        "Dispatcher": njit(_probe),  # decorating compiles nothing
    }
    for owner, names in INSTANCE.items():
        for name in names:
            if not hasattr(objects[owner], name):
                return f"{owner} instances have no {name}"
    return ""


@functools.cache
def problem() -> str:
    """'' when the installed numba and llvmlite are the tested versions and have every
    internal relied on; else what is not (the first found)."""
    if os.environ.get(ENV, "") == "off":
        return f"{ENV}=off"
    from importlib import metadata

    for dist, tested in TESTED.items():
        try:
            version = metadata.version(dist)
        except metadata.PackageNotFoundError:
            return f"{dist} is not installed"
        if _version(version) not in tested:
            checked = ", ".join(f"{a}.{b}" for a, b in tested)
            return f"{dist} {version} is outside the tested range ({checked})"
    for module_name, dotted in RELIED_ON:
        try:
            _lookup(module_name, dotted)
        except (ImportError, AttributeError):
            return f"numba has no {module_name}.{dotted}"
    try:
        return _instance_problem()
    except Exception as exc:  # a constructor that changed: as good as a rename
        return f"numba's cache classes changed ({type(exc).__name__}: {exc})"


def ok() -> bool:
    return not problem()


@functools.cache
def warn_once() -> None:
    """The one warning of the fallback (said when the first kernel is decorated)."""
    log.warning(
        "%s: kernels use numba's own cache (njit(cache=True)): no prebuilt kernels, no "
        "sealed cache files, no tiered start (docs/first-start.md, 'numba versions')",
        problem(),
    )
