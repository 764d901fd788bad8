"""The file rules every command follows (docs/reliability.md), checked before the work starts.

* no command overwrites a file it did not create in this run unless asked (``--force``), and
  never one of its own inputs (compared by identity: a hard link is the same file); two
  outputs on one file are refused; two commands on one output cannot both succeed
  (safety/claims.py);
* an output's folder must exist and be writable before anything is computed or captured;
* only regular files are read (a FIFO, a device or a folder where a file is expected is an
  error, never a hang), each bounded before it is read (safety/limits.py);
* small outputs are written to a temporary file beside the target and renamed into place, so
  a failure or a signal never leaves half a file where a good one was.
"""

from __future__ import annotations

import contextlib
import os
import stat
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import IO

from spiel_edge.errors import ConfigError, InputError
from spiel_edge.safety.claims import (  # noqa: F401  # release_claims, publish: part of the rules
    Identity,
    check_writable,
    claim_for,
    claim_key,
    identity_of,
    open_output_fd,
    open_special,
    publish,
    reason,
    release_claims,
    set_blocking,
)
from spiel_edge.safety.limits import (  # noqa: F401  # the bounded readers, where they were
    MAX_CONFIG_BYTES,
    decode_text,
    read_bytes_bounded,
    read_config_text,
    read_text_bounded,
)
from spiel_edge.safety.shown import MAX_SHOWN, escape, shorten, shorten_tokens  # noqa: F401

STDIO = "-"


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
            raise InputError(f"{option} {shorten(path)}: {reason(exc)}") from exc
        if not stat.S_ISREG(st.st_mode):
            raise InputError(f"{option} {shorten(path)}: not a regular file")
        self._claim_input(path, option, (st.st_dev, st.st_ino))
        return path

    def input_folder(self, path: str | Path, option: str) -> Path:
        path = Path(path)
        if not path.is_dir():
            raise InputError(f"{option} {shorten(path)}: not a folder")
        self._claim_input(path, option, identity_of(path))
        return path

    def _claim_input(self, path: Path, option: str, ident: Identity | None) -> None:
        key = claim_key(path)
        owner = self._outputs.get(key) or (ident is not None and self._output_ids.get(ident))
        if owner:
            raise ConfigError(f"{option} {shorten(path)}: is the output {owner}; choose another")
        self._inputs[key] = option
        if ident is not None:
            self._input_ids[ident] = option

    def input_if_file(self, path: str | Path, option: str) -> None:
        """An input that may also be a name (``--profile spiel-icra23``): noted when it is a
        regular file, so no output replaces it; otherwise its reader says what is wrong."""
        try:
            st = os.stat(path)
        except (OSError, ValueError):
            return
        if stat.S_ISREG(st.st_mode):
            self._claim_input(Path(path), option, (st.st_dev, st.st_ino))

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
        key = claim_key(path)
        ident = identity_of(path)
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
        os.chmod(tmp, 0o666 & ~current_umask())
        publish(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise


def current_umask() -> int:
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
    claim = claim_for(path)
    try:
        if claim is not None and claim.special_fd is not None:
            fd = os.dup(claim.special_fd)
        else:
            fd = open_output_fd(path, force, shown, claim)
        set_blocking(fd)
    except FileExistsError as exc:
        raise ConfigError(f"{shown}: exists; pass --force to overwrite it") from exc
    except OSError as exc:
        raise ConfigError(f"{shown}: cannot write: {reason(exc)}") from exc
    if text:
        return os.fdopen(fd, "w", encoding="utf-8")
    return os.fdopen(fd, "wb")


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
        os.chmod(self._tmp, 0o666 & ~current_umask())
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
