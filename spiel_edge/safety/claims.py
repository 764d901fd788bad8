"""Outputs by identity: what an output may be (a regular file, a terminal, a pipe with a reader,
a null device), opened without blocking, and who is writing it. An output checked by a
FilePlan is claimed here: with ``--force`` the file it may replace is locked from the check on
(another command on it is refused), a pipe's write end is kept open for the command, and
:func:`publish` moves a finished temporary file into place only over the file that was
checked, or where nothing exists yet (docs/reliability.md)."""

from __future__ import annotations

import contextlib
import errno
import os
import stat
import threading
from dataclasses import dataclass
from pathlib import Path

try:
    import fcntl
except ImportError:  # pragma: no cover - not a POSIX host
    fcntl = None  # type: ignore[assignment]

from spiel_edge.errors import ConfigError
from spiel_edge.safety.shown import shorten

Identity = tuple[int, int]  # (st_dev, st_ino): the file itself, whatever its names


def claim_key(path: Path) -> Path:
    try:
        return path.resolve()
    except (OSError, RuntimeError):  # a symlink loop: compare as written
        return path.absolute()


def identity_of(path: Path) -> Identity | None:
    try:
        st = os.stat(path)
    except (OSError, ValueError):
        return None
    return (st.st_dev, st.st_ino)


def reason(exc: BaseException) -> str:
    return getattr(exc, "strerror", None) or str(exc)


# --- outputs: what may be written, and who is writing it ------------------------------------

NONBLOCK = getattr(os, "O_NONBLOCK", 0)
_NOCTTY = getattr(os, "O_NOCTTY", 0)
CLOEXEC = getattr(os, "O_CLOEXEC", 0)
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


def claim_for(path: Path) -> _Claim | None:
    with _CLAIMS_LOCK:
        return _CLAIMS.get(claim_key(Path(path)))


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


def open_special(path: Path, shown: str) -> int:
    """The write end of an existing non-regular output, opened without blocking."""
    try:
        fd = os.open(path, os.O_WRONLY | NONBLOCK | _NOCTTY | CLOEXEC)
    except OSError as exc:
        if exc.errno == errno.ENXIO:
            raise ConfigError(f"{shown}: a pipe nobody reads; start its reader first") from None
        raise ConfigError(f"{shown}: cannot write: {reason(exc)}") from None
    try:
        _special_output(fd, os.fstat(fd), shown)
    except BaseException:
        os.close(fd)
        raise
    return fd


def set_blocking(fd: int) -> None:
    if fcntl is not None:
        flags = fcntl.fcntl(fd, fcntl.F_GETFL)
        fcntl.fcntl(fd, fcntl.F_SETFL, flags & ~NONBLOCK)


def check_writable(path: Path, option: str, force: bool) -> None:
    shown = f"{option} {shorten(path)}"
    try:
        st = os.stat(path)
    except FileNotFoundError:
        st = None
    except (OSError, ValueError) as exc:
        raise ConfigError(f"{shown}: {reason(exc)}") from exc
    claim = _Claim(force)
    if st is not None:
        if stat.S_ISDIR(st.st_mode):
            raise ConfigError(f"{shown}: is a folder")
        if stat.S_ISREG(st.st_mode) and not force:
            raise ConfigError(f"{shown}: exists; pass --force to overwrite it")
        if not stat.S_ISREG(st.st_mode):
            claim.special_fd = open_special(path, shown)
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
        old = _CLAIMS.pop(claim_key(path), None)
        _CLAIMS[claim_key(path)] = claim
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
            fd = os.open(path, flags | NONBLOCK | CLOEXEC)
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
    claim = claim_for(path)
    if claim is None:  # not checked by a FilePlan (library use): as asked
        if force is not False:
            os.replace(tmp, path)
            return
        claim = _Claim(False)
    current = identity_of(path)
    if claim.force and claim.ident is not None and current in (claim.ident, None):
        os.replace(tmp, path)
        return
    shown = shorten(path)
    if current is not None and claim.force and claim.ident is not None:
        raise ConfigError(f"{shown}: replaced by another program during {what}; not kept")
    try:
        os.link(tmp, path)
    except FileExistsError:
        raise ConfigError(
            f"{shown}: appeared during {what} (another command?); not overwritten, "
            f"{'not kept' if claim.force else 'pass --force to overwrite it'}"
        ) from None
    except OSError:  # no hard links here (some network or FAT file systems): reserve, replace
        try:
            os.close(os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666))
        except FileExistsError:
            raise ConfigError(f"{shown}: appeared during {what}; not overwritten") from None
        os.replace(tmp, path)
        return
    os.unlink(tmp)


def open_output_fd(path: Path, force: bool, shown: str, claim: _Claim | None) -> int:
    try:
        st = os.stat(path)
    except (FileNotFoundError, NotADirectoryError):
        st = None
    if st is not None and not stat.S_ISREG(st.st_mode):  # /dev/null, a pipe, a terminal
        return open_special(path, shown)
    flags = os.O_WRONLY | os.O_CREAT | NONBLOCK | _NOCTTY | CLOEXEC
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
