"""Stage 6, locate: the target where the echo-path ellipsoids intersect (PaCE, paper eq. 11-16).

Each listening channel n with echo path length d_n (mm) constrains the target p to the
ellipsoid |p - e| + |p - r_n| = d_n with foci at the emitter e and the receiver r_n; a
channel at the emitter is the sphere 2|p - e| = d_n. Instead of the paper's algebraic
quadric Q (whose scale differs per ellipsoid) we minimise the geometric residuals
|p - e| + |p - r_n| - d_n in mm by Levenberg-Marquardt: the residual then reads directly as
path error, and the problem stays well scaled for any geometry. The start point comes from
the linearisation around the monostatic range; the target is kept in front of the array.
"""

from __future__ import annotations

import math

import numpy as np

from spiel_edge._jit import jit
from spiel_edge.errors import InputError
from spiel_edge.pipeline.memg import solve_spd

MONOSTATIC_MM = 1.0  # a channel this close to the emitter is treated as the emitter itself


def locate(
    paths_mm: np.ndarray,
    channels_mm: np.ndarray,
    emitter_mm: np.ndarray,
    facing: np.ndarray,
    use: np.ndarray | None = None,
    *,
    weights: np.ndarray | None = None,
    max_iterations: int = 30,
) -> tuple[np.ndarray, float, bool]:
    """Return ``(position_mm, rms_residual_mm, ok)`` from per-channel echo path lengths.

    ``use`` masks channels (NaN paths are never used); at least 3 are needed. ``weights``
    (channels,), e.g. 1 / expected ToA error, weight the residuals (the reported rms is
    unweighted). The position is finite in every case; ``ok`` is False when the solve did
    not give a valid target in front of the array.
    """
    d = np.ascontiguousarray(paths_mm, dtype=np.float64)
    ch = np.ascontiguousarray(channels_mm, dtype=np.float64)
    if ch.ndim != 2 or ch.shape[1] != 3 or d.shape != (ch.shape[0],):
        raise InputError("paths_mm must be (channels,) and channels_mm (channels, 3)")
    mask = np.isfinite(d) if use is None else (np.asarray(use, dtype=np.bool_) & np.isfinite(d))
    w = np.ones(d.shape) if weights is None else np.ascontiguousarray(weights, dtype=np.float64)
    if w.shape != d.shape or not np.all(np.isfinite(w[mask]) & (w[mask] > 0)):
        raise InputError("weights must be (channels,) positive finite numbers")
    pos = np.zeros(3)
    ok, rms = locate_kernel(
        d,
        mask,
        w,
        np.ascontiguousarray(emitter_mm, dtype=np.float64),
        ch,
        np.ascontiguousarray(facing, dtype=np.float64),
        int(max_iterations),
        pos,
    )
    return pos, float(rms), bool(ok)


@jit
def _initial_guess(d, use, e, ch, facing, q):
    """Start point q (relative to the emitter) from the linearised ellipsoid equations."""
    radius = -1.0
    n_use = 0
    d_sum = 0.0
    for n in range(d.shape[0]):
        if use[n]:
            n_use += 1
            d_sum += d[n]
            s2 = 0.0
            for i in range(3):
                s2 += (ch[n, i] - e[i]) ** 2
            if s2 < MONOSTATIC_MM**2:
                radius = 0.5 * d[n]
    if radius <= 0.0:
        radius = 0.5 * d_sum / max(n_use, 1)
    # |q| = R and |q - s|^2 = (d - R)^2  =>  q . s = (R^2 + |s|^2 - (d - R)^2) / 2 (linear in q)
    a = np.zeros((3, 3))
    b = np.zeros(3)
    s = np.empty(3)
    for n in range(d.shape[0]):
        if not use[n]:
            continue
        for i in range(3):
            s[i] = ch[n, i] - e[i]
        s2 = s[0] * s[0] + s[1] * s[1] + s[2] * s[2]
        if s2 < MONOSTATIC_MM**2:
            continue
        rhs = 0.5 * (radius * radius + s2 - (d[n] - radius) ** 2)
        for i in range(3):
            b[i] += s[i] * rhs
            for j in range(3):
                a[i, j] += s[i] * s[j]
    trace = a[0, 0] + a[1, 1] + a[2, 2]
    for i in range(3):
        a[i, i] += 1e-6 * trace + 1e-9  # ridge: minimum-norm answer where the array is planar
    if not solve_spd(a, b, 3, q):
        q[:] = 0.0
    qf = q[0] * facing[0] + q[1] * facing[1] + q[2] * facing[2]
    qq = q[0] * q[0] + q[1] * q[1] + q[2] * q[2]
    disc = qf * qf - (qq - radius * radius)
    t = -qf + math.sqrt(disc) if disc > 0.0 else 0.5 * radius
    for i in range(3):
        q[i] += t * facing[i]


