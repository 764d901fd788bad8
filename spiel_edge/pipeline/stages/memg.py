"""Stage 3, memg: fit a sum of exponentially modified Gaussians (paper eq. 7-10) per channel.

    m(t) = alpha * exp(-u^2 / 2) * (1 + erf(eta * u / sqrt 2)),   u = (t - mu) / sigma

Levenberg-Marquardt with the analytic Jacobian, bounded iterations and box constraints
(alpha > 0, sigma in [SIGMA_MIN, SIGMA_MAX], eta in [ETA_MIN, ETA_MAX], mu within
``mu_window`` of its detection). Echoes closer than CLUSTER_GAP samples are fitted jointly
over their common window; isolated echoes alone over a short window, which keeps the normal
equations tiny (4-8 parameters) and the cost linear in the number of echoes.
"""

from __future__ import annotations

import math

import numpy as np

from spiel_edge._jit import jit
from spiel_edge.errors import InputError
from spiel_edge.pipeline.stages._validate import as_frames

SIGMA_MIN, SIGMA_MAX = 0.4, 6.0
ETA_MIN, ETA_MAX = -4.0, 8.0
CLUSTER_GAP = 7  # samples between peaks below which two echoes overlap enough to share a fit
WINDOW_BEFORE, WINDOW_AFTER = 5, 6
SQRT2 = math.sqrt(2.0)
SQRT_2_OVER_PI = math.sqrt(2.0 / math.pi)
LAMBDA_START, LAMBDA_DOWN = 1e-2, 1.0 / 3.0
REL_TOL = 1e-3  # stop when an accepted step lowers the cost by less than this share


def fit_memg(
    envelope: np.ndarray,
    peaks: np.ndarray,
    counts: np.ndarray,
    *,
    mu_window: float = 3.0,
    max_iterations: int = 30,
    window_before: int = WINDOW_BEFORE,
    window_after: int = WINDOW_AFTER,
    checked: bool = False,
) -> np.ndarray:
    """Return MEMG parameters (channels, max_echoes, 4) as [alpha, mu, sigma, eta] per echo
    (NaN where there is no echo), from the outputs of :func:`detect`. Each echo (or cluster)
    is fitted from ``window_before`` samples before its detection to ``window_after`` after
    (the profile's ``[memg]``): the default 5/6 runs in one compiled call, any other window
    cluster by cluster (:func:`_fit_windowed`, the same compiled fit per cluster).
    ``checked``: ``envelope`` is :func:`preprocess`'s output, validated there (a pipeline
    validates an acquisition once, pipeline/staged.py)."""
    y = envelope if checked else as_frames(envelope, "envelope")
    peaks = np.ascontiguousarray(peaks, dtype=np.int64)
    counts = np.ascontiguousarray(counts, dtype=np.int64)
    if peaks.ndim != 2 or peaks.shape[0] != y.shape[0] or counts.shape != (y.shape[0],):
        raise InputError("peaks must be (channels, max_echoes) and counts (channels,)")
    problem = _check_peaks(peaks, counts, y.shape[1])
    if problem == 1:
        raise InputError("counts must be in [0, max_echoes]")
    if problem == 2:
        raise InputError("peaks must be ascending sample indices inside the frame")
    if mu_window <= 0 or max_iterations < 1:
        raise InputError("mu_window must be > 0 and max_iterations >= 1")
    if not (1 <= window_before <= 64 and 1 <= window_after <= 64):
        raise InputError("window_before and window_after must be in [1, 64]")
    params = np.full((y.shape[0], peaks.shape[1], 4), np.nan)
    iterations = np.zeros(peaks.shape, dtype=np.int64)
    if (window_before, window_after) == (WINDOW_BEFORE, WINDOW_AFTER):
        memg_kernel(y, peaks, counts, float(mu_window), int(max_iterations), params, iterations)
    else:
        window = (int(window_before), int(window_after))
        _fit_windowed(y, peaks, counts, float(mu_window), int(max_iterations), window, params)
    return params


def _fit_windowed(y, peaks, counts, mu_window, max_iter, window, params) -> None:
    """:func:`memg_kernel`'s clusters and windows with another window, each cluster by the
    compiled :func:`fit_cluster` (no kernel of its own: boards with other windows have one
    or two channels, a few echoes each)."""
    before, after = window
    n_t = y.shape[1]
    p = np.empty(4 * peaks.shape[1])
    for c in range(y.shape[0]):
        first = 0
        while first < counts[c]:
            last = first
            while last + 1 < counts[c] and peaks[c, last + 1] - peaks[c, last] < CLUSTER_GAP:
                last += 1
            n_comp = last - first + 1
            lo = max(0, int(peaks[c, first]) - before)
            hi = min(n_t, int(peaks[c, last]) + after + 1)
            n_par = 4 * n_comp
            work = np.empty(
                2 * n_comp + 4 * n_par + 2 * n_par * n_par + (3 * n_comp + 1) * (hi - lo)
            )
            fit_cluster(
                y[c], lo, hi, peaks[c, first : last + 1], n_comp, mu_window, max_iter, p, work
            )
            params[c, first : last + 1] = p[:n_par].reshape(n_comp, 4)
            first = last + 1


