"""Stage 4, features: the paper's 8 per-echo features from the MEMG fit.

Columns of the feature array (FEATURE_NAMES): alpha, mu, sigma, eta (the fit), echo
confidence (share of the echo's local energy the fit explains), power (the component's
sum over the frame, paper eq. 10), ToA (samples, by the chosen estimator) and frame
confidence (share of the channel's energy the whole fit explains).
"""

from __future__ import annotations

import math

import numpy as np

from spiel_edge._jit import jit
from spiel_edge.errors import InputError
from spiel_edge.pipeline.stages._validate import as_frames
from spiel_edge.pipeline.stages.memg import SQRT2, SQRT_2_OVER_PI, emg_arguments, emg_value

FEATURE_NAMES = (
    "alpha",
    "mu",
    "sigma",
    "eta",
    "echo_confidence",
    "power",
    "toa",
    "frame_confidence",
)
N_FEATURES = len(FEATURE_NAMES)
TOA_CODES = {"mode": 0, "mu": 1, "half": 2, "peak": 3}
TOA_COLUMN = FEATURE_NAMES.index("toa")


def echo_features(
    envelope: np.ndarray,
    params: np.ndarray,
    peaks: np.ndarray,
    toa: str = "mode",
    *,
    checked: bool = False,
) -> np.ndarray:
    """Return features (channels, max_echoes, 8), NaN where there is no echo; each channel's
    echoes ordered by ToA (fitted modes of overlapping echoes can swap their detection order).
    ``checked``: ``envelope`` is :func:`preprocess`'s output, validated there (a pipeline
    validates an acquisition once, pipeline/staged.py)."""
    y = envelope if checked else as_frames(envelope, "envelope")
    params = np.ascontiguousarray(params, dtype=np.float64)
    peaks = np.ascontiguousarray(peaks, dtype=np.int64)
    if (
        params.ndim != 3
        or params.shape[:1] != y.shape[:1]
        or params.shape[2] != 4
        or peaks.shape != params.shape[:2]
    ):
        raise InputError(
            "params must be (channels, max_echoes, 4) and peaks (channels, max_echoes)"
        )
    if toa not in TOA_CODES:
        raise InputError(f"toa must be one of {sorted(TOA_CODES)}, got {toa!r}")
    out = np.full(params.shape[:2] + (N_FEATURES,), np.nan)
    features_kernel(y, params, peaks, TOA_CODES[toa], out)
    order = np.argsort(
        np.where(np.isnan(out[:, :, TOA_COLUMN]), np.inf, out[:, :, TOA_COLUMN]),
        axis=1,
        kind="stable",
    )
    return np.take_along_axis(out, order[:, :, None], axis=1)


@jit
def component_mode(alpha, mu, sigma, eta):
    """Time of the component's maximum, mu + sigma * u with u the root of the shape's slope

        f(u) = -u (1 + erf(eta u / sqrt 2)) + eta sqrt(2 / pi) exp(-eta^2 u^2 / 2)

    (it depends on eta alone: f(0) has eta's sign and f falls on [-2, 3], where the bounded
    EMG is unimodal). Newton's method kept inside a shrinking sign-change bracket, bisecting
    when a step would leave it or not halve the last one: a handful of steps (2 transcendental calls each) where a golden
    section search needed 30 evaluations of the EMG."""
    lo, hi = -2.0, 3.0
    u = 0.5 * math.tanh(eta)  # within ~0.25 of the root for every eta in the bounds
    step_before = hi - lo
    for _ in range(100):
        e = 1.0 + math.erf(eta * u / SQRT2)
        s = SQRT_2_OVER_PI * math.exp(-0.5 * eta * eta * u * u)
        f = -u * e + eta * s
        if f > 0.0:
            lo = u
        else:
            hi = u
        slope = -e - eta * u * s * (1.0 + eta * eta)
        step = f / slope if slope < 0.0 else 0.0
        if slope < 0.0 and abs(step) <= 1e-12:
            u -= step  # converged (the new point may equal a bracket end)
            break
        if slope >= 0.0 or not lo < u - step < hi or abs(2.0 * step) > abs(step_before):
            step = u - 0.5 * (lo + hi)  # bisect: Newton would leave the bracket or stall
        step_before = step
        u -= step
        if abs(step) <= 1e-12 or hi - lo <= 1e-12:
            break
    return mu + sigma * u


@jit
def _leading_half_max(alpha, mu, sigma, eta, mode):
    peak = emg_value(mode, alpha, mu, sigma, eta)
    lo = mode - 6.0 * sigma
    hi = mode
    for _ in range(32):
        mid = 0.5 * (lo + hi)
        if emg_value(mid, alpha, mu, sigma, eta) < 0.5 * peak:
            lo = mid
        else:
            hi = mid
    return 0.5 * (lo + hi)


@jit
def interpolated_peak(y, k):
    """Sub-sample maximum of the data around sample k by a parabola through 3 samples."""
    n_t = y.shape[0]
    if k <= 0 or k >= n_t - 1:
        return float(k)
    den = y[k - 1] - 2.0 * y[k] + y[k + 1]
    if den >= 0.0:
        return float(k)
    return k + 0.5 * (y[k - 1] - y[k + 1]) / den


SUPPORT_SIGMAS = 6.0  # a component is below 1e-7 of its peak beyond mu +- 6 sigma


