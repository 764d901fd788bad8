"""The file rules every command follows (docs/reliability.md), checked before the work starts.

* no command overwrites a file it did not create in this run unless asked (``--force``), and
  never one of its own inputs; two outputs on one path are refused;
* an output's folder must exist and be writable before anything is computed or captured;
* only regular files are read (a FIFO, a device or a folder where a file is expected is an
  error, never a hang);
* small outputs are written to a temporary file beside the target and renamed into place, so
  a failure or a signal never leaves half a file where a good one was.
"""

from __future__ import annotations

import contextlib
import errno
import os
import re
import stat
import tempfile
import threading
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import IO

try:
    import fcntl
except ImportError:  # pragma: no cover - not a POSIX host
    fcntl = None  # type: ignore[assignment]

from spiel_edge.errors import ConfigError, InputError

STDIO = "-"
MAX_SHOWN = 80  # characters of user-supplied text echoed into a message


# control characters, lone surrogates (bytes that were not UTF-8), line and paragraph
# separators and the bidirectional overrides that make a name read differently than it is
_UNPRINTABLE = re.compile(
    r"[\x00-\x1f\x7f-\x9f\ud800-\udfff\u2028\u2029\u200e\u200f\u202a-\u202e\u2066-\u2069]"
)


def _escape_char(match: re.Match) -> str:
    char = match.group()
    code = ord(char)
    if 0xDC80 <= code <= 0xDCFF:  # a byte that was not UTF-8 (os.fsdecode's surrogateescape)
        return f"\\x{code - 0xDC00:02x}"
    return {"\n": "\\n", "\r": "\\r", "\t": "\\t"}.get(char) or (
        f"\\x{code:02x}" if code < 0x100 else f"\\u{code:04x}"
    )


def escape(text: object) -> str:
    """``text`` safe for one line of a terminal: control characters (a newline, an escape
    sequence from a board), bytes that were not UTF-8 in a file name and lone surrogates are
    shown as ``\\n``, ``\\x1b``, ``\\xff``."""
    text = text.decode("utf-8", "surrogateescape") if isinstance(text, bytes) else str(text)
    return _UNPRINTABLE.sub(_escape_char, text)


def shorten(text: object, limit: int = MAX_SHOWN) -> str:
    """``text`` for an error message: escaped (:func:`escape`) and at most ``limit``
    characters (a 10 MB token is not echoed back)."""
    text = escape(text)
    if len(text) <= limit:
        return text
    tail = limit // 3  # a path's end (the file's own name) says the most
    return f"{text[: limit - 20 - tail]}...{text[-tail:]} ({len(text)} characters)"


_LONG_TOKEN = re.compile(rf"\S{{{MAX_SHOWN + 1},}}")


def shorten_tokens(text: str) -> str:
    """Every over-long word of ``text`` shortened and every control character escaped: a
    message or log line never carries a 10 MB token or a raw newline back to the user,
    whatever raised it. Line breaks are kept (a usage message has several lines); a message
    that must be one line goes through :func:`escape` as a whole."""
    lines = (escape(line) for line in str(text).split("\n"))
    return _LONG_TOKEN.sub(lambda m: shorten(m.group()), "\n".join(lines))


def _key(path: Path) -> Path:
    try:
        return path.resolve()
    except (OSError, RuntimeError):  # a symlink loop: compare as written
        return path.absolute()


Identity = tuple[int, int]  # (st_dev, st_ino): the file itself, whatever its names


def _identity(path: Path) -> Identity | None:
    try:
        st = os.stat(path)
    except (OSError, ValueError):
        return None
    return (st.st_dev, st.st_ino)


