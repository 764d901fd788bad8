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


def static_matrices(dt: float, static_q2: float, v02: float):
    """The IMM's static model as x' = F x + noise: the position kept, the velocity replaced by
    noise of variance ``v02`` (F zeroes it), the position a random walk of ``static_q2`` mm^2/s."""
    f = np.zeros((6, 6))
    f[:3, :3] = np.eye(3)
    q = np.diag([static_q2 * dt] * 3 + [v02] * 3)
    return f, q


def imm_mix_predict(xm, pm, mu, dt, acceleration, static_q2, switch, v02):
    """Textbook IMM mixing (transition matrix [[1-s, s], [s, 1-s]]) and prediction; returns
    (xm, pm, mu, x, P) with x, P the moment-matched mixture."""
    pi = np.array([[1 - switch, switch], [switch, 1 - switch]])
    c = pi.T @ mu
    w = pi * mu[:, None] / c[None, :]  # w[i, j] = P(model i before | model j now)
    models = [static_matrices(dt, static_q2, v02), cv_matrices(dt, acceleration)]
    new_x, new_p = np.empty_like(xm), np.empty_like(pm)
    for j, (f, q) in enumerate(models):
        x0 = w[:, j] @ xm
        p0 = sum(w[i, j] * (pm[i] + np.outer(xm[i] - x0, xm[i] - x0)) for i in range(2))
        new_x[j], new_p[j] = f @ x0, f @ p0 @ f.T + q
    return (new_x, new_p, c, *imm_combine(new_x, new_p, c))


def imm_update(xm, pm, mu, z, r):
    """Each model updated with ``z``; model probabilities times the Gaussian likelihoods."""
    like = np.empty(2)
    new_x, new_p = np.empty_like(xm), np.empty_like(pm)
    for j in range(2):
        s = pm[j][:3, :3] + r
        y = z - xm[j][:3]
        like[j] = np.exp(-0.5 * y @ np.linalg.solve(s, y)) / np.sqrt(np.linalg.det(s))
        new_x[j], new_p[j] = kf_update(xm[j], pm[j], z, r)
    mu = mu * like / (mu @ like)
    return (new_x, new_p, mu, *imm_combine(new_x, new_p, mu))


def imm_combine(xm, pm, mu):
    x = mu @ xm
    p = sum(mu[j] * (pm[j] + np.outer(xm[j] - x, xm[j] - x)) for j in range(2))
    return x, p