@jit
def _support(mu, sigma, n_t):
    lo = max(0, int(math.floor(mu - SUPPORT_SIGMAS * sigma)))
    hi = min(n_t, int(math.ceil(mu + SUPPORT_SIGMAS * sigma)) + 1)
    return lo, hi


LANES = 4  # channels whose whole-frame sums run side by side (independent addition chains)


@jit
def _channel_model(params, c, n_t, model, args, out):
    """The channel's fitted model into ``model`` (zeroed first) and each component's power
    (its sum over its support, the very values the model adds, in the same order) into
    out[c, k, 5]. Each value is :func:`emg_value`'s arithmetic; the divisions of the whole
    support go first (into ``args``, (2, n_t)), so they overlap instead of each waiting
    before its exp and erf."""
    model[:] = 0.0
    for k in range(params.shape[1]):
        alpha, mu, sigma, eta = params[c, k, 0], params[c, k, 1], params[c, k, 2], params[c, k, 3]
        if math.isnan(alpha):
            continue
        lo, hi = _support(mu, sigma, n_t)
        for t in range(lo, hi):
            _, args[0, t], args[1, t] = emg_arguments(float(t), mu, sigma, eta)
        power = 0.0
        for t in range(lo, hi):
            v = alpha * math.exp(args[0, t]) * (1.0 + math.erf(args[1, t]))
            model[t] += v
            power += v
        out[c, k, 5] = power


@jit
def _frame_confidence(energy, resid):
    frame_conf = 1.0 - resid / energy if energy > 0.0 else 0.0
    return min(max(frame_conf, 0.0), 1.0)


@jit
def features_kernel(y, params, peaks, toa_code, out):
    """Each sum over the frame (energy, residual) adds its terms in time order, one channel's
    after another's; the channels' chains run LANES at a time in one loop, which only changes
    how many run side by side, not any sum's order."""
    n_ch, n_t = y.shape
    model = np.zeros((LANES, n_t))
    args = np.empty((2, n_t))
    c0 = int(0)  # noqa: UP018 (an int64, not Literal[int]: one compiled signature)
    while c0 < n_ch:
        lanes = min(LANES, n_ch - c0)
        for i in range(lanes):
            _channel_model(params, c0 + i, n_t, model[i], args, out)
        if lanes == LANES:
            e0 = e1 = e2 = e3 = 0.0
            r0 = r1 = r2 = r3 = 0.0
            for t in range(n_t):
                e0 += y[c0, t] * y[c0, t]
                r0 += (y[c0, t] - model[0, t]) ** 2
                e1 += y[c0 + 1, t] * y[c0 + 1, t]
                r1 += (y[c0 + 1, t] - model[1, t]) ** 2
                e2 += y[c0 + 2, t] * y[c0 + 2, t]
                r2 += (y[c0 + 2, t] - model[2, t]) ** 2
                e3 += y[c0 + 3, t] * y[c0 + 3, t]
                r3 += (y[c0 + 3, t] - model[3, t]) ** 2
            _echo_rows(y, params, peaks, toa_code, c0, model[0], _frame_confidence(e0, r0), out)
            _echo_rows(y, params, peaks, toa_code, c0 + 1, model[1], _frame_confidence(e1, r1), out)
            _echo_rows(y, params, peaks, toa_code, c0 + 2, model[2], _frame_confidence(e2, r2), out)
            _echo_rows(y, params, peaks, toa_code, c0 + 3, model[3], _frame_confidence(e3, r3), out)
        else:
            for i in range(lanes):
                c = c0 + i
                energy = 0.0
                resid = 0.0
                for t in range(n_t):
                    energy += y[c, t] * y[c, t]
                    resid += (y[c, t] - model[i, t]) ** 2
                frame_conf = _frame_confidence(energy, resid)
                _echo_rows(y, params, peaks, toa_code, c, model[i], frame_conf, out)
        c0 += lanes


@jit
def _echo_rows(y, params, peaks, toa_code, c, model, frame_conf, out):
    """Channel c's feature rows (its powers already in out[c, :, 5])."""
    n_t = y.shape[1]
    for k in range(params.shape[1]):
        alpha, mu, sigma, eta = params[c, k, 0], params[c, k, 1], params[c, k, 2], params[c, k, 3]
        if math.isnan(alpha):
            continue
        mode = component_mode(alpha, mu, sigma, eta)
        lo = max(0, int(math.floor(mode - 2.0 * sigma)))
        hi = min(n_t, int(math.ceil(mode + 2.0 * sigma)) + 1)
        local_e = 0.0
        local_r = 0.0
        for t in range(lo, hi):
            local_e += y[c, t] * y[c, t]
            local_r += (y[c, t] - model[t]) ** 2
        echo_conf = 1.0 - local_r / local_e if local_e > 0.0 else 0.0
        if toa_code == 0:
            toa = mode
        elif toa_code == 1:
            toa = mu
        elif toa_code == 2:
            toa = _leading_half_max(alpha, mu, sigma, eta, mode)
        else:
            toa = interpolated_peak(y[c], peaks[c, k])
        out[c, k, 0] = alpha
        out[c, k, 1] = mu
        out[c, k, 2] = sigma
        out[c, k, 3] = eta
        out[c, k, 4] = min(max(echo_conf, 0.0), 1.0)
        out[c, k, 6] = toa
        out[c, k, 7] = frame_conf
