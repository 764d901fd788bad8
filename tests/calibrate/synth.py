"""Synthetic calibration scenes: a known perturbed geometry, echo times and envelopes."""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy.special import erf

from spiel_edge.calibrate import predict_toa
from spiel_edge.profile.schema import Geometry, Profile, load_profile


def nominal() -> Profile:
    return load_profile("spiel-icra23")


def perturbed_truth(g: Geometry, rng: np.random.Generator) -> Geometry:
    """The 'real' board: receivers up to ~3 mm off, delays 1.5-2.5 samples, speed +-1%."""
    moved = g.channels_mm.copy()
    moved[1:] += rng.uniform(-3.0, 3.0, (g.n_channels - 1, 3))
    return dataclasses.replace(
        g,
        channels_mm=moved,
        delay_samples=rng.uniform(1.5, 2.5, g.n_channels),
        speed_of_sound_m_s=g.speed_of_sound_m_s * rng.uniform(0.99, 1.01),
    )


def target_grid(rng: np.random.Generator, m: int) -> np.ndarray:
    """m target positions drawn from a wide grid in front of the array."""
    xy = np.linspace(-120.0, 120.0, 7)
    z = np.array([90.0, 130.0, 170.0, 220.0, 270.0])
    grid = np.array([[x, y, h] for x in xy for y in xy for h in z])
    return grid[rng.integers(0, len(grid), m)]


def echo_times(truth: Geometry, targets: np.ndarray, fs: float, rng, noise: float, outliers: float):
    """Flat (targets, channels, toa) with Gaussian noise and a share of wrong echoes."""
    n_ch = truth.n_channels
    flat_t = np.repeat(targets, n_ch, axis=0)
    ch = np.tile(np.arange(n_ch), len(targets))
    toa = predict_toa(truth, flat_t, ch, fs) + rng.normal(0.0, noise, len(ch))
    bad = rng.random(len(ch)) < outliers
    toa[bad] += rng.choice([-1.0, 1.0], bad.sum()) * rng.uniform(2.0, 8.0, bad.sum())
    return flat_t, ch, toa, bad


def _emg(t, mu, sigma, eta):
    u = (t - mu) / sigma
    return np.exp(-0.5 * u * u) * (1.0 + erf(eta * u / np.sqrt(2.0)))


def render(
    truth: Geometry,
    targets: np.ndarray,
    fs: float,
    n_samples: int,
    rng,
    *,
    sigma=1.3,
    eta=1.5,
    noise=1.5,
):
    """Envelopes (M, channels, samples) with the target's echo whose maximum is at its echo time,
    a clutter echo, ring-down and noise; and the matching target-free backgrounds."""
    t = np.arange(n_samples, dtype=np.float64)
    fine = np.linspace(-3, 3, 60001)
    mode_offset = fine[np.argmax(_emg(fine, 0.0, 1.0, eta))] * sigma
    n_ch = truth.n_channels
    ring = np.where(t < 9, 900.0 * np.exp(-t / 3.0), 0.0)
    bg = 40.0 + ring + np.zeros((len(targets), n_ch, n_samples))
    frames = bg + rng.normal(0.0, noise, bg.shape)
    bg = bg + rng.normal(0.0, noise, bg.shape)
    for i, p in enumerate(targets):
        toa = predict_toa(truth, np.repeat(p[None], n_ch, axis=0), np.arange(n_ch), fs)
        for n in range(n_ch):
            amp = 4.0e7 / (
                np.linalg.norm(p - truth.emitter_mm) * np.linalg.norm(p - truth.channels_mm[n])
            )
            frames[i, n] += amp * _emg(t, toa[n] - mode_offset, sigma, eta)
            frames[i, n] += (
                0.5 * amp * _emg(t, toa[n] + rng.uniform(8, 14) - mode_offset, sigma, eta)
            )
    return np.round(frames), np.round(bg)
