"""Stage 1, preprocess: envelope (RF boards), background subtraction and clip, blind zone."""

from __future__ import annotations

import numpy as np

from spiel_edge._jit import jit
from spiel_edge.errors import InputError
from spiel_edge.pipeline.stages._validate import as_frames


def preprocess(
    frames: np.ndarray,
    background: np.ndarray | None = None,
    *,
    blind_zone: int = 0,
    rf: bool = False,
    carrier_cycles_per_sample: float = 0.0,
) -> np.ndarray:
    """Return the cleaned (channels, samples) envelope as a new float64 array.

    ``rf=True`` first turns RF samples into an envelope (see :func:`envelope`); the background,
    if given, must then be RF too. Background subtraction clips at 0 because an envelope
    cannot be negative: what is left is energy the empty scene did not have.
    """
    y = as_frames(frames)
    bg = np.zeros((0, 0)) if background is None else as_frames(background, "background")
    if bg.size and bg.shape != y.shape:
        raise InputError(f"background shape {bg.shape} does not match frames shape {y.shape}")
    if not 0 <= blind_zone <= y.shape[1]:
        raise InputError(f"blind_zone must be in [0, {y.shape[1]}], got {blind_zone}")
    if rf:
        y = envelope(y, carrier_cycles_per_sample)
        if bg.size:
            bg = envelope(bg, carrier_cycles_per_sample)
    out = np.empty_like(y)
    preprocess_kernel(y, bg, int(blind_zone), out)
    return out


@jit
def preprocess_kernel(y, bg, blind_zone, out):
    n_ch, n_t = y.shape
    subtract = bg.shape[0] == n_ch
    for c in range(n_ch):
        for t in range(n_t):
            if t < blind_zone:
                out[c, t] = 0.0
                continue
            v = y[c, t] - bg[c, t] if subtract else y[c, t]
            out[c, t] = v if v > 0.0 else 0.0


def envelope(rf: np.ndarray, carrier_cycles_per_sample: float) -> np.ndarray:
    """Amplitude envelope of RF samples by I/Q demodulation at the carrier and a short low-pass.

    A Hilbert transform needs an FFT (not in numba's nopython mode); mixing down and
    averaging over one carrier period is O(T) and as accurate for narrow-band pulses.
    ``carrier_cycles_per_sample`` is carrier_hz / sample_rate_hz, in (0, 0.5).
    """
    y = as_frames(rf, "rf")
    if not 0.0 < carrier_cycles_per_sample < 0.5:
        raise InputError(
            f"carrier_cycles_per_sample must be in (0, 0.5), got {carrier_cycles_per_sample}"
        )
    half_width = max(1, int(round(0.5 / carrier_cycles_per_sample)))
    out = np.empty_like(y)
    envelope_kernel(y, carrier_cycles_per_sample, half_width, out)
    return out


@jit
def envelope_kernel(y, f, half_width, out):
    n_ch, n_t = y.shape
    i_mix = np.empty(n_t)
    q_mix = np.empty(n_t)
    for c in range(n_ch):
        mean = 0.0
        for t in range(n_t):
            mean += y[c, t]
        mean /= n_t
        for t in range(n_t):
            phase = 2.0 * np.pi * f * t
            v = y[c, t] - mean
            i_mix[t] = v * np.cos(phase)
            q_mix[t] = -v * np.sin(phase)
        for t in range(n_t):
            lo = max(0, t - half_width)
            hi = min(n_t, t + half_width + 1)
            si = 0.0
            sq = 0.0
            for k in range(lo, hi):
                si += i_mix[k]
                sq += q_mix[k]
            m = hi - lo
            out[c, t] = 2.0 * np.sqrt(si * si + sq * sq) / m
