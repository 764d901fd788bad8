"""The spiel-csv recording format of the published dataset.

A folder holds ``<name>_frames.csv`` (one line per channel, whitespace-separated samples);
labelled folders also hold ``<name>_labels.csv`` (one line per channel: channel, on-chip
range, on-chip amplitude, ground-truth x, y, z in mm). A background folder holds target-free
frames under the same names.
"""

from __future__ import annotations

import re
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from spiel_edge.errors import InputError

FRAMES_SUFFIX = "_frames.csv"
LABELS_SUFFIX = "_labels.csv"
_POSITION_RE = re.compile(r"^(-?[\d.]+)mm_(-?[\d.]+)mm_(-?[\d.]+)mm_")


@dataclass
class Recording:
    source: str  # the frames file name
    frames: np.ndarray | None
    background: np.ndarray | None
    error: str | None = None  # why frames (or the required background) could not be read


def frame_files(folder: str | Path) -> list[Path]:
    folder = Path(folder)
    if not folder.is_dir():
        raise InputError(f"{folder}: not a folder")
    files = sorted(folder.glob(f"*{FRAMES_SUFFIX}"))
    if not files:
        raise InputError(f"{folder}: no *{FRAMES_SUFFIX} files")
    return files


def read_frames(path: str | Path) -> np.ndarray:
    """One acquisition (channels, samples) as float64; InputError naming the file otherwise."""
    path = Path(path)
    try:
        text = path.read_text()
    except FileNotFoundError as exc:
        raise InputError(f"{path.name}: file not found") from exc
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"{path.name}: cannot read: {exc}") from exc
    rows = [line.replace(",", " ").split() for line in text.splitlines() if line.strip()]
    if not rows:
        raise InputError(f"{path.name}: empty file")
    if len({len(r) for r in rows}) != 1:
        raise InputError(
            f"{path.name}: channels have different sample counts {[len(r) for r in rows]}"
        )
    try:
        arr = np.array(rows, dtype=np.float64)
    except ValueError as exc:
        raise InputError(f"{path.name}: not numeric: {exc}") from exc
    if not np.all(np.isfinite(arr)):
        raise InputError(f"{path.name}: contains NaN or infinite samples")
    return arr


def iter_recordings(
    folder: str | Path, background: str | Path | None = None
) -> Iterator[Recording]:
    """Each frames file with its background; read errors become Recording.error, never raise."""
    bg_folder = Path(background) if background is not None else None
    for path in frame_files(folder):
        try:
            frames = read_frames(path)
            bg = None
            if bg_folder is not None:
                bg_path = bg_folder / path.name
                if not bg_path.exists():
                    raise InputError(f"{path.name}: no background file {bg_path}")
                bg = read_frames(bg_path)
                if bg.shape != frames.shape:
                    raise InputError(
                        f"{path.name}: background shape {bg.shape} differs from frames {frames.shape}"
                    )
            yield Recording(path.name, frames, bg)
        except InputError as exc:
            yield Recording(path.name, None, None, str(exc))


def read_truth(frames_path: str | Path) -> np.ndarray | None:
    """Ground-truth position (mm) from the labels file beside a frames file, else from its name."""
    frames_path = Path(frames_path)
    labels = frames_path.with_name(frames_path.name[: -len(FRAMES_SUFFIX)] + LABELS_SUFFIX)
    if labels.exists():
        try:
            rows = np.loadtxt(labels, ndmin=2)
            if rows.shape[1] >= 6 and np.all(np.isfinite(rows[0, 3:6])):
                return rows[0, 3:6].astype(np.float64)
        except ValueError:
            pass
    m = _POSITION_RE.match(frames_path.name)
    return np.array([float(v) for v in m.groups()]) if m else None


def position_key(name: str) -> tuple[float, float, float] | None:
    """The (x, y, z) encoded in a spiel-csv file name, used to split by position."""
    m = _POSITION_RE.match(name)
    return tuple(float(v) for v in m.groups()) if m else None