class FilePlan:
    """The inputs and outputs of one command, checked together before it does any work.

    Files are compared by identity (device and inode) as well as by resolved path, so an
    output that is a hard link to an input (another name for the same file) is refused too,
    even with ``--force``."""

    def __init__(self, force: bool = False) -> None:
        self.force = force
        self._inputs: dict[Path, str] = {}
        self._outputs: dict[Path, str] = {}
        self._input_ids: dict[Identity, str] = {}
        self._output_ids: dict[Identity, str] = {}

    def input_file(self, path: str | Path, option: str) -> Path:
        """A file to read: it must exist and be a regular file (InputError otherwise)."""
        path = Path(path)
        try:
            st = os.stat(path)
        except (OSError, ValueError) as exc:
            raise InputError(f"{option} {shorten(path)}: {_reason(exc)}") from exc
        if not stat.S_ISREG(st.st_mode):
            raise InputError(f"{option} {shorten(path)}: not a regular file")
        self._claim_input(path, option, (st.st_dev, st.st_ino))
        return path

    def input_folder(self, path: str | Path, option: str) -> Path:
        path = Path(path)
        if not path.is_dir():
            raise InputError(f"{option} {shorten(path)}: not a folder")
        self._claim_input(path, option, _identity(path))
        return path

    def _claim_input(self, path: Path, option: str, ident: Identity | None) -> None:
        key = _key(path)
        owner = self._outputs.get(key) or (ident is not None and self._output_ids.get(ident))
        if owner:
            raise ConfigError(f"{option} {shorten(path)}: is the output {owner}; choose another")
        self._inputs[key] = option
        if ident is not None:
            self._input_ids[ident] = option

    def input_any(self, path: str | Path, option: str) -> Path:
        """A folder or a regular file."""
        path = Path(path)
        return self.input_folder(path, option) if path.is_dir() else self.input_file(path, option)

    def output(self, path: str | Path | None, option: str) -> Path | None:
        """A file to write (None or ``-``: stdout, nothing to check). Refused when it is an
        input (by name, symlink or hard link), another output, an existing file without
        --force, a file another command is writing, something that is not a regular file, a
        terminal, a pipe with a reader or a null device, or its folder is missing or not
        writable."""
        if path is None or str(path) == STDIO:
            return None
        path = Path(path)
        shown = f"{option} {shorten(path)}"
        key = _key(path)
        ident = _identity(path)
        for owner, claims, ids in (
            ("the input", self._inputs, self._input_ids),
            ("also the output", self._outputs, self._output_ids),
        ):
            claimed = claims.get(key) or (ident is not None and ids.get(ident))
            if claimed:
                same = "" if key in claims else " (the same file under another name)"
                raise ConfigError(f"{shown}: is {owner} {claimed}{same}; choose another path")
        check_writable(path, option, self.force)
        self._outputs[key] = option
        if ident is not None:
            self._output_ids[ident] = option
        return path


def _reason(exc: BaseException) -> str:
    return getattr(exc, "strerror", None) or str(exc)


# --- outputs: what may be written, and who is writing it ------------------------------------

_NONBLOCK = getattr(os, "O_NONBLOCK", 0)
_NOCTTY = getattr(os, "O_NOCTTY", 0)
_CLOEXEC = getattr(os, "O_CLOEXEC", 0)
# character devices that swallow what is written (Linux "mem" major 1): null, zero, full
_SINK_DEVICES = {(1, 3), (1, 5), (1, 7)}


@dataclass
class _Claim:
    """An output checked by a FilePlan in this process: whether it may replace a file, the
    file it may replace (identity at check time, locked), or the open end of a pipe."""

    force: bool
    ident: Identity | None = None  # the regular file that existed at check time
    lock_fd: int | None = None  # flock'ed on that file: another writer is refused
    special_fd: int | None = None  # a pipe's write end (kept open: closing it ends the reader)


_CLAIMS: dict[Path, _Claim] = {}
_CLAIMS_LOCK = threading.Lock()


