"""Stage 2, detect: echo candidates per channel from the envelope's gradient (paper eq. 1).

An echo starts where the gradient rises above ``threshold`` and ends once it falls below
``threshold * hysteresis``; its candidate time is the envelope's maximum between its start
and the next start. Hysteresis keeps one ragged rise from splitting into several echoes.
"""

from __future__ import annotations

import numpy as np

from spiel_edge._jit import jit
from spiel_edge.errors import InputError
from spiel_edge.pipeline.stages._validate import as_frames


def detect(
    envelope: np.ndarray,
    *,
    threshold: float,
    hysteresis: float = 0.5,
    min_amplitude: float = 0.0,
    max_echoes: int = 6,
    first_sample: int = 0,
    checked: bool = False,
) -> tuple[np.ndarray, np.ndarray]:
    """Return ``(peaks, counts)``: per channel up to ``max_echoes`` peak sample indices
    (int64, ascending, padded with -1) of the strongest echoes, and how many there are.

    Rises before ``first_sample`` are ignored: the edge of a blanked blind zone is no echo.
    ``checked``: ``envelope`` is :func:`preprocess`'s output, validated there (a pipeline
    validates an acquisition once, pipeline/staged.py).
    """
    y = envelope if checked else as_frames(envelope, "envelope")
    if threshold <= 0 or not 0.0 <= hysteresis <= 1.0 or max_echoes < 1:
        raise InputError("detect needs threshold > 0, hysteresis in [0, 1] and max_echoes >= 1")
    peaks = np.full((y.shape[0], max_echoes), -1, dtype=np.int64)
    counts = np.zeros(y.shape[0], dtype=np.int64)
    detect_kernel(
        y,
        float(threshold),
        float(threshold * hysteresis),
        float(min_amplitude),
        int(first_sample),
        peaks,
        counts,
    )
    return peaks, counts


@jit
def detect_kernel(y, hi, lo, min_amp, first, peaks, counts):
    """One pass per channel: the gradient's rises open echoes and each echo's maximum is
    tracked as the pass goes (sample t - 1 joins the open echo once step t has shown that no
    new echo starts there), the first of equal maxima as an argmax from its start."""
    n_ch, n_t = y.shape
    k_max = peaks.shape[1]
    cand = np.empty(n_t, dtype=np.int64)
    amp = np.empty(n_t)
    for c in range(n_ch):
        n_cand = 0
        t = max(1, first + 1)
        while t < n_t and not y[c, t] - y[c, t - 1] > hi:  # before the first echo
            t += 1
        if t < n_t:
            rising = True
            best = t - 1  # the open echo's maximum so far (the first of equal ones)
            y_best = y[c, t - 1]
            for t in range(best + 2, n_t):
                prev = y[c, t - 1]
                g = y[c, t] - prev
                if rising:
                    if g < lo:
                        rising = False
                elif g > hi:  # a new echo starts at t - 1: the open one ends before it
                    if y_best >= min_amp:
                        cand[n_cand] = best
                        amp[n_cand] = y_best
                        n_cand += 1
                    rising = True
                    best = t - 1
                    y_best = prev
                    continue
                if prev > y_best:
                    best = t - 1
                    y_best = prev
            if y[c, n_t - 1] > y_best:  # the last echo runs to the frame's end
                best = n_t - 1
                y_best = y[c, n_t - 1]
            if y_best >= min_amp:
                cand[n_cand] = best
                amp[n_cand] = y_best
                n_cand += 1
        # keep the strongest k_max (the earlier of equally strong), then report in time order
        keep = min(n_cand, k_max)
        for j in range(keep):
            m = j
            for i in range(j + 1, n_cand):
                if amp[i] > amp[m] or (amp[i] == amp[m] and cand[i] < cand[m]):
                    m = i
            amp[j], amp[m] = amp[m], amp[j]
            cand[j], cand[m] = cand[m], cand[j]
        for j in range(1, keep):
            v = cand[j]
            i = j - 1
            while i >= 0 and cand[i] > v:
                cand[i + 1] = cand[i]
                i -= 1
            cand[i + 1] = v
        for j in range(keep):
            peaks[c, j] = cand[j]
        counts[c] = keep
