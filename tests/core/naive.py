"""Plain numpy/scipy references for the numba kernels (slow, obvious, independent)."""

from __future__ import annotations

import itertools
import math

import numpy as np
from numba import njit

from spiel_edge.measure.reference import detect, emg, locate, paths, preprocess  # noqa: F401
from spiel_edge.pipeline.stages import memg


def envelope(rf, f):
    n_t = rf.shape[1]
    t = np.arange(n_t)
    half = max(1, int(round(0.5 / f)))
    out = np.empty_like(rf, dtype=float)
    for c in range(rf.shape[0]):
        v = rf[c] - rf[c].mean()
        i = v * np.cos(2 * np.pi * f * t)
        q = -v * np.sin(2 * np.pi * f * t)
        for k in range(n_t):
            lo, hi = max(0, k - half), min(n_t, k + half + 1)
            out[c, k] = 2 * np.hypot(i[lo:hi].sum(), q[lo:hi].sum()) / (hi - lo)
    return out


def brute_force_association(
    paths_mm, counts, channels, emitter, facing, weights, strength, min_ch, max_diff, locate_fn
):
    """Every combination of one echo (or none) per channel, the same cost as the kernel."""
    best, best_cost = None, np.inf
    costs = brute_force_costs(
        paths_mm, counts, channels, emitter, facing, weights, strength, min_ch, max_diff, locate_fn
    )
    for choice, cost in costs.items():
        if cost < best_cost:
            best, best_cost = choice, cost
    return best, best_cost


def brute_force_costs(
    paths_mm, counts, channels, emitter, facing, weights, strength, min_ch, max_diff, locate_fn
):
    """{choice: cost} of every feasible combination, in the kernel's search order."""
    max_res, penalty, sw, rw = weights
    n_ch = len(counts)
    out = {}
    for choice in itertools.product(*[range(-1, int(k)) for k in counts]):
        used = [c for c in range(n_ch) if choice[c] >= 0]
        if len(used) < min_ch:
            continue
        if any(
            abs(paths_mm[i, choice[i]] - paths_mm[j, choice[j]]) > max_diff[i, j]
            for i in used
            for j in used
            if i < j
        ):
            continue
        d = np.array([paths_mm[c, choice[c]] if choice[c] >= 0 else 0.0 for c in range(n_ch)])
        use = np.array([k >= 0 for k in choice])
        pos, rms, ok = locate_fn(d, channels, emitter, facing, use)
        if not ok or rms > max_res:
            continue
        out[choice] = (
            rms
            + penalty * (n_ch - len(used))
            - sw * np.mean([strength[c, choice[c]] for c in used])
            + rw * np.linalg.norm(pos - emitter)
        )
    return out


def position_covariance(position, paths_mm, sigma_mm, use, channels, emitter, scale, floor_mm):
    """Covariance by a finite-difference Jacobian and a plain inverse (uncertainty.py)."""
    p = np.asarray(position, float)

    def model(q):
        return np.linalg.norm(q - emitter) + np.linalg.norm(q - channels, axis=1)

    jac = np.array([(model(p + h) - model(p - h)) / 2e-4 for h in np.eye(3) * 1e-4]).T[use]
    w = 1.0 / np.asarray(sigma_mm)[use] ** 2
    info = jac.T @ (w[:, None] * jac) + np.eye(3) / 2000.0**2
    n = int(use.sum())
    inflation = 1.0
    if n > 3:
        r = model(p)[use] - np.asarray(paths_mm)[use]
        inflation = min(max(float((w * r * r).sum()) / (n - 3), 1.0), 100.0)
    return scale**2 * inflation * np.linalg.inv(info) + floor_mm**2 * np.eye(3)


def clean_envelope(frames, background, blind_zone):
    """Power-domain background removal, blind zone zeroed."""
    y = np.asarray(frames, dtype=float)
    e = (
        y.copy()
        if background is None
        else np.sqrt(np.maximum(y**2 - np.asarray(background) ** 2, 0))
    )
    e = np.maximum(e, 0)
    e[:, :blind_zone] = 0
    return e


def refine_toa(clean, toa, half_window, log_domain):
    """Parabola (optionally through the logs) around the largest sample near each ToA."""
    out = np.array(toa, dtype=float)
    n_t = clean.shape[1]
    for c, t in enumerate(toa):
        if not np.isfinite(t):
            continue
        centre = int(round(min(max(t, 0), n_t - 1)))
        lo, hi = max(centre - half_window, 0), min(centre + half_window + 1, n_t)
        k = lo + int(np.argmax(clean[c, lo:hi]))
        if k < 1 or k > n_t - 2 or clean[c, k] <= 0:
            continue
        v = clean[c, k - 1 : k + 2]
        if log_domain:
            if np.any(v <= 0):
                out[c] = k
                continue
            v = np.log(v)
        curvature = v[0] - 2 * v[1] + v[2]
        step = 0.5 * (v[0] - v[2]) / curvature if curvature < 0 else 0.0
        out[c] = k + np.clip(step, -0.5, 0.5)
    return out


