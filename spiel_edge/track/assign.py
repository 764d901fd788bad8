"""Global assignment: the minimum-cost matching of tracks to targets (Hungarian method).

Shortest augmenting paths with potentials (Kuhn-Munkres in the Jonker-Volgenant form),
O(n^2 m) for an n x m cost matrix with n <= m. A pair whose cost is at least ``INFEASIBLE``
(outside the gate) is never matched: since one such pair outweighs any sum of gated costs,
the matching first has the most gated pairs, then the least total cost among those.
"""

from __future__ import annotations

import numpy as np

from spiel_edge._jit import jit

INFEASIBLE = 1e12  # the cost of a pair outside the gate


def assign(cost: np.ndarray) -> np.ndarray:
    """Per row the column it is matched to, or -1 (unmatched or only infeasible pairs).

    ``cost`` (rows, cols) finite; entries >= INFEASIBLE (or non-finite) are not allowed pairs.
    """
    c = np.asarray(cost, dtype=np.float64)
    if c.ndim != 2:
        raise ValueError(f"cost must be a 2-D matrix, got shape {c.shape}")
    c = np.where(np.isfinite(c), np.minimum(c, INFEASIBLE), INFEASIBLE)
    return _assign(np.ascontiguousarray(c))


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
def _assign_into(cost, n, m, out, fwork, owner, way, cols, used) -> None:
    """:func:`_assign` on the top-left ``n`` x ``m`` block of ``cost`` with preallocated
    scratch (``fwork`` (3, >= max(n, m) + 1); ``owner``, ``way``, ``cols``, ``used`` of at
    least that length): the same arithmetic, so the same matching. ``out[:n]``: per row the
    column or -1."""
    for i in range(n):
        out[i] = -1
    if n == 0 or m == 0:
        return
    flip = n > m  # the Hungarian wants rows <= columns: run it on the transpose
    rows, columns = (m, n) if flip else (n, m)
    _hungarian_into(cost, flip, rows, columns, fwork, owner, way, cols, used)
    for a in range(rows):
        b = cols[a]
        if b < 0:
            continue
        i, j = (b, a) if flip else (a, b)
        if cost[i, j] < INFEASIBLE:
            out[i] = j


@jit
def _hungarian_into(cost, flip, n, m, fwork, owner, way, cols, used) -> None:
    """:func:`_hungarian` on ``cost[:n, :m]`` (or its transpose when ``flip``) into ``cols``."""
    u, v, minv = fwork[0], fwork[1], fwork[2]
    for j in range(m + 1):
        v[j] = 0.0
        owner[j] = 0
        way[j] = 0
    for i in range(n + 1):
        u[i] = 0.0
    for i in range(1, n + 1):
        owner[0] = i
        j0 = 0
        minv[: m + 1] = np.inf
        used[: m + 1] = False
        while True:
            used[j0] = True
            i0 = owner[j0]
            delta = np.inf
            j1 = 0
            for j in range(1, m + 1):
                if not used[j]:
                    c = cost[j - 1, i0 - 1] if flip else cost[i0 - 1, j - 1]
                    cur = c - u[i0] - v[j]
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
    for i in range(n):
        cols[i] = -1
    for j in range(1, m + 1):
        if owner[j] > 0:
            cols[owner[j] - 1] = j - 1
