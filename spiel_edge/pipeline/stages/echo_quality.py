"""Between associate and locate: how far to trust, and how to correct, each matched ToA.

Envelope subtraction cannot undo the interference of a target echo with a background echo
at the same time, so an echo that sits on strong background is less reliable, and shifted:
early when the background peak comes after it (its tail was subtracted away), late when it
comes before. Weak echoes are less reliable too. Per matched echo, with ``ratio`` = background
peak / frame peak within BACKGROUND_WINDOW samples of the echo:

    expected error = toa_sigma_samples + toa_sigma_per_background * ratio + toa_sigma_alpha_counts / alpha
    ToA shift      = -toa_shift_background_after * ratio   (background peak > 0.5 sample after)
                     -toa_shift_background_before * ratio  (background peak > 0.5 sample before)

The profile's ``[locate]`` values were fitted on the training positions of spiel-icra23.
"""

from __future__ import annotations

import math

import numpy as np

from spiel_edge._jit import jit
from spiel_edge.errors import InputError
from spiel_edge.profile.schema import LocateSpec

BACKGROUND_WINDOW = 3  # samples either side of an echo where background peaks distort it
SIDE_SAMPLES = 0.5  # a background peak closer than this to the echo is "at" it: no shift


def echo_quality(
    frames: np.ndarray,
    background: np.ndarray | None,
    toa: np.ndarray,
    alpha: np.ndarray,
    spec: LocateSpec,
) -> tuple[np.ndarray, np.ndarray]:
    """``(weights, shift)`` per channel for the matched echoes (``toa``, ``alpha`` per channel,
    NaN where none): weights = 1 / expected ToA error (samples), shift = the correction to add
    to the ToA (samples). Without a background only the strength term applies."""
    y = np.ascontiguousarray(frames, dtype=np.float64)
    bg = (
        np.zeros((0, 0))
        if background is None
        else np.ascontiguousarray(background, dtype=np.float64)
    )
    if bg.size and bg.shape != y.shape:
        raise InputError(f"background shape {bg.shape} does not match frames shape {y.shape}")
    params = np.array(
        [
            spec.toa_sigma_samples,
            spec.toa_sigma_per_background,
            spec.toa_sigma_alpha_counts,
            spec.toa_shift_background_after,
            spec.toa_shift_background_before,
        ]
    )
    weights = np.empty(y.shape[0])
    shift = np.empty(y.shape[0])
    echo_quality_kernel(
        y,
        bg,
        np.ascontiguousarray(toa, dtype=np.float64),
        np.ascontiguousarray(alpha, dtype=np.float64),
        params,
        weights,
        shift,
    )
    return weights, shift


@jit
def echo_quality_kernel(y, bg, toa, alpha, params, weights, shift):
    base, per_background, alpha_counts, shift_after, shift_before = (
        params[0],
        params[1],
        params[2],
        params[3],
        params[4],
    )
    n_ch, n_t = y.shape
    for c in range(n_ch):
        sigma = base
        shift[c] = 0.0
        if not math.isnan(toa[c]):
            if bg.shape[0] == n_ch:
                centre = int(round(min(max(toa[c], 0.0), n_t - 1.0)))
                lo = max(centre - BACKGROUND_WINDOW, 0)
                hi = min(centre + BACKGROUND_WINDOW, n_t)
                bg_peak, at, y_peak = -1.0, lo, 1.0
                for t in range(lo, hi):
                    if bg[c, t] > bg_peak:
                        bg_peak, at = bg[c, t], t
                    y_peak = max(y_peak, y[c, t])
                ratio = max(bg_peak, 0.0) / y_peak
                sigma += per_background * ratio
                if at - toa[c] > SIDE_SAMPLES:
                    shift[c] = -shift_after * ratio
                elif at - toa[c] < -SIDE_SAMPLES:
                    shift[c] = -shift_before * ratio
            if not math.isnan(alpha[c]):
                sigma += alpha_counts / max(alpha[c], 1.0)
        weights[c] = 1.0 / sigma
