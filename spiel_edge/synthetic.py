"""Synthetic acquisitions from a point-target echo model, for any device profile.

Each target adds to every listening channel an exponentially modified Gaussian envelope at
its echo time (path / mm_per_sample + the channel's delay), with an amplitude falling off
with path length; Gaussian noise is added. Used by `bench` for large arrays and by tests.
"""

from __future__ import annotations

import numpy as np

from spiel_edge.pipeline.memg import SQRT2
from spiel_edge.profile import (
    AcquisitionSpec,
    AssociateSpec,
    DetectSpec,
    Geometry,
    PreprocessSpec,
    Profile,
)


def ring_profile(n_channels: int, n_samples: int, *, radius_mm: float = 75.0, sample_rate_hz: float = 22000.0) -> Profile:
    """A profile with the emitter-receiver at the origin and n - 1 receivers on a ring."""
    angles = np.linspace(0.0, 2.0 * np.pi, n_channels - 1, endpoint=False)
    ring = np.c_[radius_mm * np.cos(angles), radius_mm * np.sin(angles), np.zeros(n_channels - 1)]
    channels = np.vstack([np.zeros(3), ring])
    return Profile(
        name=f"ring-{n_channels}x{n_samples}",
        geometry=Geometry(channels_mm=channels, delay_samples=np.zeros(n_channels)),
        acquisition=AcquisitionSpec(sample_rate_hz=sample_rate_hz, n_samples=n_samples),
        preprocess=PreprocessSpec(background_subtraction=False, blind_zone_samples=4),
        detect=DetectSpec(threshold=30.0, min_amplitude=60.0, max_echoes=6),
        associate=AssociateSpec(min_channels=3),
    )


def echo_times(profile: Profile, target_mm: np.ndarray) -> np.ndarray:
    """Per-channel echo time (samples) of a point target."""
    g = profile.geometry
    p = np.asarray(target_mm, dtype=np.float64)
    path = np.linalg.norm(p - g.emitter_mm) + np.linalg.norm(p - g.channels_mm, axis=1)
    return path / profile.mm_per_sample + g.delays()


def synthesize(
    profile: Profile,
    targets_mm: np.ndarray,
    *,
    amplitude: float = 2.0e5,
    sigma: float = 1.6,
    eta: float = 1.5,
    noise: float = 5.0,
    rng: np.random.Generator | None = None,
) -> np.ndarray:
    """One acquisition (channels, samples) of envelopes with echoes of every target."""
    from math import erf

    rng = rng or np.random.default_rng(0)
    n_t = profile.acquisition.n_samples
    t = np.arange(n_t, dtype=np.float64)
    frames = np.abs(rng.normal(0.0, noise, size=(profile.geometry.n_channels, n_t)))
    verf = np.vectorize(erf)
    for target in np.atleast_2d(targets_mm):
        toa = echo_times(profile, target)
        path = toa * profile.mm_per_sample
        for c, mode in enumerate(toa):
            mu = mode - 0.6 * sigma  # the mode of a right-skewed EMG lies after mu
            u = (t - mu) / sigma
            shape = np.exp(-0.5 * u * u) * (1.0 + verf(eta * u / SQRT2))
            frames[c] += amplitude / max(path[c], 1.0) * shape
    return frames
