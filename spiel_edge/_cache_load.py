"""Start the project's kernels from numba's cache without setting up numba's compiler.

When every kernel comes from the cache, numba 0.68 still pays at the first kernel call for
three things only a compilation needs (docs/performance.md, "Fifth session"):

- ``FunctionCache.load_overload`` refreshes the target context, which imports and registers
  every lowering registry (numba.np.arraymath, linalg, the typed containers, ...);
- the runtime (NRT) compiles its small LLVM module of atomic reference counts, which brings
  LLVM's optimiser and code generator into the process;
- each loaded library parses the LLVM bitcode kept for linking it into other functions.

:func:`install` makes a cache hit of this project's kernels (``spiel_edge.*`` and
``spiel_edge.protocol.*``) initialise only the runtime before loading, keeps the runtime's
machine code in numba's cache folder beside the kernels, keyed like numba's own entries (CPU
name and features, versions), and defers each library's bitcode until something links it,
so a warm start runs no LLVM pass at all. A cache miss compiles exactly as before: numba's
compiler refreshes the context itself, and every deferred bitcode is parsed first. Other
packages' cached functions keep numba's own path. Another numba version, a damaged or
foreign runtime file, or ``SPIEL_EDGE_NUMBA_LEAN=0`` fall back to numba's own behaviour.
"""

from __future__ import annotations

import hashlib
import logging
import os
import struct
import sys
import tempfile
import weakref
from pathlib import Path

from spiel_edge import _numba_gate, _shipped

log = logging.getLogger(__name__)

ENV_SWITCH = "SPIEL_EDGE_NUMBA_LEAN"
# the numba and llvmlite versions checked, and the internals replaced below: spiel_edge.
# _numba_gate (one list for both layers); another version or a missing name loads cached
# kernels numba's own way
SUPPORTED = _numba_gate.TESTED["numba"]
SUPPORTED_LLVMLITE = _numba_gate.TESTED["llvmlite"]
OWN_MODULES = ("spiel_edge.",)
RUNTIME_MAGIC = b"spiel-edge nrt 1\n"

_state = {"installed": False, "folder": None, "loading": False}


def install() -> bool:
    """Patch numba's cache loading once per process; True when the lean path is active."""
    if _state["installed"]:
        return True
    if os.environ.get(ENV_SWITCH, "1") == "0":
        return False
    try:
        from numba.core import caching
        from numba.core.runtime import nrt, nrtdynmod
    except ImportError:
        return False
    reason = unsupported()
    if reason:
        log.debug("%s: cached kernels load numba's own way", reason)
        return False
    stock_load = caching.FunctionCache.load_overload

    def load_overload(cache, sig, target_context):
        if not getattr(cache._py_func, "__module__", "").startswith(OWN_MODULES):
            return stock_load(cache, sig, target_context)
        if _state["folder"] is None:
            _state["folder"] = runtime_folder(caching.FunctionCache) or False  # False: none
        nrt.rtsys.initialize(target_context)
        _state["loading"] = True  # under numba's compiler lock: one load at a time
        try:
            with cache._guard_against_spurious_io_errors():
                return cache._load_overload(sig, target_context)
        finally:
            _state["loading"] = False

    stock_compile = nrtdynmod.compile_nrt_functions

    def compile_nrt_functions(ctx):
        folder = _state["folder"]
        shipped = _shipped_runtime(ctx.codegen())
        if not folder and shipped is None and not os.environ.get(_shipped.ENV_BUILD):
            return stock_compile(ctx)
        return _runtime_library(ctx, folder or None, nrtdynmod.create_nrt_module, shipped)

    caching.FunctionCache.load_overload = load_overload
    nrtdynmod.compile_nrt_functions = compile_nrt_functions
    _defer_linking_bitcode()
    _state["installed"] = True
    return True


def unsupported() -> str:
    """'' when the installed numba and llvmlite are the versions this module was checked
    against and have every internal it replaces (``_numba_gate.problem``), else what is not."""
    return _numba_gate.problem()


def _defer_linking_bitcode() -> None:
    """A cached kernel's library holds machine code and the LLVM bitcode other functions
    would link; numba parses that bitcode at every load (tens of ms and MiB per kernel) though
    only a compilation in this process reads it. Libraries loaded by :func:`install`'s path
    parse it on first use instead, and all of them before any compilation starts (numba
    refreshes its context first), so a compiling process sees numba's own state."""
    import llvmlite.binding as ll
    from numba.core import codegen, cpu

    class LazyBitcodeLibrary(codegen.JITCodeLibrary):
        _bitcode = None
        _parsed = None

        @property
        def _shared_module(self):
            self.materialize()
            return self._parsed

        @_shared_module.setter
        def _shared_module(self, module):
            self._parsed = module

        def materialize(self) -> None:
            if self._bitcode is not None:
                bitcode, self._bitcode = self._bitcode, None
                self._parsed = ll.parse_bitcode(bitcode)
                self._codegen._engine._load_defined_symbols(self._parsed)

        def get_pointer_to_function(self, name):
            if self._bitcode is None:
                return super().get_pointer_to_function(name)
            self._ensure_finalized()  # the entry points numba asks for are in the machine code
            return self._codegen._engine.get_function_address(name)

    pending = weakref.WeakSet()
    stock_unserialize = codegen.JITCPUCodegen.unserialize_library
    stock_refresh = cpu.CPUContext.refresh

    def unserialize_library(generator, serialized):
        name, kind, data = serialized
        if not _state["loading"] or kind != "object":
            return stock_unserialize(generator, serialized)
        object_code, bitcode = data
        library = LazyBitcodeLibrary(generator, name)
        library.enable_object_caching()
        library._set_compiled_object(object_code)
        library._bitcode = bitcode
        library._finalize_final_module()
        pending.add(library)
        return library

    def refresh(context):
        for library in list(pending):
            library.materialize()
        pending.clear()
        return stock_refresh(context)

    codegen.JITCPUCodegen.unserialize_library = unserialize_library
    cpu.CPUContext.refresh = refresh


