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
    n, m = c.shape
    size = max(n, m) + 1
    out, owner, way, cols = np.zeros((4, size), dtype=np.int64)
    assign_into(
        np.ascontiguousarray(c),
        n,
        m,
        out,
        np.zeros((3, size)),
        owner,
        way,
        cols,
        np.zeros(size, dtype=np.bool_),
    )
    return out[:n].copy()


@jit
def assign_into(cost, n, m, out, fwork, owner, way, cols, used) -> None:
    """The matching of the top-left ``n`` x ``m`` block of ``cost`` with preallocated
    scratch (``fwork`` (3, >= max(n, m) + 1); ``owner``, ``way``, ``cols``, ``used`` of at
    least that length). ``out[:n]``: per row the
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
    """Rows n <= columns m of ``cost[:n, :m]`` (or of its transpose when ``flip``): every
    row gets a column (0-based) in ``cols``, minimum total cost."""
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
        for j in range(m + 1):  # a loop: cheaper than a slice assignment at this size
            minv[j] = np.inf
            used[j] = False
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
