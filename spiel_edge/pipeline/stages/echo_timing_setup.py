"""Build the echo-timing step a profile asks for (the step, its learned correction, its delays).

Apart from :mod:`spiel_edge.pipeline.stages.echo_timing` so that the correction, which needs the
step's feature layout, and the step do not import each other.
"""

from __future__ import annotations

import numpy as np

from spiel_edge.pipeline.learned.toa_correction import build_correction
from spiel_edge.pipeline.stages.echo_timing import EchoTiming


def build_echo_timing(profile, toa_correction: str | None = None) -> EchoTiming:
    """The profile's step; ``toa_correction`` (auto|onnx|none) overrides the profile's.
    RF boards keep the MEMG ToA: the step works on envelopes."""
    spec = profile.echo_timing
    estimator = spec.estimator if profile.acquisition.signal == "envelope" else "none"
    correction = None
    if estimator != "none":
        correction = build_correction(
            toa_correction or spec.toa_correction, profile.geometry.n_channels
        )
    return EchoTiming(
        estimator, spec.half_window, profile.preprocess.blind_zone_samples, correction
    )


def timing_delays(profile) -> np.ndarray:
    """Per-channel delays (samples) for the ToA the profile's step produces."""
    delays = np.asarray(profile.geometry.delays(), dtype=np.float64)
    spec = profile.echo_timing
    if spec.estimator != "none" and spec.delay_shift_samples:
        delays = delays + np.asarray(spec.delay_shift_samples, dtype=np.float64)
    return delays
