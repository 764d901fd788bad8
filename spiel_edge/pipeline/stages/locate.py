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

MONOSTATIC_MM = 1.0  # a channel this close to the emitter is treated as the emitter itself
# Every divisor in the compiled solve is nonzero by construction (lengths floored at 1e-9,
# Cholesky pivots > 1e-150, channel counts >= 1), so numba's zero-division checks (the
# default "python" error model) can never fire: "numpy" drops them, the same bits.
_solve = jit(error_model="numpy")


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


@_solve
def solve3(a00, a10, a11, a20, a21, a22, b0, b1, b2):
    """:func:`spiel_edge.pipeline.stages.memg.solve_spd` for n = 3 on scalars (the lower triangle of
    a symmetric a): the same operations in the same order, so the same bits, without arrays.
    Returns (ok, x0, x1, x2); ok False when a is not positive definite."""
    d = a00
    if d <= 1e-300:
        return False, 0.0, 0.0, 0.0
    d = math.sqrt(d)
    l00 = d
    l10 = a10 / d
    l20 = a20 / d
    d = a11
    d -= l10 * l10
    if d <= 1e-300:
        return False, 0.0, 0.0, 0.0
    d = math.sqrt(d)
    l11 = d
    s = a21
    s -= l20 * l10
    l21 = s / d
    d = a22
    d -= l20 * l20
    d -= l21 * l21
    if d <= 1e-300:
        return False, 0.0, 0.0, 0.0
    l22 = math.sqrt(d)
    x0 = b0 / l00
    s = b1
    s -= l10 * x0
    x1 = s / l11
    s = b2
    s -= l20 * x0
    s -= l21 * x1
    x2 = s / l22
    x2 = x2 / l22
    s = x1
    s -= l21 * x2
    x1 = s / l11
    s = x0
    s -= l10 * x1
    s -= l20 * x2
    x0 = s / l00
    return True, x0, x1, x2


@_solve
def _initial_guess(d, use, e, ch, facing):
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
    # the normal equations' lower triangle and right side as scalars
    a00 = a10 = a11 = a20 = a21 = a22 = 0.0
    b0 = b1 = b2 = 0.0
    for n in range(d.shape[0]):
        if not use[n]:
            continue
        s0 = ch[n, 0] - e[0]
        s1 = ch[n, 1] - e[1]
        s2_ = ch[n, 2] - e[2]
        s2 = s0 * s0 + s1 * s1 + s2_ * s2_
        if s2 < MONOSTATIC_MM**2:
            continue
        rhs = 0.5 * (radius * radius + s2 - (d[n] - radius) ** 2)
        b0 += s0 * rhs
        b1 += s1 * rhs
        b2 += s2_ * rhs
        a00 += s0 * s0
        a10 += s1 * s0
        a11 += s1 * s1
        a20 += s2_ * s0
        a21 += s2_ * s1
        a22 += s2_ * s2_
    trace = a00 + a11 + a22
    ridge = 1e-6 * trace + 1e-9  # minimum-norm answer where the array is planar
    a00 += ridge
    a11 += ridge
    a22 += ridge
    ok, q0, q1, q2 = solve3(a00, a10, a11, a20, a21, a22, b0, b1, b2)
    if not ok:
        q0 = q1 = q2 = 0.0
    qf = q0 * facing[0] + q1 * facing[1] + q2 * facing[2]
    qq = q0 * q0 + q1 * q1 + q2 * q2
    disc = qf * qf - (qq - radius * radius)
    t = -qf + math.sqrt(disc) if disc > 0.0 else 0.5 * radius
    return q0 + t * facing[0], q1 + t * facing[1], q2 + t * facing[2]


@_solve
def _cost(d, use, w, e, ch, p0, p1, p2):
    """Weighted and plain sums of squared path residuals at p, and the channels used."""
    weighted = 0.0
    plain = 0.0
    n_use = 0
    to_emitter = math.sqrt((p0 - e[0]) ** 2 + (p1 - e[1]) ** 2 + (p2 - e[2]) ** 2)
    for n in range(d.shape[0]):
        if use[n]:
            r = (
                to_emitter
                + math.sqrt((p0 - ch[n, 0]) ** 2 + (p1 - ch[n, 1]) ** 2 + (p2 - ch[n, 2]) ** 2)
                - d[n]
            )
            weighted += (w[n] * r) ** 2
            plain += r * r
            n_use += 1
    return weighted, plain, n_use


