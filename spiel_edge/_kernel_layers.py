"""The numba subclasses of the kernel cache (``spiel_edge._kernel_cache`` describes them):
imported only when ``spiel_edge._numba_gate`` found every numba internal they rely on."""

from __future__ import annotations

import hashlib
import inspect
import io
import os
import pickle
import time
from pathlib import Path

from numba.core import caching

from spiel_edge import _shipped
from spiel_edge._kernel_cache import (
    ENV_FORBID,
    CompileNeeded,
    cache_dir_problem_once,
    counts,
    emit,
    forbid,
    log,
    warn_once,
)


class _NowhereLocator(caching._SourceFileBackedLocatorMixin, caching._CacheLocator):
    """The last resort when no folder is writable: nothing is saved, lookups find nothing."""

    def __init__(self, py_func, py_file):
        self._py_file = py_file
        self._lineno = py_func.__code__.co_firstlineno

    def ensure_cache_path(self):
        raise OSError("no writable folder for numba's cache")

    def get_cache_path(self):
        return str(Path(self._py_file).parent / "__pycache__")

    def get_disambiguator(self):
        return str(self._lineno)

    @classmethod
    def from_function(cls, py_func, py_file):
        return cls(py_func, py_file) if os.path.exists(py_file) else None


class _BuildLocator(caching._SourceFileBackedLocatorMixin, caching._CacheLocator):
    """Release builds: every kernel's files under ``$SPIEL_EDGE_KERNELS_OUT``, laid out as the
    packages (the layout ``_shipped.index_folder`` reads)."""

    def __init__(self, py_func, py_file, folder: Path):
        self._py_file = py_file
        self._lineno = py_func.__code__.co_firstlineno
        self._folder = folder

    def get_cache_path(self):
        return str(self._folder)

    def get_disambiguator(self):
        return str(self._lineno)

    @classmethod
    def from_function(cls, py_func, py_file):
        out = os.environ.get(_shipped.ENV_BUILD)
        folder = _shipped.relative_folder(Path(out), py_file) if out else None
        if folder is None:
            return None
        self = cls(py_func, py_file, folder)
        self.ensure_cache_path()  # the release build must be able to write: raise if not
        return self


class _Impl(caching.CompileResultCacheImpl):
    _locator_classes = [_BuildLocator, *caching.CacheImpl._locator_classes, _NowhereLocator]


SEAL_TAG = b"\nspiel-edge sha256:"  # a cache file ends with this and the SHA-256 of what precedes


def _seal(body: bytes) -> bytes:
    return body + SEAL_TAG + hashlib.sha256(body).digest()


class _Unsealed(Exception):
    """A cache file without a seal: written by numba itself or an older spiel-edge."""


def _unseal(data: bytes, path: str) -> bytes:
    """What a sealed file holds; _Unsealed without a seal, ValueError when damaged."""
    n = len(SEAL_TAG) + 32
    if len(data) < n or data[-n:-32] != SEAL_TAG:
        raise _Unsealed(path)
    body = data[:-n]
    if hashlib.sha256(body).digest() != data[-32:]:
        raise ValueError(f"{path} is damaged (its SHA-256 does not match its content)")
    return body


class _SealedIndex(caching.IndexDataCacheFile):
    """numba's index and data files, each sealed with its SHA-256 when written and checked
    before it is unpickled; an unsealed index is an empty one (its kernels compile again)."""

    def _read(self, path: str) -> bytes:
        with open(path, "rb") as fh:
            return _unseal(fh.read(), path)

    def _load_index(self):
        try:
            stream = io.BytesIO(self._read(self._index_path))
        except (FileNotFoundError, _Unsealed):
            return {}
        if pickle.load(stream) != self._version:
            return {}
        stamp, overloads = pickle.loads(stream.read())
        return overloads if stamp == self._source_stamp else {}

    def _save_index(self, overloads):
        body = pickle.dumps(self._version, protocol=-1)
        body += self._dump((self._source_stamp, overloads))
        with self._open_for_write(self._index_path) as fh:
            fh.write(_seal(body))

    def _load_data(self, name):
        return pickle.loads(self._read(self._data_path(name)))

    def _save_data(self, name, data):
        with self._open_for_write(self._data_path(name)) as fh:
            fh.write(_seal(self._dump(data)))


