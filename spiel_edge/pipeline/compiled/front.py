"""The front kernel: from frames to echo features, the first part of both acquisition kernels.

``_front_kernel`` runs the finite check, preprocess (with the RF envelope), detect, memg (and
the merged-echo split), features and their ToA ordering on a Workspace's buffers, calling the
staged stages' kernels in their order, so its features are the staged ones bit for bit
(tests/core/test_fused.py). The acquisition kernels (``one_target``, ``several_targets``)
call it through :func:`packed_front` with its settings packed (``abi.front_constants``).
"""

from __future__ import annotations

import numpy as np

from spiel_edge._jit import jit
from spiel_edge.errors import InputError
from spiel_edge.pipeline.compiled.abi import (
    FF_CARRIER,
    FF_HI,
    FF_LO,
    FF_MIN_AMP,
    FF_MU_WINDOW,
    FF_SPLIT_RATIO,
    FF_SPLIT_SIGMA,
    FI_BLIND,
    FI_HALF_WIDTH,
    FI_MAX_ITER,
    FI_RF,
    FI_SPLIT,
    FI_TOA,
)
from spiel_edge.pipeline.stages.detect import detect_kernel
from spiel_edge.pipeline.stages.features import TOA_COLUMN, features_kernel
from spiel_edge.pipeline.stages.memg import memg_kernel
from spiel_edge.pipeline.stages.preprocess import envelope_kernel, preprocess_kernel
from spiel_edge.pipeline.stages.split import split_kernel

FRAMES_NOT_FINITE, BACKGROUND_NOT_FINITE = 1, 2


def raise_for(status: int) -> None:
    """The InputError of a non-zero front status (the staged path's messages)."""
    if status == FRAMES_NOT_FINITE:
        raise InputError("frames contains NaN or infinite samples")
    if status == BACKGROUND_NOT_FINITE:
        raise InputError("background contains NaN or infinite samples")


@jit(inline="always")
def packed_front(
    y, bg, fi, ff, env, bg_env, cleaned, peaks, ws_counts, params, iterations, unsorted,
    ws_features, features, counts,
):  # fmt: skip
    """:func:`_front_kernel` on the settings ``fi`` and ``ff`` (abi.FRONT_INTS, FRONT_FLOATS), then its
    features and counts copied into the caller's fresh ``features`` and ``counts``: the
    front's status (0 when done)."""
    status = _front_kernel(
        y, bg, fi[FI_BLIND], fi[FI_RF] != 0, ff[FF_CARRIER], fi[FI_HALF_WIDTH], ff[FF_HI],
        ff[FF_LO], ff[FF_MIN_AMP], ff[FF_MU_WINDOW], fi[FI_MAX_ITER], fi[FI_SPLIT] != 0,
        ff[FF_SPLIT_SIGMA], ff[FF_SPLIT_RATIO], fi[FI_TOA], env, bg_env, cleaned, peaks,
        ws_counts, params, iterations, unsorted, ws_features,
    )  # fmt: skip
    if status == 0:  # element loops: an array-to-array slice assignment would compile
        # numba's shape-mismatch message (its string formatting) into every acquisition
        # kernel, 50 MiB and seconds of each cold compile (docs/first-start.md)
        n_ch, k_max, n_f = features.shape
        for c in range(n_ch):
            counts[c] = ws_counts[c]
            for k in range(k_max):
                for f in range(n_f):
                    features[c, k, f] = ws_features[c, k, f]
    return status


@jit
def _all_finite(a):
    ok = True
    for i in range(a.shape[0]):
        for j in range(a.shape[1]):
            ok &= np.isfinite(a[i, j])
    return ok


@jit
def _front_kernel(
    y,
    bg,
    blind_zone,
    rf,
    carrier,
    half_width,
    threshold_hi,
    threshold_lo,
    min_amplitude,
    mu_window,
    max_iterations,
    split,
    split_min_sigma,
    split_max_ratio,
    toa_code,
    env,
    bg_env,
    cleaned,
    peaks,
    counts,
    params,
    iterations,
    unsorted,
    features,
):
    """Finite check, preprocess, detect, memg (and the merged-echo split), features and the ToA ordering; 0 when done,
    else FRAMES_NOT_FINITE or BACKGROUND_NOT_FINITE."""
    if not _all_finite(y):
        return FRAMES_NOT_FINITE
    if bg.shape[0] > 0 and not _all_finite(bg):
        return BACKGROUND_NOT_FINITE
    if rf:
        envelope_kernel(y, carrier, half_width, env)
        y = env
        if bg.shape[0] > 0:
            envelope_kernel(bg, carrier, half_width, bg_env)
            bg = bg_env
    preprocess_kernel(y, bg, blind_zone, cleaned)
    peaks[:, :] = -1
    counts[:] = 0
    detect_kernel(cleaned, threshold_hi, threshold_lo, min_amplitude, blind_zone, peaks, counts)
    params[:, :, :] = np.nan
    iterations[:, :] = 0
    memg_kernel(cleaned, peaks, counts, mu_window, max_iterations, params, iterations)
    if split:
        split_kernel(
            cleaned,
            peaks,
            counts,
            params,
            iterations,
            split_min_sigma,
            split_max_ratio,
            mu_window,
            max_iterations,
        )
    unsorted[:, :, :] = np.nan
    features_kernel(cleaned, params, peaks, toa_code, unsorted)
    _order_by_toa(unsorted, features)
    return 0


@jit
def _order_by_toa(unsorted, out):
    """Each channel's rows by ascending ToA, NaN last, ties in input order (as a stable sort)."""
    n_ch, k_max, n_f = unsorted.shape
    order = np.empty(k_max, dtype=np.int64)
    for c in range(n_ch):
        for k in range(k_max):
            key = unsorted[c, k, TOA_COLUMN]
            key = np.inf if np.isnan(key) else key
            i = k - 1
            while i >= 0:
                prev = unsorted[c, order[i], TOA_COLUMN]
                prev = np.inf if np.isnan(prev) else prev
                if prev <= key:
                    break
                order[i + 1] = order[i]
                i -= 1
            order[i + 1] = k
        for k in range(k_max):
            for f in range(n_f):
                out[c, k, f] = unsorted[c, order[k], f]
