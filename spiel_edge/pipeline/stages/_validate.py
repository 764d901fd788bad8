"""Input checks shared by the stage wrappers (kept out of the numba kernels)."""

from __future__ import annotations

import numpy as np

from spiel_edge.errors import InputError


def as_frames(frames: np.ndarray, name: str = "frames") -> np.ndarray:
    """A C-contiguous float64 (channels, samples) array of finite values, or InputError."""
    arr = np.asarray(frames)
    if arr.ndim != 2 or arr.shape[0] < 1 or arr.shape[1] < 2:
        raise InputError(f"{name} must be a 2-D (channels, samples) array, got shape {arr.shape}")
    if not np.issubdtype(arr.dtype, np.number):
        raise InputError(f"{name} must be numeric, got dtype {arr.dtype}")
    arr = np.ascontiguousarray(arr, dtype=np.float64)
    if not np.isfinite(arr).all():
        raise InputError(f"{name} contains NaN or infinite samples")
    return arr
