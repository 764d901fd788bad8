"""The spiel-csv recording format of the published dataset.

A folder holds ``<name>_frames.csv`` (one line per channel, whitespace-separated samples);
labelled folders also hold ``<name>_labels.csv`` (one line per channel: channel, on-chip
range, on-chip amplitude, ground-truth x, y, z in mm). A background folder holds target-free
frames under the same names.
"""

from __future__ import annotations

import re
import warnings
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from spiel_edge._jit import jit
from spiel_edge.errors import InputError
from spiel_edge.safety.guard import decode_text, read_bytes_bounded, shorten
from spiel_edge.safety.limits import InputLimits, read_input_text

FRAMES_SUFFIX = "_frames.csv"
LABELS_SUFFIX = "_labels.csv"
MAX_LABELS_BYTES = 1 << 20
_POSITION_RE = re.compile(r"^(-?[\d.]+)mm_(-?[\d.]+)mm_(-?[\d.]+)mm_")


@dataclass
class Recording:
    source: str  # the frames file name
    frames: np.ndarray | None
    background: np.ndarray | None
    error: str | None = None  # why frames (or the required background) could not be read
    time_s: float | None = None  # capture time (Unix s) when the recording has it (MCAP)
    truth_mm: np.ndarray | None = None  # ground truth (3,) when the recording carries it


def frame_files(folder: str | Path) -> list[Path]:
    folder = Path(folder)
    if not folder.is_dir():
        raise InputError(f"{folder}: not a folder")
    files = sorted(folder.glob(f"*{FRAMES_SUFFIX}"))
    if not files:
        raise InputError(f"{folder}: no *{FRAMES_SUFFIX} files")
    return files


def read_frames(path: str | Path, limits: InputLimits | None = None) -> np.ndarray:
    """One acquisition (channels, samples) as float64; InputError naming the file otherwise.

    The file must be a regular file no larger than ``limits`` allow (the profile's frame
    shape); its size and then its shape are checked before any sample is converted."""
    path = path if isinstance(path, Path) else Path(path)
    limits = limits or InputLimits()
    data = read_bytes_bounded(
        path, limits.max_text_bytes, InputError, path.name, "a frame of the profile's shape"
    )
    fast = read_integers(data)  # integer samples (what boards record): the compiled scanner
    if fast is not None:
        try:
            limits.check_shape(*fast.shape)
        except InputError as exc:
            raise InputError(f"{path.name}: {exc}") from None
        return fast
    text = decode_text(data, InputError, path.name)
    rows = [line.replace(",", " ").split() for line in text.splitlines() if line.strip()]
    if not rows:
        raise InputError(f"{path.name}: empty file")
    if len({len(r) for r in rows}) != 1:
        counts = [len(r) for r in rows]
        raise InputError(f"{path.name}: channels have different sample counts {shorten(counts)}")
    try:
        limits.check_shape(len(rows), len(rows[0]))
    except InputError as exc:
        raise InputError(f"{path.name}: {exc}") from None
    try:
        arr = np.array(rows, dtype=np.float64)
    except (ValueError, OverflowError) as exc:
        raise InputError(f"{path.name}: not numeric: {shorten(exc)}") from None
    if not np.all(np.isfinite(arr)):
        raise InputError(f"{path.name}: contains NaN or infinite samples")
    return arr


def read_integers(data: bytes) -> np.ndarray | None:
    """(rows, columns) when every token is an integer and rows agree in length, else None."""
    if not data:
        return None
    values = np.empty(len(data) // 2 + 1)
    n_values, n_rows = _scan_integers(np.frombuffer(data, dtype=np.uint8), values)
    if n_rows <= 0:
        return None
    # a copy: the scan buffer is about three times the frame (evaluate holds every frame)
    return values[:n_values].reshape(n_rows, n_values // n_rows).copy()


@jit
def _scan_integers(buf, values):
    """Integers separated by spaces, tabs or commas, one row per line (blank lines skipped);
    returns (values, rows) read, or (-1, -1) at the first byte that is not part of one or
    when rows differ in length (the general parser reports those)."""
    n_values = 0
    n_rows = 0
    in_row = 0
    width = -1
    i = 0
    n = buf.shape[0]
    while i < n:
        b = buf[i]
        if b == 10 or b == 13:  # a line break (CR LF gives an empty line, skipped)
            if in_row:
                if width >= 0 and in_row != width:
                    return -1, -1
                width = in_row
                n_rows += 1
                in_row = 0
            i += 1
        elif b == 32 or b == 9 or b == 44:
            i += 1
        else:
            negative = b == 45
            if negative:
                i += 1
            start = i
            v = 0.0
            while i < n and 48 <= buf[i] <= 57:
                v = v * 10.0 + (buf[i] - 48)
                i += 1
            if i == start or i - start > 15:
                return -1, -1  # a lone sign or more digits than float64 holds exactly
            if i < n and not (
                buf[i] == 10 or buf[i] == 32 or buf[i] == 9 or buf[i] == 44 or buf[i] == 13
            ):
                return -1, -1  # a decimal point, exponent or text: the general parser
            values[n_values] = -v if negative else v
            n_values += 1
            in_row += 1
    if in_row:
        if width >= 0 and in_row != width:
            return -1, -1
        n_rows += 1
    return n_values, n_rows


def iter_recordings(
    folder: str | Path, background: str | Path | None = None, limits: InputLimits | None = None
) -> Iterator[Recording]:
    """Each frames file with its background; read errors become Recording.error, never raise."""
    background = None if background is None else Path(background)
    for path in frame_files(folder):
        yield read_recording(path, background, limits)


def read_recording(
    path: Path, background: str | Path | None = None, limits: InputLimits | None = None
) -> Recording:
    """One frames file with its background (same name in ``background``); never raises."""
    try:
        frames = read_frames(path, limits)
        bg = None
        if background is not None:
            bg_path = Path(background) / path.name
            try:
                bg = read_frames(bg_path, limits)
            except InputError:
                if not bg_path.exists():  # checked only on failure: one stat less per frame
                    raise InputError(f"{path.name}: no background file {bg_path}") from None
                raise
            if bg.shape != frames.shape:
                raise InputError(
                    f"{path.name}: background shape {bg.shape} differs from frames {frames.shape}"
                )
        return Recording(path.name, frames, bg)
    except InputError as exc:
        return Recording(path.name, None, None, str(exc))


def read_truth(frames_path: str | Path) -> np.ndarray | None:
    """Ground-truth position (mm) from the labels file beside a frames file, else from its name."""
    frames_path = Path(frames_path)
    labels = frames_path.with_name(frames_path.name[: -len(FRAMES_SUFFIX)] + LABELS_SUFFIX)
    if labels.is_file():
        try:
            text = read_input_text(labels, "labels")
            with warnings.catch_warnings():  # an empty file: numpy's own warning, not ours
                warnings.simplefilter("ignore")
                rows = np.loadtxt(text.splitlines(), ndmin=2)
            if rows.shape[1] >= 6 and np.all(np.isfinite(rows[0, 3:6])):
                return rows[0, 3:6].astype(np.float64)
        except (ValueError, OSError, InputError):
            pass  # unreadable labels: the position in the file name, if any
    m = _POSITION_RE.match(frames_path.name)
    return np.array([float(v) for v in m.groups()]) if m else None


def position_key(name: str) -> tuple[float, float, float] | None:
    """The (x, y, z) encoded in a spiel-csv file name, used to split by position."""
    m = _POSITION_RE.match(name)
    return tuple(float(v) for v in m.groups()) if m else None
