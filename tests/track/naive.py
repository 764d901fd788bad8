"""Plain numpy references for the tracker's kernels."""

from __future__ import annotations

import itertools

import numpy as np


def cv_matrices(dt: float, acceleration: float) -> tuple[np.ndarray, np.ndarray]:
    f = np.eye(6)
    f[:3, 3:] = dt * np.eye(3)
    g = np.vstack([0.5 * dt * dt * np.eye(3), dt * np.eye(3)])
    return f, acceleration**2 * g @ g.T


def kf_predict(x, p, dt, acceleration):
    f, q = cv_matrices(dt, acceleration)
    return f @ x, f @ p @ f.T + q


def kf_update(x, p, z, r):
    h = np.hstack([np.eye(3), np.zeros((3, 3))])
    s = h @ p @ h.T + r
    k = p @ h.T @ np.linalg.inv(s)
    x = x + k @ (z - h @ x)
    a = np.eye(6) - k @ h
    return x, a @ p @ a.T + k @ r @ k.T


def mahalanobis2(x, p, z, r):
    s = p[:3, :3] + r
    y = z - x[:3]
    return float(y @ np.linalg.solve(s, y))


def best_matching(cost: np.ndarray, feasible: np.ndarray) -> tuple[int, float]:
    """Brute force: the most feasible pairs, then the least total cost: (pairs, cost)."""
    n, m = cost.shape
    best = (0, 0.0)
    for k in range(min(n, m), 0, -1):
        found = None
        for rows in itertools.combinations(range(n), k):
            for cols in itertools.permutations(range(m), k):
                if all(feasible[i, j] for i, j in zip(rows, cols, strict=True)):
                    total = sum(cost[i, j] for i, j in zip(rows, cols, strict=True))
                    if found is None or total < found:
                        found = total
        if found is not None:
            return k, found
    return best
