"""The reference for the tracker's compiled step (the implementation before the step ran on
preallocated arrays, spiel_edge/track/step.py): predict, gate, assign, update,
confirm/delete, birth.

Track slots are rows of fixed arrays (the cap is their length): ``status`` 0 free,
1 tentative, 2 confirmed. Confirmed tracks are matched first, tentative ones get the targets
left over, and targets nobody took start tentative tracks (not inside a confirmed track's
gate, where they are more likely a split detection of that track than a new object).
"""

from __future__ import annotations

import numpy as np

from spiel_edge._jit import jit
from spiel_edge.track.assign import INFEASIBLE
from spiel_edge.track.kalman import gate_kernel, predict_kernel, sym_inv3, update_kernel

FREE, TENTATIVE, CONFIRMED = 0, 1, 2


@jit
def _assign(cost: np.ndarray) -> np.ndarray:
    n, m = cost.shape
    out = np.full(n, -1, dtype=np.int64)
    if n == 0 or m == 0:
        return out
    if n <= m:
        cols = _hungarian(cost)
        for i in range(n):
            if cols[i] >= 0 and cost[i, cols[i]] < INFEASIBLE:
                out[i] = cols[i]
        return out
    rows = _hungarian(cost.T.copy())
    for j in range(m):
        if rows[j] >= 0 and cost[rows[j], j] < INFEASIBLE:
            out[rows[j]] = j
    return out


@jit
def _hungarian(cost: np.ndarray) -> np.ndarray:
    """Rows n <= columns m; every row gets a column (0-based), minimum total cost."""
    n, m = cost.shape
    u = np.zeros(n + 1)
    v = np.zeros(m + 1)
    owner = np.zeros(m + 1, dtype=np.int64)  # owner[j]: 1-based row holding column j
    way = np.zeros(m + 1, dtype=np.int64)
    minv = np.empty(m + 1)
    used = np.empty(m + 1, dtype=np.bool_)
    for i in range(1, n + 1):
        owner[0] = i
        j0 = 0
        minv[:] = np.inf
        used[:] = False
        while True:
            used[j0] = True
            i0 = owner[j0]
            delta = np.inf
            j1 = 0
            for j in range(1, m + 1):
                if not used[j]:
                    cur = cost[i0 - 1, j - 1] - u[i0] - v[j]
                    if cur < minv[j]:
                        minv[j] = cur
                        way[j] = j0
                    if minv[j] < delta:
                        delta = minv[j]
                        j1 = j
            for j in range(m + 1):
                if used[j]:
                    u[owner[j]] += delta
                    v[j] -= delta
                else:
                    minv[j] -= delta
            j0 = j1
            if owner[j0] == 0:
                break
        while True:  # flip the augmenting path
            j1 = way[j0]
            owner[j0] = owner[j1]
            j0 = j1
            if j0 == 0:
                break
    cols = np.full(n, -1, dtype=np.int64)
    for j in range(1, m + 1):
        if owner[j] > 0:
            cols[owner[j] - 1] = j - 1
    return cols


@jit
def _measurement_noise(r: np.ndarray, out: np.ndarray, floor2: float, fallback2: float) -> None:
    """Symmetrised covariance plus the floor into ``out``; the fallback when it is not
    finite or not positive definite."""
    ok = True
    for i in range(3):
        for j in range(3):
            v = 0.5 * (r[i, j] + r[j, i])
            ok = ok and np.isfinite(v)
            out[i, j] = v
    if ok:
        for i in range(3):
            out[i, i] += floor2
        det = sym_inv3(out[0, 0], out[0, 1], out[0, 2], out[1, 1], out[1, 2], out[2, 2])[0]
        minor = out[0, 0] * out[1, 1] - out[0, 1] * out[1, 0]
        ok = out[0, 0] > 0.0 and minor > 0.0 and det > 0.0 and np.isfinite(det)
    if not ok:
        out[:, :] = 0.0
        for i in range(3):
            out[i, i] = fallback2 + floor2


@jit
def _finite(a: np.ndarray) -> bool:
    total = 0.0
    for v in a.ravel():
        total += v * 0.0  # NaN or inf make it NaN
    return total == 0.0