@_solve
def _gauss_newton(d, use, w, e, ch, p0, p1, p2, max_iter):
    """Levenberg-Marquardt from p; (rms, p0, p1, p2). Scalars only (the association solves
    this for every candidate combination): no arrays made, |p - e| once per point."""
    lam = 1e-3
    cost, plain, n_use = _cost(d, use, w, e, ch, p0, p1, p2)
    for _ in range(max_iter):
        a00 = a10 = a11 = a20 = a21 = a22 = 0.0
        b0 = b1 = b2 = 0.0
        ue0, ue1, ue2 = p0 - e[0], p1 - e[1], p2 - e[2]
        le = max(math.sqrt(ue0**2 + ue1**2 + ue2**2), 1e-9)
        for n in range(d.shape[0]):
            if not use[n]:
                continue
            ur0, ur1, ur2 = p0 - ch[n, 0], p1 - ch[n, 1], p2 - ch[n, 2]
            lr = max(math.sqrt(ur0**2 + ur1**2 + ur2**2), 1e-9)
            r = w[n] * (le + lr - d[n])
            g0 = w[n] * (ue0 / le + ur0 / lr)
            g1 = w[n] * (ue1 / le + ur1 / lr)
            g2 = w[n] * (ue2 / le + ur2 / lr)
            b0 -= g0 * r
            b1 -= g1 * r
            b2 -= g2 * r
            a00 += g0 * g0
            a10 += g1 * g0
            a11 += g1 * g1
            a20 += g2 * g0
            a21 += g2 * g1
            a22 += g2 * g2
        accepted = False
        for _try in range(6):
            ok, s0, s1, s2 = solve3(
                a00 + lam * (a00 + 1e-9),
                a10,
                a11 + lam * (a11 + 1e-9),
                a20,
                a21,
                a22 + lam * (a22 + 1e-9),
                b0,
                b1,
                b2,
            )
            if not ok:
                lam *= 10.0
                continue
            t0, t1, t2 = p0 + s0, p1 + s1, p2 + s2
            new_cost, new_plain, _ = _cost(d, use, w, e, ch, t0, t1, t2)
            if new_cost <= cost:
                small = abs(s0) + abs(s1) + abs(s2) < 1e-4
                p0, p1, p2 = t0, t1, t2
                cost, plain = new_cost, new_plain
                lam = max(lam * 0.3, 1e-9)
                accepted = not small
                break
            lam *= 10.0
        if not accepted:
            break
    return math.sqrt(plain / max(n_use, 1)), p0, p1, p2


@_solve
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
    q0, q1, q2 = _initial_guess(d, use, e, ch, facing)
    rms, p0, p1, p2 = _gauss_newton(d, use, w, e, ch, q0 + e[0], q1 + e[1], q2 + e[2], max_iter)
    ahead = (p0 - e[0]) * facing[0] + (p1 - e[1]) * facing[1] + (p2 - e[2]) * facing[2]
    if ahead < 0.0:
        # the mirror image behind a (near-)planar array fits as well: take the front one
        p0 -= 2.0 * ahead * facing[0]
        p1 -= 2.0 * ahead * facing[1]
        p2 -= 2.0 * ahead * facing[2]
        rms, p0, p1, p2 = _gauss_newton(d, use, w, e, ch, p0, p1, p2, max_iter)
        ahead = (p0 - e[0]) * facing[0] + (p1 - e[1]) * facing[1] + (p2 - e[2]) * facing[2]
    finite = math.isfinite(rms) and math.isfinite(p0) and math.isfinite(p1) and math.isfinite(p2)
    if not finite:
        return False, math.inf
    out[0] = p0
    out[1] = p1
    out[2] = p2
    return ahead > 0.0, rms