@jit
def _check_peaks(peaks, counts, n_t):
    """0 when valid; 1 for a count out of range; 2 for peaks not ascending inside the frame
    (a compiled check: numpy's per-call overhead would cost more than the fit itself)."""
    for c in range(peaks.shape[0]):
        if counts[c] < 0 or counts[c] > peaks.shape[1]:
            return 1
        for k in range(counts[c]):
            if peaks[c, k] < 0 or peaks[c, k] >= n_t or (k > 0 and peaks[c, k] <= peaks[c, k - 1]):
                return 2
    return 0


@jit(inline="always")
def emg_arguments(t, mu, sigma, eta):
    """u and the arguments of the exp and the erf in :func:`_emg_shape`."""
    u = (t - mu) / sigma
    return u, -0.5 * u * u, eta * u / SQRT2


@jit(inline="always")
def emg_value(t, alpha, mu, sigma, eta):
    _, x_exp, x_erf = emg_arguments(t, mu, sigma, eta)
    return alpha * math.exp(x_exp) * (1.0 + math.erf(x_erf))


@jit(inline="always")
def _emg_shape(t, mu, sigma, eta):
    """u, the Gaussian g and the skew factor e of one component at t (its value: alpha g e)."""
    u, x_exp, x_erf = emg_arguments(t, mu, sigma, eta)
    return u, math.exp(x_exp), 1.0 + math.erf(x_erf)


@jit(inline="always")
def _emg_slopes(alpha, sigma, eta, u, g, e):
    """d/d alpha, d/d mu, d/d sigma, d/d eta of one component from its :func:`_emg_shape`."""
    s = SQRT_2_OVER_PI * math.exp(-0.5 * eta * eta * u * u)
    dm_du = alpha * g * (-u * e + eta * s)
    return g * e, -dm_du / sigma, -dm_du * u / sigma, alpha * g * s * u


@jit(inline="always")
def _clamp(p, n_comp, lower_mu, upper_mu, alpha_max):
    for k in range(n_comp):
        p[4 * k] = min(max(p[4 * k], 1e-6), alpha_max)
        p[4 * k + 1] = min(max(p[4 * k + 1], lower_mu[k]), upper_mu[k])
        p[4 * k + 2] = min(max(p[4 * k + 2], SIGMA_MIN), SIGMA_MAX)
        p[4 * k + 3] = min(max(p[4 * k + 3], ETA_MIN), ETA_MAX)


@jit
def solve_spd(a, b, n, x):
    """Solve a x = b for the leading n x n block of a symmetric positive definite a
    (Cholesky, in place on a). Returns False when a is not positive definite."""
    return _solve_spd_inline(a, b, n, x)


@jit(inline="always")
def _solve_spd_inline(a, b, n, x):
    """:func:`solve_spd`'s body, compiled into the fit (a call would cost an atomic reference
    count per array)."""
    for j in range(n):
        d = a[j, j]
        for k in range(j):
            d -= a[j, k] * a[j, k]
        if d <= 1e-300:
            return False
        d = math.sqrt(d)
        a[j, j] = d
        for i in range(j + 1, n):
            s = a[i, j]
            for k in range(j):
                s -= a[i, k] * a[j, k]
            a[i, j] = s / d
    for i in range(n):
        s = b[i]
        for k in range(i):
            s -= a[i, k] * x[k]
        x[i] = s / a[i, i]
    for i in range(n - 1, -1, -1):
        s = x[i]
        for k in range(i + 1, n):
            s -= a[k, i] * x[k]
        x[i] = s / a[i, i]
    return True


@jit
def work_size(n_comp):
    """Floats of :func:`fit_cluster`'s ``work`` for up to n_comp components (the window of
    n_comp detections, each within CLUSTER_GAP of the next, spans < window_size samples)."""
    n_par = 4 * n_comp
    return 2 * n_comp + 4 * n_par + 2 * n_par * n_par + (3 * n_comp + 1) * window_size(n_comp)


@jit
def window_size(n_comp):
    return WINDOW_BEFORE + WINDOW_AFTER + 1 + (n_comp - 1) * (CLUSTER_GAP - 1)


