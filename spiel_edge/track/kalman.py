"""Constant-velocity Kalman filter in 3-D: state [x, y, z, vx, vy, vz] (mm, mm/s).

Process noise: white acceleration of std ``acceleration`` (mm/s^2), discrete per axis
sigma^2 [[dt^4/4, dt^3/2], [dt^3/2, dt^2]]. Measurement: the position, with the target's
3x3 covariance. The update is in Joseph form and the covariance re-symmetrised, so it stays
symmetric positive semi-definite in floating point. The public functions copy and validate;
the tracker calls the ``_kernels`` from its own compiled step.
"""

from __future__ import annotations

import numpy as np

from spiel_edge._jit import jit


def predict(x: np.ndarray, p: np.ndarray, dt: float, acceleration: float):
    """One prediction step over ``dt`` seconds; returns new (x, P)."""
    x2, p2 = _checked(x, p)
    predict_kernel(x2, p2, float(dt), float(acceleration))
    return x2, p2


def update(x: np.ndarray, p: np.ndarray, z: np.ndarray, r: np.ndarray):
    """One measurement update with position ``z`` (3,) of covariance ``r`` (3, 3)."""
    x2, p2 = _checked(x, p)
    z2, r2 = np.asarray(z, dtype=np.float64), np.asarray(r, dtype=np.float64)
    update_kernel(x2, p2, z2, r2, np.empty((6, 15)))
    return x2, p2


def mahalanobis2(x: np.ndarray, p: np.ndarray, z: np.ndarray, r: np.ndarray) -> float:
    """Squared Mahalanobis distance of ``z`` from the predicted position."""
    x2, p2 = _checked(x, p)
    d2, _ = gate_kernel(x2, p2, np.asarray(z, dtype=np.float64), np.asarray(r, dtype=np.float64))
    return float(d2)


def _checked(x, p):
    x2 = np.array(x, dtype=np.float64).reshape(6)
    p2 = np.array(p, dtype=np.float64).reshape(6, 6)
    return x2, p2


@jit
def predict_kernel(x: np.ndarray, p: np.ndarray, dt: float, acceleration: float) -> None:
    for a in range(3):
        x[a] += dt * x[a + 3]
    # P <- F P F^T with F = [[I, dt I], [0, I]]: rows then columns
    for j in range(6):
        for a in range(3):
            p[a, j] += dt * p[a + 3, j]
    for i in range(6):
        for a in range(3):
            p[i, a] += dt * p[i, a + 3]
    s2 = acceleration * acceleration
    for a in range(3):
        p[a, a] += s2 * dt**4 / 4.0
        p[a, a + 3] += s2 * dt**3 / 2.0
        p[a + 3, a] += s2 * dt**3 / 2.0
        p[a + 3, a + 3] += s2 * dt * dt


@jit
def sym_inv3(a00, a01, a02, a11, a12, a22):
    """Determinant and inverse (upper triangle) of a symmetric 3x3 matrix, as scalars."""
    i00 = a11 * a22 - a12 * a12
    i01 = a02 * a12 - a01 * a22
    i02 = a01 * a12 - a02 * a11
    det = a00 * i00 + a01 * i01 + a02 * i02
    if not det > 0.0:
        return det, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
    i11 = a00 * a22 - a02 * a02
    i12 = a02 * a01 - a00 * a12
    i22 = a00 * a11 - a01 * a01
    return det, i00 / det, i01 / det, i02 / det, i11 / det, i12 / det, i22 / det


@jit
def _innovation_inverse(p: np.ndarray, r: np.ndarray, inv: np.ndarray) -> float:
    """S = P_pos + R (symmetric); its inverse into ``inv`` (3, 3); returns det S."""
    det, i00, i01, i02, i11, i12, i22 = sym_inv3(
        p[0, 0] + r[0, 0],
        0.5 * (p[0, 1] + p[1, 0] + r[0, 1] + r[1, 0]),
        0.5 * (p[0, 2] + p[2, 0] + r[0, 2] + r[2, 0]),
        p[1, 1] + r[1, 1],
        0.5 * (p[1, 2] + p[2, 1] + r[1, 2] + r[2, 1]),
        p[2, 2] + r[2, 2],
    )
    inv[0, 0], inv[0, 1], inv[0, 2] = i00, i01, i02
    inv[1, 0], inv[1, 1], inv[1, 2] = i01, i11, i12
    inv[2, 0], inv[2, 1], inv[2, 2] = i02, i12, i22
    return det


@jit
def gate_kernel(x: np.ndarray, p: np.ndarray, z: np.ndarray, r: np.ndarray):
    """(squared Mahalanobis distance, log det S) of ``z``; (inf, 0) when S is singular."""
    d2, det = gate_det(x, p, z, r)
    if not det > 0.0:
        return np.inf, 0.0
    return d2, np.log(det)