def _version(text: str) -> tuple[int, int]:
    try:
        major, minor = text.split(".")[:2]
        return int(major), int(minor)
    except ValueError:
        return (0, 0)


def _anchor() -> None:
    """Not a kernel: numba's cache locator places the runtime file as it would place a kernel
    of this module (beside the package, in NUMBA_CACHE_DIR or in the user's cache)."""


def runtime_folder(function_cache) -> Path | None:
    try:
        return Path(function_cache(_anchor)._cache_path)
    except Exception as exc:  # no usable cache location: numba raises RuntimeError
        log.debug("no folder for the numba runtime cache: %s", exc)
        return None


def runtime_file(folder: Path, codegen) -> Path:
    """The runtime's cache file for this CPU, numba, llvmlite and Python."""
    import llvmlite
    import numba

    key = repr((codegen.magic_tuple(), numba.__version__, llvmlite.__version__, sys.version))
    return folder / f"spiel_edge-nrt-{hashlib.sha256(key.encode()).hexdigest()[:16]}.nbo"


def shipped_runtime_name(codegen) -> str:
    """The runtime's file among a wheel's prebuilt kernels: keyed by CPU, numba, llvmlite and
    the Python ABI (not the exact interpreter build, as :func:`runtime_file` is)."""
    import llvmlite
    import numba

    key = repr((codegen.magic_tuple(), numba.__version__, llvmlite.__version__))
    key += sys.implementation.cache_tag
    return f"spiel_edge-nrt-{hashlib.sha256(key.encode()).hexdigest()[:16]}.nbo"


def _shipped_runtime(codegen) -> Path | None:
    if not _shipped.status()["active"]:
        return None
    return _shipped.FOLDER / shipped_runtime_name(codegen)


def _runtime_library(ctx, folder: Path | None, create_module, shipped: Path | None = None):
    """The NRT library from the wheel's prebuilt kernels or ``folder`` when there and intact,
    else compiled and saved (a release build also keeps it beside the kernels it builds)."""
    codegen = ctx.codegen()
    path = runtime_file(folder, codegen) if folder else None
    for candidate in (shipped, path):
        if candidate is None:
            continue
        try:
            blob = candidate.read_bytes()
            if candidate == shipped and _shipped.file_digest(candidate) != _shipped.sha256(blob):
                raise ValueError("not the file the wheel's manifest lists")
            parts = _unpack(blob)
            library = codegen.unserialize_library((parts[0].decode(), "object", parts[1:]))
            log.debug("numba runtime loaded from %s", candidate)
            _keep_for_release(codegen, blob)
            return library
        except FileNotFoundError:
            continue
        except Exception as exc:  # a damaged or foreign file: compile as numba would
            log.debug("numba runtime cache %s unusable (%s)", candidate, exc)
    made = create_module(ctx)
    ir_module, library = made if isinstance(made, tuple) else (made, None)
    library = library or codegen.create_library("nrt")
    library.enable_object_caching()
    library.add_ir_module(ir_module)
    library.finalize()
    name, _kind, (object_code, bitcode) = library.serialize_using_object_code()
    blob = _pack((name.encode(), object_code, bitcode))
    if path is not None:
        _save(path, blob)
    _keep_for_release(codegen, blob)
    return library


def _keep_for_release(codegen, blob: bytes) -> None:
    out = os.environ.get(_shipped.ENV_BUILD)
    if out:
        target = Path(out) / shipped_runtime_name(codegen)
        if not target.exists():
            target.parent.mkdir(parents=True, exist_ok=True)
            _save(target, blob)


def _pack(parts: tuple[bytes, ...]) -> bytes:
    body = b"".join(struct.pack("<Q", len(p)) + p for p in parts)
    return RUNTIME_MAGIC + hashlib.sha256(body).digest() + body


def _unpack(blob: bytes) -> tuple[bytes, ...]:
    """The parts of a :func:`_pack` blob; ValueError when it is not one, whole."""
    head = len(RUNTIME_MAGIC)
    if blob[:head] != RUNTIME_MAGIC:
        raise ValueError("not a runtime cache file")
    digest, body = blob[head : head + 32], blob[head + 32 :]
    if hashlib.sha256(body).digest() != digest:
        raise ValueError("checksum mismatch")
    parts, at = [], 0
    while at < len(body):
        (size,) = struct.unpack_from("<Q", body, at)
        parts.append(bytes(body[at + 8 : at + 8 + size]))
        at += 8 + size
    if len(parts) != 3:
        raise ValueError("wrong number of parts")
    return tuple(parts)


def _save(path: Path, blob: bytes) -> None:
    """Write beside, then rename: readers see the whole file or none (a read-only cache
    folder only costs the next start its compile)."""
    tmp = None
    try:
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=path.name, suffix=".tmp")
        with os.fdopen(fd, "wb") as fh:
            fh.write(blob)
        os.chmod(tmp, 0o644)  # as numba's own cache files: a service user reads what root wrote
        os.replace(tmp, path)
    except OSError as exc:
        log.debug("numba runtime cache not written to %s: %s", path, exc)
        if tmp is not None:
            Path(tmp).unlink(missing_ok=True)