def release_claims() -> None:
    """Forget every output claim and drop their locks (the command is over)."""
    with _CLAIMS_LOCK:
        claims = list(_CLAIMS.values())
        _CLAIMS.clear()
    for claim in claims:
        for fd in (claim.lock_fd, claim.special_fd):
            if fd is not None:
                with contextlib.suppress(OSError):
                    os.close(fd)


def _claim_for(path: Path) -> _Claim | None:
    with _CLAIMS_LOCK:
        return _CLAIMS.get(_key(Path(path)))


def _lock(fd: int) -> bool:
    """An exclusive, non-blocking lock on an open file; False when another holds one."""
    if fcntl is None:
        return True
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        return False
    except OSError:  # a file system without locks: nothing to detect with
        return True
    return True


def _special_output(fd: int, st: os.stat_result, shown: str) -> None:
    """Accept a terminal, a pipe or a null device as an output; ConfigError otherwise."""
    mode = st.st_mode
    if stat.S_ISFIFO(mode) or os.isatty(fd):
        return
    if stat.S_ISCHR(mode) and (os.major(st.st_rdev), os.minor(st.st_rdev)) in _SINK_DEVICES:
        return
    kind = (
        "a device"
        if stat.S_ISCHR(mode) or stat.S_ISBLK(mode)
        else "a socket"
        if stat.S_ISSOCK(mode)
        else "not a regular file"
    )
    raise ConfigError(
        f"{shown}: {kind}; an output must be a regular file, a terminal, a pipe with a "
        "reader or /dev/null"
    )


def _open_special(path: Path, shown: str) -> int:
    """The write end of an existing non-regular output, opened without blocking."""
    try:
        fd = os.open(path, os.O_WRONLY | _NONBLOCK | _NOCTTY | _CLOEXEC)
    except OSError as exc:
        if exc.errno == errno.ENXIO:
            raise ConfigError(f"{shown}: a pipe nobody reads; start its reader first") from None
        raise ConfigError(f"{shown}: cannot write: {_reason(exc)}") from None
    try:
        _special_output(fd, os.fstat(fd), shown)
    except BaseException:
        os.close(fd)
        raise
    return fd


def _blocking(fd: int) -> None:
    if fcntl is not None:
        flags = fcntl.fcntl(fd, fcntl.F_GETFL)
        fcntl.fcntl(fd, fcntl.F_SETFL, flags & ~_NONBLOCK)


def check_writable(path: Path, option: str, force: bool) -> None:
    shown = f"{option} {shorten(path)}"
    try:
        st = os.stat(path)
    except FileNotFoundError:
        st = None
    except (OSError, ValueError) as exc:
        raise ConfigError(f"{shown}: {_reason(exc)}") from exc
    claim = _Claim(force)
    if st is not None:
        if stat.S_ISDIR(st.st_mode):
            raise ConfigError(f"{shown}: is a folder")
        if stat.S_ISREG(st.st_mode) and not force:
            raise ConfigError(f"{shown}: exists; pass --force to overwrite it")
        if not stat.S_ISREG(st.st_mode):
            claim.special_fd = _open_special(path, shown)
    parent = path.parent
    if claim.special_fd is None and not parent.is_dir():
        raise ConfigError(f"{shown}: folder {shorten(parent)} does not exist")
    if (
        claim.special_fd is None
        and not os.access(parent, os.W_OK | os.X_OK)
        and not (st is not None and os.access(path, os.W_OK))
    ):
        raise ConfigError(f"{shown}: folder {shorten(parent)} is not writable")
    if st is not None and stat.S_ISREG(st.st_mode):  # --force: lock the file to replace
        claim.ident = (st.st_dev, st.st_ino)
        claim.lock_fd = _lock_existing(path)
        if claim.lock_fd is None:
            raise ConfigError(f"{shown}: another command is writing it; choose another path")
    with _CLAIMS_LOCK:
        old = _CLAIMS.pop(_key(path), None)
        _CLAIMS[_key(path)] = claim
    if old is not None:
        for fd in (old.lock_fd, old.special_fd):
            if fd is not None:
                with contextlib.suppress(OSError):
                    os.close(fd)


