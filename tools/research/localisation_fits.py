"""Where the localisation error comes from: pure numpy helpers for the study in
``tools.research.localisation_study`` (docs/localisation.md).

Everything here works on arrays the study collects from the pipeline (per acquisition and
channel: the ToA the solve uses, the ideal ToA of the labelled position) and never reads files.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from spiel_edge.errors import InputError


def position_folds(xys: Sequence[Sequence[float]], k: int = 3) -> np.ndarray:
    """Fold index (0..k-1) per row, by (x, y) position: the distinct positions, sorted, are
    dealt round-robin, so every height of one position is in one fold (as in
    ``split_by_position``)."""
    if k < 2:
        raise InputError(f"k must be at least 2, got {k}")
    keys = [tuple(float(v) for v in xy[:2]) for xy in xys]
    order = {xy: i % k for i, xy in enumerate(sorted(set(keys)))}
    return np.array([order[xy] for xy in keys], dtype=np.int64)


def bias_and_noise(residual: np.ndarray, groups: Sequence) -> tuple[float, float, float]:
    """(total, between-group, within-group) standard deviation of ``residual`` (rows ×
    channels, NaN = none) where a group is one pose (all acquisitions of one position): the
    between part is the sd of the per-group, per-channel means (a bias that averaging
    acquisitions cannot remove), the within part the sd of what is left (frame-to-frame noise)."""
    r = np.asarray(residual, dtype=np.float64)
    if r.ndim != 2:
        raise InputError(f"residual must be (rows, channels), got shape {r.shape}")
    g = np.asarray(groups)
    if g.shape[0] != r.shape[0]:
        raise InputError("groups must have one entry per row of residual")
    means, left = [], []
    for key in np.unique(g):
        rows = r[g == key]
        counts = np.isfinite(rows).sum(0)
        mu = np.where(counts > 0, np.nansum(rows, 0) / np.maximum(counts, 1), np.nan)
        means.append(mu)
        left.append(rows - mu)
    return _sd(r), _sd(np.array(means)), _sd(np.vstack(left))


def _sd(a: np.ndarray) -> float:
    v = a[np.isfinite(a)]
    return float(v.std()) if v.size else float("nan")


def path_jacobian(position: np.ndarray, channels: np.ndarray, emitter: np.ndarray) -> np.ndarray:
    """d(echo path)/d(position) per channel: (channels, 3)."""
    p = np.asarray(position, dtype=np.float64)
    to_e = p - np.asarray(emitter, dtype=np.float64)
    to_r = p - np.asarray(channels, dtype=np.float64)
    ue = to_e / max(float(np.linalg.norm(to_e)), 1e-9)
    ur = to_r / np.maximum(np.linalg.norm(to_r, axis=1), 1e-9)[:, None]
    return ue[None, :] + ur


def position_sd_mm(
    position: np.ndarray, channels: np.ndarray, emitter: np.ndarray, path_sd_mm: float
) -> np.ndarray:
    """Per-axis standard deviation (mm) of the least-squares position when every channel's
    path has independent error ``path_sd_mm`` (linearised: the geometry's dilution)."""
    j = path_jacobian(position, channels, emitter)
    return np.sqrt(np.diag(np.linalg.pinv(j.T @ j))) * float(path_sd_mm)


def fit_delays_and_scale(
    toa: np.ndarray, ideal: np.ndarray, inlier: np.ndarray, *, scale: bool
) -> tuple[np.ndarray, float]:
    """Least squares ``toa = delay[channel] + k * ideal`` over the inlier echoes (rows ×
    channels): per-channel delays (samples) and, with ``scale``, one path scale k (k > 1: the
    ToA grows faster with range than the profile's speed of sound says), else k = 1."""
    t = np.asarray(toa, dtype=np.float64)
    i = np.asarray(ideal, dtype=np.float64)
    m = np.asarray(inlier, dtype=np.bool_)
    if t.ndim != 2 or t.shape != i.shape or m.shape != t.shape:
        raise InputError("toa, ideal and inlier must be (rows, channels) of one shape")
    ok = m & np.isfinite(t) & np.isfinite(i)
    n_ch = t.shape[1]
    if (ok.sum(0) < 2).any():
        raise InputError("every channel needs at least 2 inlier echoes")
    rows, cols = np.nonzero(ok)
    x = np.zeros((rows.size, n_ch + 1))
    x[np.arange(rows.size), cols] = 1.0
    x[:, n_ch] = i[rows, cols]
    y = t[rows, cols] - i[rows, cols]
    if not scale:
        x = x[:, :n_ch]
    beta, *_ = np.linalg.lstsq(x, y, rcond=None)
    return beta[:n_ch], 1.0 + (float(beta[n_ch]) if scale else 0.0)