@jit(inline="always")
def trial_cost(y, lo, hi, p, n_comp, shape, resid, bound):
    """The cost sum r^2 at p over y[lo:hi] (the same sum as
    ``tests/core/naive.normal_equations``, the one-pass reference); each
    component's u, g, e go to shape[3 * (n_comp * i + k):][:3] and the residuals to resid[i]
    (i = t - lo), from which :func:`jacobian_sums` makes the normal equations.

    Stops early, returning the partial sum, once it reaches ``bound`` (the cost to beat): a
    sum of non-negative terms never falls as terms are added (rounding is monotone), so the
    step is rejected either way and the full cost would not be used (inf: no early stop)."""
    # first the divisions of every sample (independent of each other, so they overlap),
    # then the exp and erf calls on their results: _emg_shape's arithmetic, in two passes
    for k in range(n_comp):
        mu, sigma, eta = p[4 * k + 1], p[4 * k + 2], p[4 * k + 3]
        for t in range(lo, hi):
            at = 3 * (n_comp * (t - lo) + k)
            shape[at], shape[at + 1], shape[at + 2] = emg_arguments(float(t), mu, sigma, eta)
    cost = 0.0
    for t in range(lo, hi):
        i = t - lo
        m = 0.0
        for k in range(n_comp):
            at = 3 * (n_comp * i + k)
            g = math.exp(shape[at + 1])
            e = 1.0 + math.erf(shape[at + 2])
            m += p[4 * k] * g * e
            shape[at + 1], shape[at + 2] = g, e
        r = y[t] - m
        resid[i] = r
        cost += r * r
        if cost >= bound:
            return cost
    return cost


@jit(inline="always")
def jacobian_sums(n_win, p, n_comp, shape, resid, jac_row, a, b):
    """J^T J into a and J^T r into b from :func:`trial_cost`'s stores for the same p: the
    terms and their order are ``tests/core/naive.normal_equations``, so a and b are its bit
    for bit."""
    if n_comp == 1:
        _jacobian_sums_1(n_win, p[0], p[2], p[3], shape, resid, a, b)
        return
    n_par = 4 * n_comp
    a[:, :] = 0.0
    b[:] = 0.0
    for i in range(n_win):
        for k in range(n_comp):
            at = 3 * (n_comp * i + k)
            jac_row[4 * k], jac_row[4 * k + 1], jac_row[4 * k + 2], jac_row[4 * k + 3] = (
                _emg_slopes(
                    p[4 * k], p[4 * k + 2], p[4 * k + 3], shape[at], shape[at + 1], shape[at + 2]
                )
            )
        r = resid[i]
        for i2 in range(n_par):
            b[i2] += jac_row[i2] * r
            for j in range(i2 + 1):
                a[i2, j] += jac_row[i2] * jac_row[j]
    for i2 in range(n_par):
        for j in range(i2 + 1, n_par):
            a[i2, j] = a[j, i2]


@jit(inline="always")
def _jacobian_sums_1(n_win, alpha, sigma, eta, shape, resid, a, b):
    """:func:`jacobian_sums` for one component, its sums in registers."""
    a00 = a10 = a11 = a20 = a21 = a22 = a30 = a31 = a32 = a33 = 0.0
    b0 = b1 = b2 = b3 = 0.0
    for i in range(n_win):
        j0, j1, j2, j3 = _emg_slopes(
            alpha, sigma, eta, shape[3 * i], shape[3 * i + 1], shape[3 * i + 2]
        )
        r = resid[i]
        b0 += j0 * r
        a00 += j0 * j0
        b1 += j1 * r
        a10 += j1 * j0
        a11 += j1 * j1
        b2 += j2 * r
        a20 += j2 * j0
        a21 += j2 * j1
        a22 += j2 * j2
        b3 += j3 * r
        a30 += j3 * j0
        a31 += j3 * j1
        a32 += j3 * j2
        a33 += j3 * j3
    b[0], b[1], b[2], b[3] = b0, b1, b2, b3
    a[0, 0], a[0, 1], a[0, 2], a[0, 3] = a00, a10, a20, a30
    a[1, 0], a[1, 1], a[1, 2], a[1, 3] = a10, a11, a21, a31
    a[2, 0], a[2, 1], a[2, 2], a[2, 3] = a20, a21, a22, a32
    a[3, 0], a[3, 1], a[3, 2], a[3, 3] = a30, a31, a32, a33