def _lock_existing(path: Path) -> int | None:
    """A locked descriptor of an existing regular file (-1: it cannot be opened to lock,
    nothing to detect with), None when another process holds the lock."""
    for flags in (os.O_RDONLY, os.O_WRONLY):
        try:
            fd = os.open(path, flags | _NONBLOCK | _CLOEXEC)
        except OSError:
            continue
        if _lock(fd):
            return fd
        os.close(fd)
        return None
    return -1


def publish(
    tmp: str | Path, path: str | Path, what: str = "the command", force: bool | None = None
) -> None:
    """Move the finished temporary file ``tmp`` to ``path``. An output claimed with
    ``--force`` replaces the file that was there when it was checked (locked since); any
    other is linked into place only if ``path`` still does not exist, so a file another
    command wrote meanwhile is never replaced (ConfigError, ``tmp`` removed). Outputs not
    claimed by a FilePlan (library use) are replaced unless ``force`` is False."""
    tmp, path = Path(tmp), Path(path)
    claim = _claim_for(path) or _Claim(force is not False, ident=_identity(path))
    if claim.lock_fd is None and claim.force and force is None:  # unclaimed: as asked
        os.replace(tmp, path)
        return
    current = _identity(path)
    if claim.force and claim.ident is not None and current in (claim.ident, None):
        os.replace(tmp, path)
        return
    shown = shorten(path)
    if current is not None and claim.force:
        raise ConfigError(f"{shown}: replaced by another program while {what} ran; not kept")
    try:
        os.link(tmp, path)
    except FileExistsError:
        raise ConfigError(
            f"{shown}: appeared while {what} ran (another command?); not overwritten, "
            f"{'not kept' if claim.force else 'pass --force to overwrite it'}"
        ) from None
    except OSError:  # no hard links here (some network or FAT file systems): reserve, replace
        try:
            os.close(os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666))
        except FileExistsError:
            raise ConfigError(f"{shown}: appeared while {what} ran; not overwritten") from None
        os.replace(tmp, path)
        return
    os.unlink(tmp)


@contextlib.contextmanager
def atomic_write(path: str | Path, mode: str = "w") -> Iterator[IO]:
    """Write to a temporary file beside ``path`` and rename it into place only when the block
    succeeds; on any failure the temporary file goes and ``path`` is untouched."""
    path = Path(path)
    if path.exists() and not path.is_file():  # /dev/null, a pipe: no file to replace
        with open_exclusive(path, force=True, text="b" not in mode) as fh:
            yield fh
        return
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name[:40]}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, mode, **({} if "b" in mode else {"encoding": "utf-8"})) as fh:
            yield fh
            fh.flush()
            os.fsync(fh.fileno())
        os.chmod(tmp, 0o666 & ~_umask())
        publish(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def open_exclusive(path: str | Path, force: bool, text: bool = False) -> IO:
    """Open ``path`` for writing; without ``force`` it must not exist (checked atomically,
    so a file that appeared since the checks is not overwritten either). Opened without
    blocking and checked: a regular file (locked: a second command writing it is refused;
    truncated only once the lock is held), a terminal, a pipe with a reader or a null
    device; anything else is refused."""
    path = Path(path)
    shown = shorten(path)
    claim = _claim_for(path)
    try:
        if claim is not None and claim.special_fd is not None:
            fd = os.dup(claim.special_fd)
        else:
            fd = _open_output_fd(path, force, shown, claim)
        _blocking(fd)
    except FileExistsError as exc:
        raise ConfigError(f"{shown}: exists; pass --force to overwrite it") from exc
    except OSError as exc:
        raise ConfigError(f"{shown}: cannot write: {_reason(exc)}") from exc
    if text:
        return os.fdopen(fd, "w", encoding="utf-8")
    return os.fdopen(fd, "wb")


def _open_output_fd(path: Path, force: bool, shown: str, claim: _Claim | None) -> int:
    try:
        st = os.stat(path)
    except (FileNotFoundError, NotADirectoryError):
        st = None
    if st is not None and not stat.S_ISREG(st.st_mode):  # /dev/null, a pipe, a terminal
        return _open_special(path, shown)
    flags = os.O_WRONLY | os.O_CREAT | _NONBLOCK | _NOCTTY | _CLOEXEC
    if not force:
        flags |= os.O_EXCL
    fd = os.open(path, flags, 0o666)
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):  # it changed since the stat
            _special_output(fd, st, shown)
            return fd
        ours = claim is not None and claim.ident == (st.st_dev, st.st_ino) and claim.lock_fd
        if not ours and not _lock(fd):
            raise ConfigError(f"{shown}: another command is writing it; choose another path")
        if st.st_size:
            os.ftruncate(fd, 0)
    except BaseException:
        os.close(fd)
        raise
    return fd