@jit
def _cost(d, use, w, e, ch, p):
    """Weighted and plain sums of squared path residuals, and the channels used."""
    weighted = 0.0
    plain = 0.0
    n_use = 0
    for n in range(d.shape[0]):
        if use[n]:
            r = (
                math.sqrt((p[0] - e[0]) ** 2 + (p[1] - e[1]) ** 2 + (p[2] - e[2]) ** 2)
                + math.sqrt(
                    (p[0] - ch[n, 0]) ** 2 + (p[1] - ch[n, 1]) ** 2 + (p[2] - ch[n, 2]) ** 2
                )
                - d[n]
            )
            weighted += (w[n] * r) ** 2
            plain += r * r
            n_use += 1
    return weighted, plain, n_use


@jit
def _gauss_newton(d, use, w, e, ch, p, max_iter):
    # scalars and buffers made once, not per channel or try: the same arithmetic, no
    # allocations in the loop (the association solves this for every candidate combination)
    a = np.empty((3, 3))
    damped = np.empty((3, 3))
    b = np.empty(3)
    step = np.empty(3)
    trial = np.empty(3)
    lam = 1e-3
    cost, plain, n_use = _cost(d, use, w, e, ch, p)
    for _ in range(max_iter):
        a[:, :] = 0.0
        b[:] = 0.0
        for n in range(d.shape[0]):
            if not use[n]:
                continue
            ue0, ue1, ue2 = p[0] - e[0], p[1] - e[1], p[2] - e[2]
            ur0, ur1, ur2 = p[0] - ch[n, 0], p[1] - ch[n, 1], p[2] - ch[n, 2]
            le = max(math.sqrt(ue0**2 + ue1**2 + ue2**2), 1e-9)
            lr = max(math.sqrt(ur0**2 + ur1**2 + ur2**2), 1e-9)
            r = w[n] * (le + lr - d[n])
            g0 = w[n] * (ue0 / le + ur0 / lr)
            g1 = w[n] * (ue1 / le + ur1 / lr)
            g2 = w[n] * (ue2 / le + ur2 / lr)
            b[0] -= g0 * r
            b[1] -= g1 * r
            b[2] -= g2 * r
            a[0, 0] += g0 * g0
            a[1, 0] += g1 * g0
            a[1, 1] += g1 * g1
            a[2, 0] += g2 * g0
            a[2, 1] += g2 * g1
            a[2, 2] += g2 * g2
        a[0, 1] = a[1, 0]
        a[0, 2] = a[2, 0]
        a[1, 2] = a[2, 1]
        accepted = False
        for _try in range(6):
            damped[:, :] = a
            for i in range(3):
                damped[i, i] += lam * (a[i, i] + 1e-9)
            if not solve_spd(damped, b, 3, step):
                lam *= 10.0
                continue
            for i in range(3):
                trial[i] = p[i] + step[i]
            new_cost, new_plain, _ = _cost(d, use, w, e, ch, trial)
            if new_cost <= cost:
                small = abs(step[0]) + abs(step[1]) + abs(step[2]) < 1e-4
                p[:] = trial
                cost, plain = new_cost, new_plain
                lam = max(lam * 0.3, 1e-9)
                accepted = not small
                break
            lam *= 10.0
        if not accepted:
            break
    return math.sqrt(plain / max(n_use, 1))


@jit
def locate_kernel(d, use, w, e, ch, facing, max_iter, out):
    """The solve for other kernels (association tries candidate echo sets with it): paths
    ``d``, channel mask ``use``, weights ``w``; the position into ``out``; (ok, rms mm)."""
    n_use = 0
    for n in range(d.shape[0]):
        if use[n]:
            n_use += 1
    out[:] = 0.0
    if n_use < 3:
        return False, math.inf
    q = np.empty(3)
    _initial_guess(d, use, e, ch, facing, q)
    p = q + e
    rms = _gauss_newton(d, use, w, e, ch, p, max_iter)
    ahead = (p[0] - e[0]) * facing[0] + (p[1] - e[1]) * facing[1] + (p[2] - e[2]) * facing[2]
    if ahead < 0.0:
        # the mirror image behind a (near-)planar array fits as well: take the front one
        for i in range(3):
            p[i] -= 2.0 * ahead * facing[i]
        rms = _gauss_newton(d, use, w, e, ch, p, max_iter)
        ahead = (p[0] - e[0]) * facing[0] + (p[1] - e[1]) * facing[1] + (p[2] - e[2]) * facing[2]
    finite = (
        math.isfinite(rms) and math.isfinite(p[0]) and math.isfinite(p[1]) and math.isfinite(p[2])
    )
    if not finite:
        out[:] = 0.0
        return False, math.inf
    out[:] = p
    return ahead > 0.0, rms