@jit(inline="always")
def gate_det(x, p, z, r, inv=None):
    """(squared Mahalanobis distance, det S) of ``z``, (inf, 0) when S is singular; with
    ``inv`` (3, 3) given, S^-1 goes there too (as :func:`_innovation_inverse`), so that
    :func:`update_inv` need not invert S again."""
    det, i00, i01, i02, i11, i12, i22 = sym_inv3(
        p[0, 0] + r[0, 0],
        0.5 * (p[0, 1] + p[1, 0] + r[0, 1] + r[1, 0]),
        0.5 * (p[0, 2] + p[2, 0] + r[0, 2] + r[2, 0]),
        p[1, 1] + r[1, 1],
        0.5 * (p[1, 2] + p[2, 1] + r[1, 2] + r[2, 1]),
        p[2, 2] + r[2, 2],
    )
    if not det > 0.0:
        return np.inf, 0.0
    if inv is not None:
        inv[0, 0], inv[0, 1], inv[0, 2] = i00, i01, i02
        inv[1, 0], inv[1, 1], inv[1, 2] = i01, i11, i12
        inv[2, 0], inv[2, 1], inv[2, 2] = i02, i12, i22
    y0, y1, y2 = z[0] - x[0], z[1] - x[1], z[2] - x[2]
    d2 = (
        i00 * y0 * y0
        + i11 * y1 * y1
        + i22 * y2 * y2
        + 2.0 * (i01 * y0 * y1 + i02 * y0 * y2 + i12 * y1 * y2)
    )
    return d2, det


@jit
def update_kernel(
    x: np.ndarray, p: np.ndarray, z: np.ndarray, r: np.ndarray, work: np.ndarray
) -> bool:
    """Joseph-form update in place (``work``: scratch (6, 15)); False (state untouched) when
    S is singular."""
    inv = work[:3, 12:15]
    det = _innovation_inverse(p, r, inv)
    if not det > 0.0:
        return False
    update_inv(x, p, z, r, work, inv)
    return True


@jit
def update_inv(x, p, z, r, work, inv) -> None:
    """:func:`update_kernel` with S^-1 (3, 3) already in ``inv`` (not inside ``work[:, :12]``)."""
    k = work[:, 0:3]  # K = P H^T S^-1
    for i in range(6):
        for j in range(3):
            acc = 0.0
            for c in range(3):
                acc += p[i, c] * inv[c, j]
            k[i, j] = acc
    y0, y1, y2 = z[0] - x[0], z[1] - x[1], z[2] - x[2]  # before x changes
    for i in range(6):
        x[i] += k[i, 0] * y0 + k[i, 1] * y1 + k[i, 2] * y2
    # Joseph form P <- A P A^T + K R K^T with A = I - K H (H picks the position)
    ap = work[:, 3:9]
    for i in range(6):
        for j in range(max(3, i + 1)):  # the entries used below: j <= i or j < 3
            acc = p[i, j]
            for c in range(3):
                acc -= k[i, c] * p[c, j]
            ap[i, j] = acc
    kr = work[:, 9:12]
    for i in range(6):
        for j in range(3):
            acc = 0.0
            for c in range(3):
                acc += k[i, c] * r[c, j]
            kr[i, j] = acc
    for i in range(6):
        for j in range(i + 1):
            acc = ap[i, j]
            for c in range(3):
                acc -= ap[i, c] * k[j, c]
                acc += kr[i, c] * k[j, c]
            p[i, j] = acc
    for i in range(6):
        for j in range(i):
            p[j, i] = p[i, j]  # exactly symmetric (the lower triangle is the one computed)


@jit(inline="always")
def gate_at(x, p, s, z, r, j, gate):
    """gate_kernel of the step's slot ``s`` and target ``j`` (the same arithmetic) without array views
    and without the logarithm: (squared Mahalanobis distance, det S); (inf, 0) if singular.
    A pair far outside the gate is rejected before inverting S: for S positive definite
    d2 >= |y|^2 / trace S, so |y|^2 > 2 gate trace S means d2 > gate (the factor 2 leaves
    rounding no say; the same pairs are gated as with the inverse)."""
    y0, y1, y2 = z[j, 0] - x[s, 0], z[j, 1] - x[s, 1], z[j, 2] - x[s, 2]
    trace = p[s, 0, 0] + r[j, 0, 0] + p[s, 1, 1] + r[j, 1, 1] + p[s, 2, 2] + r[j, 2, 2]
    if trace > 0.0 and y0 * y0 + y1 * y1 + y2 * y2 > 2.0 * gate * trace:
        return np.inf, 0.0
    det, i00, i01, i02, i11, i12, i22 = sym_inv3(
        p[s, 0, 0] + r[j, 0, 0],
        0.5 * (p[s, 0, 1] + p[s, 1, 0] + r[j, 0, 1] + r[j, 1, 0]),
        0.5 * (p[s, 0, 2] + p[s, 2, 0] + r[j, 0, 2] + r[j, 2, 0]),
        p[s, 1, 1] + r[j, 1, 1],
        0.5 * (p[s, 1, 2] + p[s, 2, 1] + r[j, 1, 2] + r[j, 2, 1]),
        p[s, 2, 2] + r[j, 2, 2],
    )
    if not det > 0.0:
        return np.inf, 0.0
    d2 = (
        i00 * y0 * y0
        + i11 * y1 * y1
        + i22 * y2 * y2
        + 2.0 * (i01 * y0 * y1 + i02 * y0 * y2 + i12 * y1 * y2)
    )
    return d2, det