class AtomicTextFile:
    """A text output written to a temporary file and renamed into place by :meth:`commit`;
    :meth:`discard` (or a failure) leaves the target untouched."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        fd, self._tmp = tempfile.mkstemp(
            prefix=f".{self.path.name[:40]}.", suffix=".tmp", dir=self.path.parent
        )
        self.fh = os.fdopen(fd, "w", encoding="utf-8")

    def write(self, text: str) -> int:
        return self.fh.write(text)

    def flush(self) -> None:
        self.fh.flush()

    def commit(self) -> None:
        if self.fh.closed:
            return
        self.fh.flush()
        os.fsync(self.fh.fileno())
        self.fh.close()
        os.chmod(self._tmp, 0o666 & ~_umask())
        try:
            publish(self._tmp, self.path)
        except BaseException:
            with contextlib.suppress(OSError):
                os.unlink(self._tmp)
            raise

    def discard(self) -> None:
        if not self.fh.closed:
            self.fh.close()
        with contextlib.suppress(OSError):
            os.unlink(self._tmp)


MAX_CONFIG_BYTES = 1 << 20  # a profile, calibration or board config is a few kB


def read_config_text(path: str | Path, what: str) -> str:
    """A small text file (profile, calibration, config): regular, at most MAX_CONFIG_BYTES,
    UTF-8; ConfigError naming the file otherwise (never blocks on a FIFO)."""
    path = Path(path)
    name = f"{shorten(path)}: {what}"
    return read_text_bounded(path, MAX_CONFIG_BYTES, ConfigError, name, f"a {what} file")


def read_text_bounded(
    path: Path, max_bytes: int, error: type[Exception], name: str, limit: str
) -> str:
    """The UTF-8 text of :func:`read_bytes_bounded`'s file, else ``error`` naming ``name``."""
    return decode_text(read_bytes_bounded(path, max_bytes, error, name, limit), error, name)


def decode_text(data: bytes, error: type[Exception], name: str) -> str:
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError:
        raise error(f"{name}: not text (bytes that are not UTF-8)") from None


def read_bytes_bounded(
    path: Path, max_bytes: int, error: type[Exception], name: str, limit: str
) -> bytes:
    """The bytes of a regular file of at most ``max_bytes`` (what ``limit`` can take), else
    ``error`` naming ``name``. Opened non-blocking and checked with fstat, so a FIFO or a
    device never hangs the read, and a file too large is refused by its size, unread; plain
    ``os`` calls (no buffered file object): replay reads thousands of small frames."""
    try:
        fd = os.open(path, os.O_RDONLY | _NONBLOCK)
    except FileNotFoundError:
        raise error(f"{name}: file not found") from None
    except OSError as exc:
        raise error(f"{name}: cannot read: {exc.strerror}") from None
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            raise error(f"{name}: not a regular file")
        if st.st_size > max_bytes:
            raise error(f"{name}: {st.st_size} bytes, more than {limit} can take ({max_bytes})")
        chunks, size = [], 0
        while size <= max_bytes:
            wanted = max_bytes + 1 - size
            chunk = os.read(fd, wanted)
            chunks.append(chunk)
            size += len(chunk)
            if not chunk or (len(chunk) < wanted and size >= st.st_size):
                break  # the end: one read when it holds all that fstat counted
    except OSError as exc:
        raise error(f"{name}: cannot read: {exc.strerror}") from None
    finally:
        os.close(fd)
    if size > max_bytes:
        raise error(f"{name}: grew beyond {max_bytes} bytes while read")
    return chunks[0] if len(chunks) == 1 else b"".join(chunks)


