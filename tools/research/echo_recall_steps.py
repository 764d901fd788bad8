"""Per-channel echo recall of the front end (detect + MEMG) against labelled targets: pure
numpy helpers for ``tools.research.echo_recall`` (docs/localisation.md, "Two targets at one range").

A true target's echo on a channel is *recalled* when some detected echo's ToA (after MEMG)
lies within a tolerance of the target's ideal ToA there (labelled position, calibrated
geometry and delays). Nothing here reads files or runs the pipeline.
"""

from __future__ import annotations

import numpy as np

from spiel_edge.errors import InputError

GAP_EDGES = (1.0, 2.0, 3.0, 5.0, 8.0)  # samples to the nearest other truth: bins <1, 1-2, ..., >=8


def ideal_toa(
    paths_mm: np.ndarray, mm_per_sample: float, delays: np.ndarray, offset: np.ndarray | None = None
) -> np.ndarray:
    """Ideal ToA in samples (truths, channels) from echo paths (truths, channels) in mm: the
    path in samples plus each channel's delay (and an optional per-channel estimator offset)."""
    p = np.atleast_2d(np.asarray(paths_mm, dtype=np.float64))
    if mm_per_sample <= 0:
        raise InputError(f"mm_per_sample must be > 0, got {mm_per_sample}")
    d = np.asarray(delays, dtype=np.float64)
    if d.shape != (p.shape[1],):
        raise InputError(f"delays must have one value per channel ({p.shape[1]}), got {d.shape}")
    out = p / mm_per_sample + d
    return out if offset is None else out + np.asarray(offset, dtype=np.float64)


def nearest_echo(toa: np.ndarray, ideal: np.ndarray) -> np.ndarray:
    """Signed distance (samples; truths, channels) from each ideal ToA to the nearest detected
    echo on its channel; NaN where a channel has no echo. ``toa`` is (channels, echoes), NaN
    padded."""
    t = np.asarray(toa, dtype=np.float64)
    i = np.atleast_2d(np.asarray(ideal, dtype=np.float64))
    if t.ndim != 2 or i.shape[1] != t.shape[0]:
        raise InputError(
            f"toa (channels, echoes) and ideal (truths, channels) disagree: {t.shape}, {i.shape}"
        )
    diff = t[None, :, :] - i[:, :, None]
    absd = np.where(np.isfinite(diff), np.abs(diff), np.inf)
    k = absd.argmin(axis=2)
    out = np.take_along_axis(diff, k[..., None], axis=2)[..., 0]
    return np.where(np.isfinite(absd.min(axis=2)), out, np.nan)


def truth_gap(ideal: np.ndarray) -> np.ndarray:
    """Per truth and channel, |ideal ToA − the nearest other truth's| in samples (inf alone)."""
    i = np.atleast_2d(np.asarray(ideal, dtype=np.float64))
    d = np.abs(i[:, None, :] - i[None, :, :])
    n = len(i)
    d[np.arange(n), np.arange(n)] = np.inf
    return d.min(axis=1) if n > 1 else np.full(i.shape, np.inf)


def gap_bin(gap: np.ndarray, edges=GAP_EDGES) -> np.ndarray:
    """Bin index per gap: 0 for < edges[0], ..., len(edges) for >= edges[-1]."""
    return np.searchsorted(np.asarray(edges), np.asarray(gap), side="right")


def shared_echo(toa: np.ndarray, ideal: np.ndarray, tol: float) -> np.ndarray:
    """Per truth and channel: its nearest echo within ``tol`` is also the nearest echo of
    another truth within ``tol`` (one echo for two targets)."""
    t = np.asarray(toa, dtype=np.float64)
    i = np.atleast_2d(np.asarray(ideal, dtype=np.float64))
    diff = np.abs(t[None, :, :] - i[:, :, None])
    diff = np.where(np.isfinite(diff), diff, np.inf)
    k = diff.argmin(axis=2)
    hit = diff.min(axis=2) <= tol
    out = np.zeros(i.shape, dtype=np.bool_)
    for a in range(len(i)):
        for b in range(len(i)):
            if a != b:
                out[a] |= hit[a] & hit[b] & (k[a] == k[b])
    return out
