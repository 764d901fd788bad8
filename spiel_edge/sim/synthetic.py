"""Synthetic acquisitions for any array size: a ring-array profile plus the virtual board's
physical echo model (:class:`spiel_edge.sim.scenes.EchoModelScene`). Used by `bench`."""

from __future__ import annotations

import numpy as np

from spiel_edge.profile.schema import AcquisitionSpec, DetectSpec, Geometry, PreprocessSpec, Profile


def ring_profile(
    n_channels: int, n_samples: int, *, radius_mm: float = 75.0, sample_rate_hz: float = 22000.0
) -> Profile:
    """A profile with the emitter-receiver at the origin and n - 1 receivers on a ring."""
    angles = np.linspace(0.0, 2.0 * np.pi, n_channels - 1, endpoint=False)
    ring = np.c_[radius_mm * np.cos(angles), radius_mm * np.sin(angles), np.zeros(n_channels - 1)]
    channels = np.vstack([np.zeros(3), ring])
    return Profile(
        name=f"ring-{n_channels}x{n_samples}",
        geometry=Geometry(channels_mm=channels, delay_samples=np.zeros(n_channels)),
        acquisition=AcquisitionSpec(sample_rate_hz=sample_rate_hz, n_samples=n_samples),
        preprocess=PreprocessSpec(background_subtraction=True, blind_zone_samples=4),
        detect=DetectSpec(threshold=30.0, min_amplitude=60.0, max_echoes=6),
    )


def synthesize(
    profile: Profile, targets_mm: np.ndarray, *, noise: float = 5.0, seed: int = 0
) -> tuple[np.ndarray, np.ndarray]:
    """One acquisition ``(frames, background)`` (channels, samples) with echoes of every target."""
    from spiel_edge.sim.scenes import EchoModelScene

    n_samples = profile.acquisition.n_samples
    scene = EchoModelScene(
        profile.geometry,
        sample_rate_hz=profile.acquisition.sample_rate_hz,
        n_samples=n_samples,
        targets_mm=np.atleast_2d(targets_mm),
        noise=noise,
        seed=seed,
    )
    frame = scene.frame(0, n_samples, 0.0)
    return frame.samples.astype(np.float64), frame.background.astype(np.float64)
