"""Stage 3b (optional, ``[memg] split_merged``): split merged echoes after the MEMG fit.

Two targets whose echoes are 2-5 samples apart on a channel form one envelope hump: detect sees
one rise and MEMG fits one component whose mode lies between the two (docs/localisation.md,
"Two targets at one range: the front end"). For every echo fitted alone whose component is
wider than a single echo of this board (sigma >= ``min_sigma``), one two-component fit starts
at the detection -/+ SPLIT_OFFSET samples (exactly MEMG's fit had detect reported those two
samples); it replaces the one component when, over that fit's window, it leaves at most
``max_cost_ratio`` of the one-component residual and its
weaker component has at least MIN_SHARE of the stronger's amplitude. The second component
takes a free echo slot, so the step costs at most ``max_echoes - count`` extra fits per
channel and never exceeds ``max_echoes``.
"""

from __future__ import annotations

import numpy as np

from spiel_edge._jit import jit
from spiel_edge.errors import InputError
from spiel_edge.pipeline.stages._validate import as_frames
from spiel_edge.pipeline.stages.memg import (
    CLUSTER_GAP,
    WINDOW_AFTER,
    WINDOW_BEFORE,
    emg_value,
    fit_cluster,
    work_size,
)

SPLIT_OFFSET = 2  # samples either side of the detection where the two components start
MIN_SHARE = 0.15  # the weaker component's amplitude over the stronger's: below, a skew fit
ONE_COMPONENT, TWO_COMPONENTS = 1, 2  # passed as int(...): numba compiles int64, not Literal[int]
N_PAR_2 = 8


def split_merged(
    envelope: np.ndarray,
    peaks: np.ndarray,
    counts: np.ndarray,
    params: np.ndarray,
    *,
    min_sigma: float,
    max_cost_ratio: float,
    mu_window: float = 3.0,
    max_iterations: int = 30,
    checked: bool = False,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Return new ``(peaks, counts, params)`` with merged echoes split in two (the inputs are
    the outputs of :func:`detect` and :func:`fit_memg`; they are not modified). A split
    echo's two peaks are its start samples, detection -/+ SPLIT_OFFSET; the new one is
    inserted in time order.
    ``checked``: ``envelope`` is :func:`preprocess`'s output, validated there (a pipeline
    validates an acquisition once, pipeline/staged.py)."""
    y = envelope if checked else as_frames(envelope, "envelope")
    peaks = np.array(peaks, dtype=np.int64)
    counts = np.array(counts, dtype=np.int64)
    params = np.array(params, dtype=np.float64)
    if (
        peaks.ndim != 2
        or peaks.shape[0] != y.shape[0]
        or counts.shape != (y.shape[0],)
        or params.shape != peaks.shape + (4,)
    ):
        raise InputError(
            "peaks must be (channels, max_echoes), counts (channels,) and params "
            "(channels, max_echoes, 4)"
        )
    if (counts < 0).any() or (counts > peaks.shape[1]).any():
        raise InputError("counts must be in [0, max_echoes]")
    if not min_sigma > 0 or not 0 < max_cost_ratio <= 1:
        raise InputError("split needs min_sigma > 0 and max_cost_ratio in (0, 1]")
    if mu_window <= 0 or max_iterations < 1:
        raise InputError("mu_window must be > 0 and max_iterations >= 1")
    iterations = np.zeros(peaks.shape, dtype=np.int64)
    split_kernel(
        y,
        peaks,
        counts,
        params,
        iterations,
        float(min_sigma),
        float(max_cost_ratio),
        float(mu_window),
        int(max_iterations),
    )
    return peaks, counts, params


@jit
def _window_cost(y, lo, hi, p, n_comp):
    cost = 0.0
    for t in range(lo, hi):
        m = 0.0
        for k in range(n_comp):
            m += emg_value(float(t), p[4 * k], p[4 * k + 1], p[4 * k + 2], p[4 * k + 3])
        cost += (y[t] - m) ** 2
    return cost


@jit
def _isolated(peaks, n, k):
    """Echo k was fitted alone by MEMG (no other detection within CLUSTER_GAP)."""
    before = k == 0 or peaks[k] - peaks[k - 1] >= CLUSTER_GAP
    after = k == n - 1 or peaks[k + 1] - peaks[k] >= CLUSTER_GAP
    return before and after


@jit
def _insert(peaks, params, iterations, n, at, peak, p, used):
    """Insert one echo at index ``at`` of the first n (shifting the rest back by one)."""
    for j in range(n, at, -1):
        peaks[j] = peaks[j - 1]
        iterations[j] = iterations[j - 1]
        for i in range(4):
            params[j, i] = params[j - 1, i]
    peaks[at] = peak
    iterations[at] = used
    for i in range(4):
        params[at, i] = p[i]


@jit
def split_kernel(y, peaks, counts, params, iterations, min_sigma, max_ratio, mu_window, max_iter):
    """In place on one acquisition's peaks, counts, params and iterations."""
    n_ch, n_t = y.shape
    k_max = peaks.shape[1]
    p = np.empty(N_PAR_2)
    one = np.empty(4)
    starts = np.empty(2, dtype=np.int64)
    work = np.empty(work_size(int(TWO_COMPONENTS)))
    alone = np.empty(k_max, dtype=np.bool_)
    for c in range(n_ch):
        n0 = counts[c]
        for j in range(n0):
            alone[j] = _isolated(peaks[c], n0, j)  # on the detections, before any split
        shift = 0
        for j in range(n0):
            n = counts[c]
            if n >= k_max:
                break
            k = j + shift
            pk = peaks[c, k]
            if not alone[j] or not params[c, k, 2] >= min_sigma:
                continue
            starts[0] = max(pk - SPLIT_OFFSET, 0)
            starts[1] = min(pk + SPLIT_OFFSET, n_t - 1)
            # MEMG's window for these two detections: the two-component fit is the one MEMG
            # would make had detect reported them
            lo = max(0, starts[0] - WINDOW_BEFORE)
            hi = min(n_t, starts[1] + WINDOW_AFTER + 1)
            for i in range(4):
                one[i] = params[c, k, i]
            cost1 = _window_cost(y[c], lo, hi, one, int(ONE_COMPONENT))
            used = fit_cluster(
                y[c], lo, hi, starts, int(TWO_COMPONENTS), mu_window, max_iter, p, work
            )
            cost2 = _window_cost(y[c], lo, hi, p, int(TWO_COMPONENTS))
            weak, strong = min(p[0], p[4]), max(p[0], p[4])
            if cost2 <= max_ratio * cost1 and weak >= MIN_SHARE * strong:
                for i in range(4):
                    params[c, k, i] = p[i]
                peaks[c, k] = starts[0]
                iterations[c, k] = used
                _insert(peaks[c], params[c], iterations[c], n, k + 1, starts[1], p[4:], used)
                counts[c] = n + 1
                shift += 1
