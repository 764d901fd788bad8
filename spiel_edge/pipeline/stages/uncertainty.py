"""Position uncertainty: a 3x3 covariance (mm^2) per located target.

Linearised least squares: with J the (channels x 3) Jacobian of the echo paths
|p - e| + |p - r_n| at the solution and sigma_n each used channel's expected path error
(echo_quality's expected ToA error times mm per sample),

    C = scale^2 * (J^T diag(1 / sigma^2) J + I / PRIOR_MM^2)^-1 + floor_mm^2 * I

The weak prior (PRIOR_MM, far larger than the field of view) keeps C finite, symmetric and
positive definite when the used channels barely constrain a direction (3 channels of a planar
array near its plane); ``floor_mm`` stands for what the ToA model leaves out (geometry and
delay calibration errors, wrong echoes), the same in every direction; ``scale`` and ``floor_mm``
are fitted on the training positions so that the truth lies in
the 95 % ellipsoid (Mahalanobis^2 <= CHI2_95_3DOF) for about 95 % of targets (see
docs/scene.md). When more than 3 channels are used the covariance is also inflated by the
solve's normalised residual (weighted rss / (n - 3)) when that exceeds 1: a poor fit is less
certain than its geometry says.
"""

from __future__ import annotations

import math

import numpy as np

from spiel_edge._jit import jit
from spiel_edge.errors import InputError

PRIOR_MM = 2000.0  # std of the implicit prior per axis: far outside any echo path of interest
CHI2_95_3DOF = 7.815  # 95 % quantile of chi-square with 3 degrees of freedom
MAX_INFLATION = 100.0  # bound on the residual inflation of the variance


def position_covariance(
    position_mm: np.ndarray,
    paths_mm: np.ndarray,
    sigma_mm: np.ndarray,
    use: np.ndarray,
    channels_mm: np.ndarray,
    emitter_mm: np.ndarray,
    scale: float = 1.0,
    floor_mm: float = 0.0,
) -> np.ndarray:
    """Covariance (3, 3) in mm^2 of ``position_mm`` located from ``paths_mm`` (channels,) of
    the ``use`` channels, each with expected path error ``sigma_mm`` (channels,). Always
    finite, symmetric and positive definite."""
    p = np.ascontiguousarray(position_mm, dtype=np.float64)
    d = np.ascontiguousarray(paths_mm, dtype=np.float64)
    s = np.ascontiguousarray(sigma_mm, dtype=np.float64)
    ch = np.ascontiguousarray(channels_mm, dtype=np.float64)
    u = np.ascontiguousarray(use, dtype=np.bool_) & np.isfinite(d) & np.isfinite(s) & (s > 0)
    if p.shape != (3,) or ch.ndim != 2 or ch.shape[1] != 3 or d.shape != (ch.shape[0],):
        raise InputError(
            "position_mm must be (3,), paths_mm (channels,), channels_mm (channels, 3)"
        )
    if s.shape != d.shape or u.shape != d.shape:
        raise InputError("sigma_mm and use must be (channels,) like paths_mm")
    if not (math.isfinite(scale) and scale > 0):
        raise InputError(f"scale must be a positive finite number, got {scale}")
    if not (math.isfinite(floor_mm) and floor_mm >= 0):
        raise InputError(f"floor_mm must be a finite number >= 0, got {floor_mm}")
    out = np.empty((3, 3))
    e = np.ascontiguousarray(emitter_mm, dtype=np.float64)
    if not np.all(np.isfinite(p)):
        p = np.zeros(3)
    covariance_kernel(p, d, s, u, ch, e, float(scale), float(floor_mm), out)
    return out


@jit
def covariance_kernel(p, d, sigma, use, ch, e, scale, floor_mm, out):
    a = np.zeros((3, 3))
    rss = 0.0
    n_use = 0
    le = max(math.sqrt((p[0] - e[0]) ** 2 + (p[1] - e[1]) ** 2 + (p[2] - e[2]) ** 2), 1e-9)
    for n in range(d.shape[0]):
        if not use[n]:
            continue
        lr = max(
            math.sqrt((p[0] - ch[n, 0]) ** 2 + (p[1] - ch[n, 1]) ** 2 + (p[2] - ch[n, 2]) ** 2),
            1e-9,
        )
        g = np.empty(3)
        for i in range(3):
            g[i] = (p[i] - e[i]) / le + (p[i] - ch[n, i]) / lr
        w = 1.0 / (sigma[n] * sigma[n])
        for i in range(3):
            for j in range(3):
                a[i, j] += w * g[i] * g[j]
        r = le + lr - d[n]
        rss += w * r * r
        n_use += 1
    for i in range(3):
        a[i, i] += 1.0 / (PRIOR_MM * PRIOR_MM)
    inflation = 1.0
    if n_use > 3:
        inflation = min(max(rss / (n_use - 3), 1.0), MAX_INFLATION)
    _inverse_sym3(a, out)
    f = scale * scale * inflation
    for i in range(3):
        for j in range(i, 3):
            v = 0.5 * (out[i, j] + out[j, i]) * f
            out[i, j] = v
            out[j, i] = v
        out[i, i] += floor_mm * floor_mm


@jit
def _inverse_sym3(a, out):
    """Inverse of a symmetric positive definite 3x3 matrix by its adjugate."""
    c00 = a[1, 1] * a[2, 2] - a[1, 2] * a[2, 1]
    c01 = a[1, 2] * a[2, 0] - a[1, 0] * a[2, 2]
    c02 = a[1, 0] * a[2, 1] - a[1, 1] * a[2, 0]
    det = a[0, 0] * c00 + a[0, 1] * c01 + a[0, 2] * c02
    out[0, 0] = c00 / det
    out[1, 0] = c01 / det
    out[2, 0] = c02 / det
    out[0, 1] = (a[0, 2] * a[2, 1] - a[0, 1] * a[2, 2]) / det
    out[1, 1] = (a[0, 0] * a[2, 2] - a[0, 2] * a[2, 0]) / det
    out[2, 1] = (a[0, 1] * a[2, 0] - a[0, 0] * a[2, 1]) / det
    out[0, 2] = (a[0, 1] * a[1, 2] - a[0, 2] * a[1, 1]) / det
    out[1, 2] = (a[0, 2] * a[1, 0] - a[0, 0] * a[1, 2]) / det
    out[2, 2] = (a[0, 0] * a[1, 1] - a[0, 1] * a[1, 0]) / det


def mahalanobis2(error_mm: np.ndarray, covariance_mm2: np.ndarray) -> float:
    """Squared Mahalanobis distance of an error under a covariance (inside the 95 % ellipsoid
    when <= CHI2_95_3DOF)."""
    e = np.asarray(error_mm, dtype=np.float64)
    return float(e @ np.linalg.solve(np.asarray(covariance_mm2, dtype=np.float64), e))
