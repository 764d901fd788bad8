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
import os
import re
import stat
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import IO

from spiel_edge.errors import ConfigError, InputError

STDIO = "-"
MAX_SHOWN = 80  # characters of user-supplied text echoed into a message


def shorten(text: object, limit: int = MAX_SHOWN) -> str:
    """``text`` for an error message: at most ``limit`` characters (a 10 MB token is not
    echoed back)."""
    text = str(text)
    return text if len(text) <= limit else f"{text[: limit - 20]}... ({len(text)} characters)"


_LONG_TOKEN = re.compile(rf"\S{{{MAX_SHOWN + 1},}}")


def shorten_tokens(text: str) -> str:
    """Every over-long word of ``text`` shortened: a message or log line never carries a
    10 MB token back to the user, whatever raised it."""
    return _LONG_TOKEN.sub(lambda m: shorten(m.group()), text)


def _key(path: Path) -> Path:
    try:
        return path.resolve()
    except (OSError, RuntimeError):  # a symlink loop: compare as written
        return path.absolute()


class FilePlan:
    """The inputs and outputs of one command, checked together before it does any work."""

    def __init__(self, force: bool = False) -> None:
        self.force = force
        self._inputs: dict[Path, str] = {}
        self._outputs: dict[Path, str] = {}

    def input_file(self, path: str | Path, option: str) -> Path:
        """A file to read: it must exist and be a regular file (InputError otherwise)."""
        path = Path(path)
        try:
            mode = os.stat(path).st_mode
        except OSError as exc:
            raise InputError(f"{option} {shorten(path)}: {exc.strerror or exc}") from exc
        if not stat.S_ISREG(mode):
            raise InputError(f"{option} {shorten(path)}: not a regular file")
        self._inputs[_key(path)] = option
        return path

    def input_folder(self, path: str | Path, option: str) -> Path:
        path = Path(path)
        if not path.is_dir():
            raise InputError(f"{option} {shorten(path)}: not a folder")
        self._inputs[_key(path)] = option
        return path

    def input_any(self, path: str | Path, option: str) -> Path:
        """A folder or a regular file."""
        path = Path(path)
        return self.input_folder(path, option) if path.is_dir() else self.input_file(path, option)

    def output(self, path: str | Path | None, option: str) -> Path | None:
        """A file to write (None or ``-``: stdout, nothing to check). Refused when it is an
        input, another output, an existing file without --force, or its folder is missing or
        not writable."""
        if path is None or str(path) == STDIO:
            return None
        path = Path(path)
        shown = f"{option} {shorten(path)}"
        key = _key(path)
        for owner, claims in (("the input", self._inputs), ("also the output", self._outputs)):
            if key in claims:
                raise ConfigError(f"{shown}: is {owner} {claims[key]}; choose another path")
        check_writable(path, option, self.force)
        self._outputs[key] = option
        return path


def check_writable(path: Path, option: str, force: bool) -> None:
    shown = f"{option} {shorten(path)}"
    try:
        st = os.stat(path)
    except FileNotFoundError:
        st = None
    except OSError as exc:
        raise ConfigError(f"{shown}: {exc.strerror or exc}") from exc
    if st is not None:
        if stat.S_ISDIR(st.st_mode):
            raise ConfigError(f"{shown}: is a folder")
        if stat.S_ISREG(st.st_mode) and not force:
            raise ConfigError(f"{shown}: exists; pass --force to overwrite it")
    parent = path.parent
    if not parent.is_dir():
        raise ConfigError(f"{shown}: folder {shorten(parent)} does not exist")
    if not os.access(parent, os.W_OK | os.X_OK) and not (
        st is not None and os.access(path, os.W_OK)
    ):
        raise ConfigError(f"{shown}: folder {shorten(parent)} is not writable")


@contextlib.contextmanager
def atomic_write(path: str | Path, mode: str = "w") -> Iterator[IO]:
    """Write to a temporary file beside ``path`` and rename it into place only when the block
    succeeds; on any failure the temporary file goes and ``path`` is untouched."""
    path = Path(path)
    if path.exists() and not path.is_file():  # /dev/null, a FIFO: no file to replace
        with open(path, mode, **({} if "b" in mode else {"encoding": "utf-8"})) as fh:
            yield fh
        return
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name[:40]}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, mode, **({} if "b" in mode else {"encoding": "utf-8"})) as fh:
            yield fh
            fh.flush()
            os.fsync(fh.fileno())
        os.chmod(tmp, 0o666 & ~_umask())
        os.replace(tmp, path)
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
    so a file that appeared since the checks is not overwritten either)."""
    path = Path(path)
    special = path.exists() and not path.is_file()  # /dev/null, a FIFO: nothing to destroy
    mode = ("w" if force or special else "x") + ("" if text else "b")
    try:
        return open(path, mode, **({"encoding": "utf-8"} if text else {}))  # noqa: SIM115
    except FileExistsError as exc:
        raise ConfigError(f"{shorten(path)}: exists; pass --force to overwrite it") from exc
    except OSError as exc:
        raise ConfigError(f"{shorten(path)}: cannot write: {exc.strerror or exc}") from exc


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
        os.replace(self._tmp, self.path)

    def discard(self) -> None:
        if not self.fh.closed:
            self.fh.close()
        with contextlib.suppress(OSError):
            os.unlink(self._tmp)


_NONBLOCK = getattr(os, "O_NONBLOCK", 0)
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