def toa_features(frames, background, clean, toa, half_width=6):
    n_ch, n_t = frames.shape
    rows = []
    for c, t in enumerate(toa):
        width = 3 * (2 * half_width + 1) + 3 + n_ch
        if not np.isfinite(t) or round(t) - half_width < 0 or round(t) + half_width >= n_t:
            rows.append(np.full(width, np.nan))
            continue
        k = int(round(t))
        sl = slice(k - half_width, k + half_width + 1)
        p = max(clean[c, k], 1.0)
        bg = np.zeros(2 * half_width + 1) if background is None else background[c, sl] / p
        scalars = [t - k, np.log(p), float(background is not None)]
        rows.append(
            np.concatenate([frames[c, sl] / p, bg, clean[c, sl] / p, scalars, np.eye(n_ch)[c]])
        )
    return np.array(rows)


def joint_selection_value(choices, gains, max_targets, share_penalty):
    """Best objective of the scene's joint choice by trying every subset of at most
    ``max_targets`` combinations: sum of gains minus ``share_penalty`` per extra use of an
    echo; a subset where one combination uses only echoes of the others is not allowed."""
    best = 0.0
    for size in range(1, max_targets + 1):
        for subset in itertools.combinations(range(len(gains)), size):
            uses: dict = {}
            for i in subset:
                for c, k in enumerate(choices[i]):
                    if k >= 0:
                        uses[(c, k)] = uses.get((c, k), 0) + 1
            if any(
                all(uses[(c, k)] >= 2 for c, k in enumerate(choices[i]) if k >= 0) for i in subset
            ):
                continue
            extra = sum(u - 1 for u in uses.values())
            best = max(best, sum(gains[i] for i in subset) - share_penalty * extra)
    return best


def cholesky_solve(a, b):
    """memg.solve_spd on a copy, in plain Python: (ok, x)."""
    a = [list(map(float, row)) for row in a]
    n = len(b)
    x = [0.0] * n
    for j in range(n):
        d = a[j][j]
        for k in range(j):
            d -= a[j][k] * a[j][k]
        if d <= 1e-300:
            return False, x
        d = math.sqrt(d)
        a[j][j] = d
        for i in range(j + 1, n):
            s = a[i][j]
            for k in range(j):
                s -= a[i][k] * a[j][k]
            a[i][j] = s / d
    for i in range(n):
        s = float(b[i])
        for k in range(i):
            s -= a[i][k] * x[k]
        x[i] = s / a[i][i]
    for i in range(n - 1, -1, -1):
        s = x[i]
        for k in range(i + 1, n):
            s -= a[k][i] * x[k]
        x[i] = s / a[i][i]
    return True, x


