"""Where calibration data comes from: labelled recordings and target-position lists (I/O)."""

from __future__ import annotations

import csv
import logging
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from spiel_edge.errors import ConfigError, InputError
from spiel_edge.recordings.spiel_csv import iter_recordings, position_key, read_truth

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class LabelledSet:
    names: list[str]
    frames: np.ndarray  # (M, channels, samples)
    backgrounds: np.ndarray | None
    truth_mm: np.ndarray  # (M, 3)


def load_recordings(
    folder: str | Path,
    background: str | Path | None = None,
    *,
    positions: set | None = None,
    exclude_z: Iterable[float] = (),
) -> LabelledSet:
    """Labelled acquisitions from a spiel-csv folder or a labelled .npz (told by the content);
    ``positions`` keeps those (x, y); unreadable or unlabelled files are skipped with a
    warning."""
    from spiel_edge.recordings.kinds import recording_kind

    if recording_kind(folder, ("spiel-csv", "labelled")) == "labelled":
        if background is not None:
            raise ConfigError(
                f"--background is for a spiel-csv folder; {folder} carries its own backgrounds"
            )
        from spiel_edge.recordings.labelled import load_labelled

        data = load_labelled(folder, positions=positions, exclude_z=exclude_z)
        if not len(data):
            raise InputError(f"{folder}: no labelled acquisitions to calibrate from")
        return LabelledSet(data.names, data.frames, data.backgrounds, data.truth_mm)
    names, frames, bgs, truth = [], [], [], []
    skip_z = {float(z) for z in exclude_z}
    for rec in iter_recordings(folder, background):
        key = position_key(rec.source)
        if positions is not None and (key is None or key[:2] not in positions):
            continue
        if rec.error is not None:
            log.warning("skipped: %s", rec.error)
            continue
        t = read_truth(Path(folder) / rec.source)
        if t is None:
            log.warning("skipped %s: no label file and no position in the name", rec.source)
            continue
        if float(t[2]) in skip_z:
            continue
        names.append(rec.source)
        frames.append(rec.frames)
        bgs.append(rec.background)
        truth.append(t)
    if not names:
        raise InputError(f"{folder}: no labelled acquisitions to calibrate from")
    if len({f.shape for f in frames}) != 1:
        raise InputError(f"{folder}: acquisitions have different shapes")
    background_arr = None if background is None else np.stack(bgs)
    return LabelledSet(names, np.stack(frames), background_arr, np.stack(truth))


def read_positions(path: str | Path) -> np.ndarray:
    """Target positions (P, 3) in mm from a CSV with x, y, z per row (a header and # comments
    are allowed)."""
    from spiel_edge.safety.limits import read_input_text  # the bounded reader (positions: 1 MiB)

    path = Path(path)
    text = read_input_text(path, "positions")
    rows: list[list[float]] = []
    header_allowed = True
    for lineno, row in enumerate(csv.reader(line for line in text.splitlines()), start=1):
        cells = [c.strip() for c in row if c.strip()]
        if not cells or cells[0].startswith("#"):
            continue
        try:
            values = [float(c) for c in cells]
        except ValueError:
            if header_allowed:
                header_allowed = False
                continue
            raise InputError(f"{path}:{lineno}: expected x, y, z numbers, got {row}") from None
        header_allowed = False
        if len(values) != 3 or not np.all(np.isfinite(values)):
            raise InputError(
                f"{path}:{lineno}: expected 3 finite numbers (x, y, z in mm), got {row}"
            )
        rows.append(values)
    if not rows:
        raise InputError(f"{path}: no positions")
    return np.array(rows, dtype=np.float64)