@jit
def _match(x, p, slots, z, r, usable, gate, gated):
    """Global assignment of ``slots`` to the usable targets; per slot a target or -1."""
    n, m = len(slots), len(z)
    cost = np.full((n, m), INFEASIBLE)
    for a in range(n):
        s = slots[a]
        for j in range(m):
            if usable[j]:
                d2, logdet = gate_kernel(x[s], p[s], z[j], r[j])
                if d2 <= gate:
                    cost[a, j] = d2 + logdet
                    gated[j] = True
    return _assign(cost)


@jit
def _step(x, p, status, ids, age, hits, misses, next_id, z, r_in, dt, params, counts) -> np.ndarray:
    """One acquisition. params: acceleration, gate, floor^2, fallback^2, v0^2, confirm_hits,
    confirm_window, max_misses. Returns per target the id of the confirmed track it went to,
    or -1."""
    acceleration, gate, floor2, fallback2, v02 = (
        params[0],
        params[1],
        params[2],
        params[3],
        params[4],
    )
    confirm_hits, confirm_window, max_misses = int(params[5]), int(params[6]), int(params[7])
    m = len(z)
    r = np.empty((m, 3, 3))
    usable = np.empty(m, dtype=np.bool_)
    for j in range(m):
        _measurement_noise(r_in[j], r[j], floor2, fallback2)
        usable[j] = np.isfinite(z[j, 0]) and np.isfinite(z[j, 1]) and np.isfinite(z[j, 2])
    for s in range(len(status)):
        if status[s] != FREE:
            predict_kernel(x[s], p[s], dt, acceleration)
            age[s] += 1
            misses[s] += 1  # undone on a hit
    target_slot = np.full(m, -1, dtype=np.int64)
    near_confirmed = np.zeros(m, dtype=np.bool_)
    scratch = np.zeros(m, dtype=np.bool_)
    work = np.empty((6, 15))
    for kind in (CONFIRMED, TENTATIVE):
        slots = np.flatnonzero(status == kind)
        gated = near_confirmed if kind == CONFIRMED else scratch
        chosen = _match(x, p, slots, z, r, usable, gate, gated)
        for a in range(len(slots)):
            j = chosen[a]
            s = slots[a]
            if j >= 0 and update_kernel(x[s], p[s], z[j], r[j], work):
                hits[s] += 1
                misses[s] = 0
                target_slot[j] = s
                usable[j] = False
    for s in range(len(status)):
        finite = _finite(x[s]) and _finite(p[s])
        if status[s] == TENTATIVE and finite and hits[s] >= confirm_hits:
            status[s] = CONFIRMED
            ids[s] = next_id[0]
            next_id[0] += 1
            continue
        expired = age[s] >= confirm_window if status[s] == TENTATIVE else misses[s] >= max_misses
        if status[s] != FREE and (expired or not finite):
            status[s] = FREE
    for j in range(m):
        if not usable[j] or near_confirmed[j]:
            continue
        free = np.flatnonzero(status == FREE)
        if len(free) == 0:
            counts[0] += 1  # a birth dropped at the cap
            continue
        s = free[0]
        x[s, :3] = z[j]
        x[s, 3:] = 0.0
        p[s] = 0.0
        p[s, :3, :3] = r[j]
        for a in range(3, 6):
            p[s, a, a] = v02
        status[s], ids[s], age[s], hits[s], misses[s] = TENTATIVE, -1, 1, 1, 0
        if confirm_hits <= 1:
            status[s] = CONFIRMED
            ids[s] = next_id[0]
            next_id[0] += 1
        target_slot[j] = s
    target_ids = np.full(m, -1, dtype=np.int64)
    for j in range(m):
        s = target_slot[j]
        if s >= 0 and status[s] == CONFIRMED:
            target_ids[j] = ids[s]
    return target_ids


@jit
def _snapshot(status, ids, age, hits, misses, x, p):
    """The confirmed tracks by id: (id, age, hits, misses) rows, states, covariances."""
    slots = np.flatnonzero(status == CONFIRMED)
    slots = slots[np.argsort(ids[slots])]
    n = len(slots)
    meta = np.empty((n, 4), dtype=np.int64)
    xs = np.empty((n, 6))
    ps = np.empty((n, 6, 6))
    for k in range(n):
        s = slots[k]
        meta[k, 0], meta[k, 1], meta[k, 2], meta[k, 3] = ids[s], age[s], hits[s], misses[s]
        xs[k] = x[s]
        ps[k] = p[s]
    return meta, xs, ps
