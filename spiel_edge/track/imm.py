"""Interacting multiple model (IMM) per track: a near-static model and the constant-velocity
one, mixed at every acquisition.

Model 0 (static): the position is a random walk of ``static_q2`` mm^2 per second; the velocity
is not part of it (held at 0 with variance ``v02``, uncorrelated), so its update only averages
positions. Model 1: the constant-velocity filter of kalman.py. Per acquisition (Blom and
Bar-Shalom's IMM): mix the two models' estimates with the probabilities of having switched
(``switch`` per acquisition, both ways), predict each, and after a measurement update each
model and reweight them by the measurement's likelihood under each. The track's estimate is
the moment-matched mixture of the two (:func:`combine_kernel`), which the tracker gates, assigns
and reports. A static target's track then averages its acquisitions like a running mean
instead of letting the velocity follow the noise; a moving one is carried by model 1.

``xm`` (2, 6) and ``pm`` (2, 6, 6) are a track's two model states, ``mu`` (2,) their
probabilities; ``wx`` (2, 6) and ``wp`` (2, 6, 6) are scratch. The public functions copy and
validate; the tracker's step calls the ``_kernels``. tests/track/test_imm.py checks them against
a plain numpy IMM.
"""

from __future__ import annotations

import numpy as np

from spiel_edge._jit import jit
from spiel_edge.track.kalman import gate_det, predict_kernel, update_inv

STATIC, MOVING = 0, 1
_TINY = 1e-300  # a model probability below this is taken as zero in the mixing


def mix_predict(xm, pm, mu, dt, acceleration, static_q2, switch, v02):
    """Mixing and prediction over ``dt`` s; returns new (xm, pm, mu, x, P) (x, P combined)."""
    xm2, pm2, mu2 = _copies(xm, pm, mu)
    x, p = np.empty(6), np.empty((6, 6))
    wx, wp = np.empty((2, 6)), np.empty((2, 6, 6))
    mix_predict_kernel(
        xm2, pm2, mu2, x, p, float(dt), float(acceleration), float(static_q2), float(switch),
        float(v02), wx, wp,
    )  # fmt: skip
    return xm2, pm2, mu2, x, p


def update(xm, pm, mu, z, r):
    """Measurement update of both models with position ``z`` of covariance ``r``; returns new
    (xm, pm, mu, x, P), or None when the innovation covariance is singular."""
    xm2, pm2, mu2 = _copies(xm, pm, mu)
    x, p = np.empty(6), np.empty((6, 6))
    z2, r2 = np.asarray(z, dtype=np.float64), np.asarray(r, dtype=np.float64)
    if not imm_update(xm2, pm2, mu2, x, p, z2, r2, np.empty((6, 15))):
        return None
    return xm2, pm2, mu2, x, p


def _copies(xm, pm, mu):
    return (
        np.array(xm, dtype=np.float64).reshape(2, 6),
        np.array(pm, dtype=np.float64).reshape(2, 6, 6),
        np.array(mu, dtype=np.float64).reshape(2),
    )


@jit
def mix_predict_kernel(xm, pm, mu, x, p, dt, acceleration, static_q2, switch, v02, wx, wp) -> None:
    """Mix (into the scratch ``wx``, ``wp``), predict each model, combine into ``x``, ``p``;
    ``mu`` becomes the predicted model probabilities."""
    c0 = (1.0 - switch) * mu[0] + switch * mu[1]
    c1 = switch * mu[0] + (1.0 - switch) * mu[1]
    for j in range(2):
        cj = c0 if j == 0 else c1
        w0 = ((1.0 - switch) if j == 0 else switch) * mu[0]
        if cj > _TINY:
            w0 /= cj
        else:  # the model had no weight: keep its own estimate
            w0 = 1.0 if j == 0 else 0.0
        w1 = 1.0 - w0
        # the static model's velocity and its covariance are set by _predict_static below:
        # of its mixture only the position and its covariance are needed
        n = 3 if j == STATIC else 6
        for a in range(n):
            wx[j, a] = w0 * xm[0, a] + w1 * xm[1, a]
        for a in range(n):
            d0a, d1a = xm[0, a] - wx[j, a], xm[1, a] - wx[j, a]
            for b in range(a + 1):  # symmetric: the lower triangle, mirrored
                d0b, d1b = xm[0, b] - wx[j, b], xm[1, b] - wx[j, b]
                v = w0 * (pm[0, a, b] + d0a * d0b) + w1 * (pm[1, a, b] + d1a * d1b)
                wp[j, a, b] = v
                wp[j, b, a] = v
    for j in range(2):  # plain loops: numba's array assignment costs more at this size
        for a in range(6):
            xm[j, a] = wx[j, a]
            for b in range(6):
                pm[j, a, b] = wp[j, a, b]
    mu[0], mu[1] = c0, c1
    _predict_static(xm[STATIC], pm[STATIC], dt, static_q2, v02)
    predict_kernel(xm[MOVING], pm[MOVING], dt, acceleration)
    combine_kernel(xm, pm, mu, x, p)


@jit
def _predict_static(x, p, dt, static_q2, v02) -> None:
    """Position unchanged (random walk of ``static_q2`` mm^2/s), velocity 0 with variance
    ``v02`` and no correlation with the position: the static model ignores velocity."""
    for a in range(3):
        x[a + 3] = 0.0
        for b in range(3):
            p[a, b + 3] = 0.0
            p[a + 3, b] = 0.0
            p[a + 3, b + 3] = 0.0
        p[a + 3, a + 3] = v02
        p[a, a] += static_q2 * dt


@jit
def imm_update(xm, pm, mu, x, p, z, r, work) -> bool:
    """Update both models with ``z`` (covariance ``r``) and reweight them by its likelihood;
    combine into ``x``, ``p``. False (nothing changed) when a model's S is singular."""
    inv0, inv1 = work[:3, 12:15], work[3:, 12:15]  # each model's S^-1, for its update
    d0, det0 = gate_det(xm[STATIC], pm[STATIC], z, r, inv0)
    d1, det1 = gate_det(xm[MOVING], pm[MOVING], z, r, inv1)
    if not (np.isfinite(d0) and np.isfinite(d1)):
        return False
    ll0, ll1 = -0.5 * (d0 + np.log(det0)), -0.5 * (d1 + np.log(det1))
    top = max(ll0, ll1)
    l0, l1 = mu[0] * np.exp(ll0 - top), mu[1] * np.exp(ll1 - top)
    total = l0 + l1
    if total > 0.0 and np.isfinite(total):  # else both were ~0: keep the predicted weights
        mu[0], mu[1] = l0 / total, l1 / total
    update_inv(xm[STATIC], pm[STATIC], z, r, work, inv0)
    update_inv(xm[MOVING], pm[MOVING], z, r, work, inv1)
    combine_kernel(xm, pm, mu, x, p)
    return True


@jit
def combine_kernel(xm, pm, mu, x, p) -> None:
    """Moment-matched mixture: x = sum mu_j x_j, P = sum mu_j (P_j + d_j d_j^T), exactly
    symmetric."""
    for a in range(6):
        x[a] = mu[0] * xm[0, a] + mu[1] * xm[1, a]
    for a in range(6):
        d0a, d1a = xm[0, a] - x[a], xm[1, a] - x[a]
        for b in range(a + 1):
            d0b, d1b = xm[0, b] - x[b], xm[1, b] - x[b]
            v = mu[0] * (pm[0, a, b] + d0a * d0b) + mu[1] * (pm[1, a, b] + d1a * d1b)
            p[a, b] = v
            p[b, a] = v
