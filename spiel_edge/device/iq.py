"""I/Q samples (SampleFormat.I16_IQ) to the envelope the pipeline takes, and the phase kept.

The board sends int16 (q, i) pairs per sample, in the order TDK SonicLib's ``ch_get_iq_data``
fills them; the envelope is their magnitude rounded to a whole count, which is what the CH101's
own amplitude data (``ch_get_amplitude_data``) is, so an I/Q stream feeds the pipeline the same
numbers as an amplitude stream of the same acquisitions; the phase is ``atan2(q, i)`` in
radians. One small numba kernel, called before the pipeline.
"""

from __future__ import annotations

import math

import numpy as np

from spiel_edge._jit import jit
from spiel_edge.errors import InputError

__all__ = ["iq_envelope", "iq_envelope_reference"]


def iq_envelope(pairs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``pairs``: (channels, 2 * samples) int16, q and i interleaved (the wire order).
    Returns (envelope float64, phase float32), each (channels, samples)."""
    arr = np.asarray(pairs)
    if arr.ndim != 2 or arr.shape[1] % 2 or arr.dtype != np.int16:
        raise InputError(
            f"I/Q samples must be (channels, 2 x samples) int16, got {arr.shape} {arr.dtype}"
        )
    arr = np.ascontiguousarray(arr)
    n_ch, n = arr.shape[0], arr.shape[1] // 2
    envelope = np.empty((n_ch, n), dtype=np.float64)
    phase = np.empty((n_ch, n), dtype=np.float32)
    _iq_kernel(arr, envelope, phase)
    return envelope, phase


@jit
def _iq_kernel(pairs, envelope, phase):
    n_ch, n = envelope.shape
    for c in range(n_ch):
        for k in range(n):
            q = float(pairs[c, 2 * k])
            i = float(pairs[c, 2 * k + 1])
            envelope[c, k] = math.floor(math.sqrt(i * i + q * q) + 0.5)
            phase[c, k] = math.atan2(q, i)


def iq_envelope_reference(pairs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Plain numpy, for tests."""
    q = pairs[:, 0::2].astype(np.float64)
    i = pairs[:, 1::2].astype(np.float64)
    return np.floor(np.hypot(i, q) + 0.5), np.arctan2(q, i).astype(np.float32)