def locate_lm(d, use, w, e, ch, facing, max_iter):
    """locate.locate_kernel in plain Python, written as before its scalar rewrite (3 x 3
    arrays, |p - e| per channel): (ok, rms, position)."""
    d, w, e, ch, facing = (np.asarray(v, dtype=np.float64).tolist() for v in (d, w, e, ch, facing))
    use = [bool(u) for u in use]
    n_ch = len(d)
    if sum(use) < 3:
        return False, math.inf, [0.0, 0.0, 0.0]

    def sq(v):
        return v * v

    def cost(p):
        weighted = plain = 0.0
        n_use = 0
        for n in range(n_ch):
            if use[n]:
                r = (
                    math.sqrt(sq(p[0] - e[0]) + sq(p[1] - e[1]) + sq(p[2] - e[2]))
                    + math.sqrt(sq(p[0] - ch[n][0]) + sq(p[1] - ch[n][1]) + sq(p[2] - ch[n][2]))
                    - d[n]
                )
                weighted += sq(w[n] * r)
                plain += r * r
                n_use += 1
        return weighted, plain, n_use

    def gauss_newton(p):
        lam = 1e-3
        c, plain, n_use = cost(p)
        for _ in range(max_iter):
            a = [[0.0] * 3 for _ in range(3)]
            b = [0.0] * 3
            for n in range(n_ch):
                if not use[n]:
                    continue
                ue = [p[i] - e[i] for i in range(3)]
                ur = [p[i] - ch[n][i] for i in range(3)]
                le = max(math.sqrt(sq(ue[0]) + sq(ue[1]) + sq(ue[2])), 1e-9)
                lr = max(math.sqrt(sq(ur[0]) + sq(ur[1]) + sq(ur[2])), 1e-9)
                r = w[n] * (le + lr - d[n])
                g = [w[n] * (ue[i] / le + ur[i] / lr) for i in range(3)]
                for i in range(3):
                    b[i] -= g[i] * r
                    for j in range(i + 1):
                        a[i][j] += g[i] * g[j]
            accepted = False
            for _try in range(6):
                damped = [row[:] for row in a]
                for i in range(3):
                    damped[i][i] += lam * (a[i][i] + 1e-9)
                ok, step = cholesky_solve(damped, b)
                if not ok:
                    lam *= 10.0
                    continue
                trial = [p[i] + step[i] for i in range(3)]
                new_cost, new_plain, _ = cost(trial)
                if new_cost <= c:
                    small = abs(step[0]) + abs(step[1]) + abs(step[2]) < 1e-4
                    p = trial
                    c, plain = new_cost, new_plain
                    lam = max(lam * 0.3, 1e-9)
                    accepted = not small
                    break
                lam *= 10.0
            if not accepted:
                break
        return math.sqrt(plain / max(n_use, 1)), p

    # start point: the linearised ellipsoid equations
    radius, n_use, d_sum = -1.0, 0, 0.0
    for n in range(n_ch):
        if use[n]:
            n_use += 1
            d_sum += d[n]
            if sq(ch[n][0] - e[0]) + sq(ch[n][1] - e[1]) + sq(ch[n][2] - e[2]) < 1.0:
                radius = 0.5 * d[n]
    if radius <= 0.0:
        radius = 0.5 * d_sum / max(n_use, 1)
    a = [[0.0] * 3 for _ in range(3)]
    b = [0.0] * 3
    for n in range(n_ch):
        if not use[n]:
            continue
        s = [ch[n][i] - e[i] for i in range(3)]
        s2 = s[0] * s[0] + s[1] * s[1] + s[2] * s[2]
        if s2 < 1.0:
            continue
        rhs = 0.5 * (radius * radius + s2 - sq(d[n] - radius))
        for i in range(3):
            b[i] += s[i] * rhs
            for j in range(3):
                a[i][j] += s[i] * s[j]
    trace = a[0][0] + a[1][1] + a[2][2]
    for i in range(3):
        a[i][i] += 1e-6 * trace + 1e-9
    ok, q = cholesky_solve(a, b)
    if not ok:
        q = [0.0, 0.0, 0.0]
    qf = q[0] * facing[0] + q[1] * facing[1] + q[2] * facing[2]
    qq = q[0] * q[0] + q[1] * q[1] + q[2] * q[2]
    disc = qf * qf - (qq - radius * radius)
    t = -qf + math.sqrt(disc) if disc > 0.0 else 0.5 * radius
    p = [q[i] + t * facing[i] + e[i] for i in range(3)]
    rms, p = gauss_newton(p)
    ahead = sum((p[i] - e[i]) * facing[i] for i in range(3))
    if ahead < 0.0:
        p = [p[i] - 2.0 * ahead * facing[i] for i in range(3)]
        rms, p = gauss_newton(p)
        ahead = sum((p[i] - e[i]) * facing[i] for i in range(3))
    if not (math.isfinite(rms) and all(math.isfinite(v) for v in p)):
        return False, math.inf, [0.0, 0.0, 0.0]
    return ahead > 0.0, rms, p


@njit
def emg_jacobian_row(t, alpha, mu, sigma, eta, out, col):
    """Value of one MEMG component at t; its partial derivatives go to out[col:col + 4]
    (memg's own shape and slope steps, one sample at a time)."""
    u, g, e = memg._emg_shape(t, mu, sigma, eta)
    out[col], out[col + 1], out[col + 2], out[col + 3] = memg._emg_slopes(
        alpha, sigma, eta, u, g, e
    )
    return alpha * g * e


@njit
def normal_equations(y, lo, hi, p, n_comp, jac_row, a, b):
    """J^T J into a and J^T r into b over y[lo:hi], and the cost sum r^2 at p, in one plain
    pass: the sums the fit takes, in the same order, from memg's ``trial_cost`` and
    ``jacobian_sums`` (the tests hold them to it bit for bit)."""
    n_par = 4 * n_comp
    a[:, :] = 0.0
    b[:] = 0.0
    cost = 0.0
    for t in range(lo, hi):
        m = 0.0
        for k in range(n_comp):
            m += emg_jacobian_row(
                float(t), p[4 * k], p[4 * k + 1], p[4 * k + 2], p[4 * k + 3], jac_row, 4 * k
            )
        r = y[t] - m
        cost += r * r
        for i in range(n_par):
            b[i] += jac_row[i] * r
            for j in range(i + 1):
                a[i, j] += jac_row[i] * jac_row[j]
    for i in range(n_par):
        for j in range(i + 1, n_par):
            a[i, j] = a[j, i]
    return cost
