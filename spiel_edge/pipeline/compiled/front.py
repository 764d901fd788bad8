"""The fused path's front kernel: one compiled call from frames to echo features.

``_front_kernel`` runs the finite check, preprocess (with the RF envelope), detect, memg (and
the merged-echo split), features and their ToA ordering on a Workspace's buffers, calling the
staged stages' kernels in their order, so its features are the staged ones bit for bit
(tests/core/test_fused.py). Its 13 scalars come from :func:`front_scalars`; the back kernels
that run a whole acquisition in one call (``back._acquisition_kernel``,
``back_scene._scene_acquisition_kernel``) take them packed (:func:`front_packed`).
"""

from __future__ import annotations

import numpy as np

from spiel_edge._jit import jit
from spiel_edge.errors import InputError
from spiel_edge.pipeline.stages.detect import _detect_kernel
from spiel_edge.pipeline.stages.features import TOA_CODES, TOA_COLUMN, _features_kernel
from spiel_edge.pipeline.stages.memg import _memg_kernel
from spiel_edge.pipeline.stages.preprocess import _envelope_kernel, _preprocess_kernel
from spiel_edge.pipeline.stages.split import _split_kernel

FRAMES_NOT_FINITE, BACKGROUND_NOT_FINITE = 1, 2


def front_scalars(profile) -> tuple:
    """The front kernel's scalar arguments for a profile, in its order."""
    acq, d, m = profile.acquisition, profile.detect, profile.memg
    cycles_per_sample = acq.carrier_hz / acq.sample_rate_hz
    return (
        int(profile.preprocess.blind_zone_samples),
        acq.signal == "rf",
        float(cycles_per_sample),
        max(1, int(round(0.5 / cycles_per_sample))),  # as envelope()
        float(d.threshold),
        float(d.threshold * d.hysteresis),
        float(d.min_amplitude),
        float(m.mu_window),
        int(m.max_iterations),
        bool(m.split_merged),
        float(m.split_min_sigma),
        float(m.split_max_cost_ratio),
        TOA_CODES[m.toa],
    )


_INT_SLOTS = (0, 1, 3, 8, 9, 12)  # front_scalars' integers and flags, in _packed_front's order
_FLOAT_SLOTS = (2, 4, 5, 6, 7, 10, 11)


def front_packed(scalars: tuple) -> tuple[np.ndarray, np.ndarray]:
    """:func:`front_scalars` as (int64 array, float64 array) for :func:`_packed_front`."""
    ints = np.array([int(scalars[i]) for i in _INT_SLOTS], dtype=np.int64)
    return ints, np.array([scalars[i] for i in _FLOAT_SLOTS], dtype=np.float64)


def raise_for(status: int) -> None:
    """The InputError of a non-zero front status (the staged path's messages)."""
    if status == FRAMES_NOT_FINITE:
        raise InputError("frames contains NaN or infinite samples")
    if status == BACKGROUND_NOT_FINITE:
        raise InputError("background contains NaN or infinite samples")


@jit(inline="always")
def _packed_front(
    y, bg, fi, ff, env, bg_env, cleaned, peaks, ws_counts, params, iterations, unsorted,
    ws_features, features, counts,
):  # fmt: skip
    """:func:`_front_kernel` on :func:`front_packed`'s arrays ``fi`` and ``ff``, then its
    features and counts copied into the caller's fresh ``features`` and ``counts``: the
    front's status (0 when done)."""
    status = _front_kernel(
        y, bg, fi[0], fi[1] != 0, ff[0], fi[2], ff[1], ff[2], ff[3], ff[4], fi[3], fi[4] != 0,
        ff[5], ff[6], fi[5], env, bg_env, cleaned, peaks, ws_counts, params, iterations,
        unsorted, ws_features,
    )  # fmt: skip
    if status == 0:
        features[:] = ws_features
        counts[:] = ws_counts
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
    blind,
    rf,
    carrier,
    half_width,
    hi,
    lo,
    min_amp,
    mu_window,
    max_iter,
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
        _envelope_kernel(y, carrier, half_width, env)
        y = env
        if bg.shape[0] > 0:
            _envelope_kernel(bg, carrier, half_width, bg_env)
            bg = bg_env
    _preprocess_kernel(y, bg, blind, cleaned)
    peaks[:, :] = -1
    counts[:] = 0
    _detect_kernel(cleaned, hi, lo, min_amp, blind, peaks, counts)
    params[:, :, :] = np.nan
    iterations[:, :] = 0
    _memg_kernel(cleaned, peaks, counts, mu_window, max_iter, params, iterations)
    if split:
        _split_kernel(
            cleaned,
            peaks,
            counts,
            params,
            iterations,
            split_min_sigma,
            split_max_ratio,
            mu_window,
            max_iter,
        )
    unsorted[:, :, :] = np.nan
    _features_kernel(cleaned, params, peaks, toa_code, unsorted)
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
