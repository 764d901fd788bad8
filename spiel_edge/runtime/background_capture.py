"""Target-free background captures: take several acquisitions of the empty scene, keep the
per-sample median (robust to a passing reflection), save it for ``run --background``."""

from __future__ import annotations

import threading
from collections.abc import Iterable
from pathlib import Path

import numpy as np

from spiel_edge.errors import InputError
from spiel_edge.safety.guard import atomic_write


def median_background(
    acquisitions: Iterable, count: int, stop: threading.Event | None = None
) -> np.ndarray:
    """Per-sample median of the first ``count`` acquisitions' samples (channels, samples)."""
    if count < 1:
        raise InputError(f"a background needs at least 1 acquisition, got {count}")
    frames = []
    for acq in acquisitions:
        frames.append(np.asarray(acq.samples, dtype=np.float64))
        if frames[0].shape != frames[-1].shape:
            raise InputError(
                f"acquisition shape changed during the capture: {frames[0].shape} -> {frames[-1].shape}"
            )
        if len(frames) == count or (stop is not None and stop.is_set()):
            break
    if len(frames) < count:
        raise InputError(f"background capture stopped after {len(frames)} of {count} acquisitions")
    return background_of(np.stack(frames))


def background_of(frames: np.ndarray) -> np.ndarray:
    """The empty scene from a stack (acquisitions, channels, samples): the per-sample median,
    robust to a passing reflection (the one estimator for ``background`` and calibration)."""
    return np.median(np.asarray(frames, dtype=np.float64), axis=0)


def save_background(path: str | Path, background: np.ndarray) -> Path:
    """Write a .npy file (or, for any other suffix, a spiel-csv frames file)."""
    path = Path(path)
    with atomic_write(path, "wb") as fh:  # never half a file where a good one was
        if path.suffix == ".npy":
            np.save(fh, background, allow_pickle=False)
        else:
            np.savetxt(fh, background, fmt="%.1f")
    return path