# --- every input bounded, in one place --------------------------------------------------------

# Bytes each kind of input may have (docs/reliability.md): refused by its size, unread, beyond.
INPUT_LIMITS: dict[str, int] = {
    "profile": MAX_CONFIG_BYTES,
    "calibration": MAX_CONFIG_BYTES,
    "config": MAX_CONFIG_BYTES,
    "positions": MAX_CONFIG_BYTES,  # a few hundred x, y, z rows
    "env": 64 * 1024,  # spiel-edge.env: a few KEY=VALUE lines
    "labels": 1 << 20,  # a spiel-csv labels file: one row per acquisition
    "background": 16 << 20,  # .npy: 64 channels x 16384 samples of float64 is 8 MiB
    "static model": 64 << 20,  # .npz, uncompressed members together
    "scenes": 256 << 20,  # .npz of scene frames (measure), uncompressed members together
}
MAX_NPZ_MEMBERS = 64
NUMERIC_KINDS = "biuf"  # bool, signed, unsigned, float: no objects, strings or records


def input_limit(kind: str) -> int:
    return INPUT_LIMITS[kind]


def read_input_text(path: str | Path, kind: str, error: type[Exception] = InputError) -> str:
    """The UTF-8 text of an input of ``kind`` (INPUT_LIMITS), read only when small enough."""
    path = Path(path)
    limit = INPUT_LIMITS[kind]
    return read_text_bounded(path, limit, error, f"{shorten(path)}: {kind}", f"a {kind} file")


def loads_toml(text: str, error: type[Exception], name: str) -> dict:
    """TOML text parsed; ``error`` naming ``name`` when it is not TOML or nested too deeply."""
    from spiel_edge.compat import tomllib

    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise error(f"{name}: not valid TOML: {exc}") from None
    except RecursionError:
        raise error(f"{name}: not valid TOML: nested too deeply") from None


def _open_regular(path: Path, error: type[Exception], name: str, limit: int) -> int:
    try:
        fd = os.open(path, os.O_RDONLY | _NONBLOCK | _CLOEXEC)
    except FileNotFoundError:
        raise error(f"{name}: file not found") from None
    except (OSError, ValueError) as exc:
        raise error(f"{name}: cannot read: {_reason(exc)}") from None
    st = os.fstat(fd)
    if not stat.S_ISREG(st.st_mode):
        os.close(fd)
        raise error(f"{name}: not a regular file")
    if st.st_size > limit:
        os.close(fd)
        raise error(f"{name}: {st.st_size} bytes, more than it may have ({limit})")
    _blocking(fd)
    return fd