class _ShippedIndex(caching.IndexDataCacheFile):
    """numba's index and data files, read-only, each checked against the wheel's manifest."""

    def _checked_bytes(self, path: str) -> bytes:
        with open(path, "rb") as fh:
            data = fh.read()
        want = _shipped.file_digest(Path(path))
        if want is None or _shipped.sha256(data) != want:
            raise ValueError(f"{path} does not match the wheel's manifest")
        return data

    def _load_index(self):
        try:
            data = self._checked_bytes(self._index_path)
        except FileNotFoundError:
            return {}
        stream = io.BytesIO(data)
        if pickle.load(stream) != self._version:
            return {}
        stamp, overloads = pickle.loads(stream.read())
        return overloads if stamp == self._source_stamp else {}

    def _load_data(self, name):
        return pickle.loads(self._checked_bytes(self._data_path(name)))

    def save(self, key, data):  # pragma: no cover - never called: shipped files are read-only
        raise OSError("the shipped kernels are read-only")


class KernelCache(caching.FunctionCache):
    _impl_class = _Impl

    def __init__(self, py_func):
        super().__init__(py_func)
        self._cache_file = _SealedIndex(
            cache_path=self._cache_path,
            filename_base=self._impl.filename_base,
            source_stamp=self._impl.locator.get_source_stamp(),
        )
        self._name = f"{py_func.__module__}.{py_func.__qualname__}"
        self.writable = not isinstance(self._impl.locator, _NowhereLocator)
        if self.writable and (problem := cache_dir_problem_once()):
            warn_once("cache-dir", f"{problem}: compiled kernels are kept in {self._cache_path}")
        shipped = _shipped.index_folder(inspect.getfile(py_func))
        self._shipped = None
        if shipped is not None and not os.environ.get(_shipped.ENV_BUILD):
            self._shipped = _ShippedIndex(
                cache_path=str(shipped),
                filename_base=self._impl.filename_base,
                source_stamp=self._impl.locator.get_source_stamp(),
            )
        self._started: dict = {}

    def has_copy(self, codegen) -> bool:
        """Whether some layer holds this kernel compiled for ``codegen``'s CPU from this
        bytecode (any signature)."""
        _sig, magic, code = self._index_key(None, codegen)
        for layer in (self._shipped, self._cache_file):
            try:
                index = layer._load_index() if layer is not None else {}
            except Exception:  # damaged: as good as absent
                continue
            if any(key[1] == magic and key[2] == code for key in index):
                return True
        return False

    def _load_overload(self, sig, target_context):
        if not self._enabled:
            return None
        key = self._index_key(sig, target_context.codegen())
        for layer, shipped in ((self._shipped, True), (self._cache_file, False)):
            if layer is None:
                continue
            try:
                data = layer.load(key)
                if data is not None:
                    result = self._impl.rebuild(target_context, data)
                    counts["hits"] += 1
                    counts["shipped_hits"] += shipped
                    return result
            except Exception as exc:  # a damaged or foreign file: compile instead
                if forbid["on"]:
                    continue  # a probe: whoever compiles it next says why
                where = "prebuilt kernel" if shipped else "cached kernel"
                warn_once(
                    f"load:{layer._index_path}",
                    f"{where} {self._name} unusable ({type(exc).__name__}: {exc}): compiling it",
                )
        if forbid["on"] or os.environ.get(ENV_FORBID, "0") not in ("", "0"):
            raise CompileNeeded(self._name)
        if not self.writable:
            warn_once(
                "nowhere",
                "no writable folder for compiled kernels: kernels compiled now are not kept "
                "(set NUMBA_CACHE_DIR to a folder this user can write)",
            )
        self._started[sig] = time.perf_counter()
        emit("compile", self._name, sig)
        return None

    def _save_or_renew(self, sig, data) -> None:
        """numba's save; an index it cannot read (damaged) is started afresh first."""
        try:
            self._save_overload(sig, data)
        except OSError:
            raise
        except Exception as exc:
            log.debug("cache index of %s unreadable (%s): starting it afresh", self._name, exc)
            self._cache_file.flush()
            self._save_overload(sig, data)

    def save_overload(self, sig, data):
        started = self._started.pop(sig, None)
        counts["compiled"] += 1
        try:
            if self.writable:
                self._save_or_renew(sig, data)
        except Exception as exc:  # read-only folder, full disk: the kernel runs from memory
            warn_once(
                f"save:{self._cache_path}",
                f"compiled kernel {self._name} not saved to {self._cache_path} "
                f"({type(exc).__name__}: {exc}): it compiles again next start",
            )
        seconds = time.perf_counter() - started if started is not None else 0.0
        emit("compiled", self._name, seconds)


def make(py_func) -> caching._Cache:
    """A :class:`KernelCache` for ``py_func``, or numba's no-op cache when numba finds no
    locator at all (NUMBA_CACHE_LOCATOR_CLASSES naming none that fits)."""
    try:
        return KernelCache(py_func)
    except RuntimeError as exc:
        warn_once("nocache", f"kernels are not cached: {exc}")
        return caching.NullCache()