# _nrt=False: the fit allocates nothing (numba refuses to compile it if it did), and without
# the runtime the views of ``work`` and the arrays handed to its steps skip their atomic
# reference counts, which took ~20 % of its time (perf: NRT_incref / NRT_decref)
@jit(_nrt=False)
def fit_cluster(y, lo, hi, peaks, n_comp, mu_window, max_iter, p, work):
    """LM on components fitted jointly over y[lo:hi]; p holds 4 * n_comp parameters.

    A trial evaluates the cost alone, keeping each sample's u, g, e and residual; only an
    accepted step that the fit goes on from turns them into the next normal equations
    (:func:`jacobian_sums`), so rejected and final steps cost no Jacobian. Stops when an
    accepted step lowers the cost by less than REL_TOL of itself: the fits that ran to the cap
    were weakly identified shapes (eta or sigma at a bound, wide flat echoes) creeping along a
    flat valley with no effect on the ToA (docs/performance.md).
    ``work`` is a scratch buffer (>= work_size(K) floats for K components, whose window must
    be at most window_size(K) samples) so the hot loop allocates nothing. Returns the number
    of iterations."""
    n_par = 4 * n_comp
    lower_mu = work[0:n_comp]
    upper_mu = work[n_comp : 2 * n_comp]
    y_max = 0.0
    for t in range(lo, hi):
        y_max = max(y_max, y[t])
    for k in range(n_comp):
        pk = float(peaks[k])
        # the mode of a right-skewed EMG lies after mu: start mu a little before the peak
        p[4 * k] = max(y[peaks[k]], 1e-3) * 0.6
        p[4 * k + 1] = pk - 0.5
        p[4 * k + 2] = 1.5
        p[4 * k + 3] = 1.0
        lower_mu[k] = pk - mu_window
        upper_mu[k] = pk + mu_window
    alpha_max = 4.0 * y_max + 1.0
    base = 2 * n_comp
    jac_row = work[base : base + n_par]
    b = work[base + n_par : base + 2 * n_par]
    step = work[base + 2 * n_par : base + 3 * n_par]
    trial = work[base + 3 * n_par : base + 4 * n_par]
    start = base + 4 * n_par
    nn = n_par * n_par
    a = work[start : start + nn].reshape((n_par, n_par))
    damped = work[start + nn : start + 2 * nn].reshape((n_par, n_par))
    n_win = hi - lo
    start += 2 * nn
    shape = work[start : start + 3 * n_comp * n_win]
    resid = work[start + 3 * n_comp * n_win : start + (3 * n_comp + 1) * n_win]
    lam = LAMBDA_START
    cost = trial_cost(y, lo, hi, p, n_comp, shape, resid, np.inf)
    jacobian_sums(n_win, p, n_comp, shape, resid, jac_row, a, b)
    iterations = 0
    for it in range(max_iter):
        iterations += 1
        improved = False
        for _try in range(8):
            for i in range(n_par):
                for j in range(n_par):
                    damped[i, j] = a[i, j]
                damped[i, i] += lam * (a[i, i] + 1e-9)
            if not _solve_spd_inline(damped, b, n_par, step):
                lam *= 10.0
                continue
            for i in range(n_par):
                trial[i] = p[i] + step[i]
            _clamp(trial, n_comp, lower_mu, upper_mu, alpha_max)
            new_cost = trial_cost(y, lo, hi, trial, n_comp, shape, resid, cost)
            if new_cost < cost:
                converged = cost - new_cost <= REL_TOL * cost
                for i in range(n_par):
                    p[i] = trial[i]
                if not converged and it + 1 < max_iter:  # the fit goes on from here
                    jacobian_sums(n_win, p, n_comp, shape, resid, jac_row, a, b)
                cost = new_cost
                lam = max(lam * LAMBDA_DOWN, 1e-7)
                improved = not converged
                break
            lam *= 4.0
        if not improved:
            break
    return iterations


@jit
def memg_kernel(y, peaks, counts, mu_window, max_iter, params, iterations):
    """Fit every channel's echoes into params; LM iterations per echo into iterations."""
    n_ch, n_t = y.shape
    n_max = 4 * peaks.shape[1]
    p = np.empty(n_max)
    work = np.empty(work_size(peaks.shape[1]))
    for c in range(n_ch):
        first = 0
        while first < counts[c]:
            last = first
            while last + 1 < counts[c] and peaks[c, last + 1] - peaks[c, last] < CLUSTER_GAP:
                last += 1
            n_comp = last - first + 1
            lo = max(0, peaks[c, first] - WINDOW_BEFORE)
            hi = min(n_t, peaks[c, last] + WINDOW_AFTER + 1)
            used = fit_cluster(
                y[c], lo, hi, peaks[c, first : last + 1], n_comp, mu_window, max_iter, p, work
            )
            for k in range(n_comp):
                iterations[c, first + k] = used
                for j in range(4):
                    params[c, first + k, j] = p[4 * k + j]
            first = last + 1
