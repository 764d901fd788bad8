"""I/Q samples (SampleFormat.I16_IQ) to the envelope the pipeline takes, and the phase kept.

The board sends int16 (q, i) pairs per sample, in the order TDK SonicLib's ``ch_get_iq_data``
fills them; the envelope is their magnitude rounded to a whole count, which is what the CH101's
own amplitude data (``ch_get_amplitude_data``) is, so an I/Q stream feeds the pipeline the same
numbers as an amplitude stream of the same acquisitions. One small numba kernel, called before
the pipeline; the phase ``atan2(q, i)`` (radians) is computed from the kept pairs when it is
asked for (recordings), off the pipeline's path.
"""

from __future__ import annotations

import math

import numpy as np

from spiel_edge._jit import jit
from spiel_edge.errors import InputError

__all__ = ["iq_amplitude", "iq_envelope", "iq_envelope_reference", "iq_phase"]


def _checked(pairs: np.ndarray) -> np.ndarray:
    if not (
        isinstance(pairs, np.ndarray)
        and pairs.ndim == 2
        and pairs.dtype == np.int16
        and not pairs.shape[1] % 2
    ):
        arr = np.asarray(pairs)
        raise InputError(
            f"I/Q samples must be (channels, 2 x samples) int16, got {arr.shape} {arr.dtype}"
        )
    return pairs if pairs.flags.c_contiguous else np.ascontiguousarray(pairs)


def iq_amplitude(pairs: np.ndarray) -> np.ndarray:
    """``pairs``: (channels, 2 * samples) int16, q and i interleaved (the wire order).
    The envelope (channels, samples) float64: the magnitude rounded to a whole count."""
    pairs = _checked(pairs)
    envelope = np.empty((pairs.shape[0], pairs.shape[1] // 2), dtype=np.float64)
    _amplitude_kernel(pairs, envelope)
    return envelope


def iq_phase(pairs: np.ndarray) -> np.ndarray:
    """The phase atan2(q, i), (channels, samples) float32 radians."""
    pairs = _checked(pairs)
    return np.arctan2(pairs[:, 0::2], pairs[:, 1::2], dtype=np.float32)


def iq_envelope(pairs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(envelope float64, phase float32), each (channels, samples)."""
    return iq_amplitude(pairs), iq_phase(pairs)


@jit
def _amplitude_kernel(pairs, envelope):
    n_ch, n = envelope.shape
    for c in range(n_ch):
        for k in range(n):
            q = float(pairs[c, 2 * k])
            i = float(pairs[c, 2 * k + 1])
            envelope[c, k] = math.floor(math.sqrt(i * i + q * q) + 0.5)


def iq_envelope_reference(pairs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Plain numpy, for tests."""
    q = pairs[:, 0::2].astype(np.float64)
    i = pairs[:, 1::2].astype(np.float64)
    return np.floor(np.hypot(i, q) + 0.5), np.arctan2(q, i).astype(np.float32)