def _npy_header(fh: IO[bytes], error: type[Exception], name: str, limit: int, text_ok=False):
    """(shape, dtype, fortran) of the .npy stream at ``fh``, checked before any data is read:
    a numeric dtype, at most ``limit`` bytes of data."""
    import numpy as np
    from numpy.lib import format as npy

    try:
        version = npy.read_magic(fh)
        if version == (1, 0):
            shape, fortran, dtype = npy.read_array_header_1_0(fh, max_header_size=10000)
        elif version in ((2, 0), (3, 0)):
            shape, fortran, dtype = npy.read_array_header_2_0(fh, max_header_size=10000)
        else:
            raise ValueError(f"unknown .npy version {version}")
    except (ValueError, OSError, EOFError, SyntaxError, TypeError) as exc:
        raise error(f"{name}: not a .npy array ({shorten(exc, 120)})") from None
    kinds = NUMERIC_KINDS + ("US" if text_ok else "")
    if dtype.kind not in kinds or dtype.fields is not None or dtype.hasobject:
        raise error(f"{name}: holds {dtype} values, not numbers")
    count = int(np.prod(shape, dtype=np.float64)) if shape else 1
    if count * dtype.itemsize > limit:
        raise error(f"{name}: a {'x'.join(map(str, shape))} array, more than it may hold")
    return shape, dtype, fortran, count


def _npy_data(fh: IO[bytes], shape, dtype, fortran: bool, count: int, error, name: str):
    import numpy as np

    size = count * dtype.itemsize
    data = fh.read(size)
    if len(data) != size:
        raise error(f"{name}: cut short ({len(data)} of {size} bytes of data)")
    arr = np.frombuffer(data, dtype=dtype, count=count)
    return arr.reshape(shape, order="F" if fortran else "C")


def load_npy_bounded(path: str | Path, kind: str, error: type[Exception] = InputError):
    """A numeric array from a .npy file of ``kind``: a regular file within INPUT_LIMITS[kind],
    its header (dtype, shape, size) checked before the data is read."""
    path = Path(path)
    name = f"{shorten(path)}: {kind}"
    limit = INPUT_LIMITS[kind]
    with os.fdopen(_open_regular(path, error, name, limit), "rb") as fh:
        shape, dtype, fortran, count = _npy_header(fh, error, name, limit)
        return _npy_data(fh, shape, dtype, fortran, count, error, name)


def load_npz_bounded(
    path: str | Path,
    kind: str,
    error: type[Exception] = InputError,
    *,
    headers_only: bool = False,
    text_ok: bool = False,
) -> dict:
    """The numeric arrays of a .npz archive of ``kind``: a regular file, at most
    MAX_NPZ_MEMBERS members whose declared uncompressed sizes together stay within
    INPUT_LIMITS[kind] (checked before anything is decompressed), each a numeric .npy whose
    header is checked before its data is read (``text_ok``: fixed-width strings allowed too).
    ``headers_only``: check, and return {name: (shape, dtype)}."""
    import zipfile

    path = Path(path)
    name = f"{shorten(path)}: {kind}"
    limit = INPUT_LIMITS[kind]
    fh = os.fdopen(_open_regular(path, error, name, limit), "rb")
    try:
        try:
            archive = zipfile.ZipFile(fh)
        except (zipfile.BadZipFile, OSError, ValueError, EOFError):
            raise error(f"{name}: not a .npz archive") from None
        with archive:
            members = archive.infolist()
            if len(members) > MAX_NPZ_MEMBERS:
                raise error(f"{name}: {len(members)} members, more than {MAX_NPZ_MEMBERS}")
            declared = sum(m.file_size for m in members)
            if declared > limit:
                raise error(f"{name}: {declared} bytes once decompressed, more than {limit}")
            out = {}
            for member in members:
                key = member.filename[:-4] if member.filename.endswith(".npy") else None
                where = f"{name}: member {shorten(member.filename, 40)}"
                if key is None:
                    raise error(f"{where}: not a .npy array")
                try:
                    with archive.open(member) as part:
                        shape, dtype, fortran, count = _npy_header(
                            part, error, where, limit, text_ok
                        )
                        if headers_only:
                            out[key] = (shape, dtype)
                            continue
                        out[key] = _npy_data(part, shape, dtype, fortran, count, error, where)
                except (zipfile.BadZipFile, OSError, EOFError, NotImplementedError) as exc:
                    raise error(f"{where}: damaged ({shorten(exc, 80)})") from None
            return out
    finally:
        fh.close()
