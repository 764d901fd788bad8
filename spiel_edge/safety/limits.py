"""How large an input may be before it is parsed: derived from the profile's frame shape, so
a hostile or damaged file costs at most about one frame's worth of memory."""

from __future__ import annotations

import os
import stat
from dataclasses import dataclass
from pathlib import Path
from typing import IO

from spiel_edge.errors import ConfigError, InputError
from spiel_edge.safety.claims import CLOEXEC, NONBLOCK, reason, set_blocking
from spiel_edge.safety.shown import shorten

MAX_VALUE_CHARS = 32  # one sample as text, separator included ("-1.2345678901234567e+308 ")
OVERHEAD_BYTES = 64 * 1024  # metadata beside the samples (MCAP JSON) or blank lines (csv)
GENERIC_CHANNELS, GENERIC_SAMPLES = 64, 16384  # when no profile says otherwise


@dataclass(frozen=True)
class InputLimits:
    max_channels: int = GENERIC_CHANNELS
    max_samples: int = GENERIC_SAMPLES

    @classmethod
    def for_profile(cls, profile) -> InputLimits:
        """The profile's frame shape (a little slack, so a wrong shape still gets its own
        clear error naming both shapes)."""
        channels = len(profile.geometry.channels_mm)
        samples = int(profile.acquisition.n_samples)
        return cls(max(2 * channels, 8), max(2 * samples, 64))

    @property
    def max_values(self) -> int:
        return self.max_channels * self.max_samples

    @property
    def max_text_bytes(self) -> int:
        return self.max_values * MAX_VALUE_CHARS + OVERHEAD_BYTES

    @property
    def max_json_bytes(self) -> int:
        return self.max_text_bytes

    def check_shape(self, channels: int, samples: int) -> None:
        if channels > self.max_channels or samples > self.max_samples:
            raise InputError(
                f"{channels} channels x {samples} samples exceed the profile's bound of "
                f"{self.max_channels} x {self.max_samples}"
            )


# --- the bounded readers: every file a command reads goes through one of them ------------

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
        fd = os.open(path, os.O_RDONLY | NONBLOCK)
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
        fd = os.open(path, os.O_RDONLY | NONBLOCK | CLOEXEC)
    except FileNotFoundError:
        raise error(f"{name}: file not found") from None
    except (OSError, ValueError) as exc:
        raise error(f"{name}: cannot read: {reason(exc)}") from None
    st = os.fstat(fd)
    if not stat.S_ISREG(st.st_mode):
        os.close(fd)
        raise error(f"{name}: not a regular file")
    if st.st_size > limit:
        os.close(fd)
        raise error(f"{name}: {st.st_size} bytes, more than it may have ({limit})")
    set_blocking(fd)
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
