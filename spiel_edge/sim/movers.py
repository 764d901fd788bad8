"""Targets on smooth random paths for the virtual board (``sim://?scene=model&movers=N``).

Each coordinate of each target is a sum of three sinusoids with random amplitudes, periods
and phases (seeded): smooth, bounded inside a box in front of the array, and with a speed that
never exceeds the target's top speed (drawn between ``MIN_TOP_SPEED_MM_S`` and
``MAX_TOP_SPEED_MM_S``; the bound is exact: the sum over sinusoids of amplitude x angular
rate, per axis). Paths share one box, so targets cross each other's ranges now and then.
"""

from __future__ import annotations

import numpy as np

CENTER_MM = np.array([0.0, 0.0, 200.0])
HALF_RANGE_MM = np.array([90.0, 90.0, 70.0])  # box: x, y in [-90, 90], z in [130, 270]
MIN_TOP_SPEED_MM_S = 250.0
MAX_TOP_SPEED_MM_S = 500.0
TERMS = 3


class MoverPaths:
    """``positions(time_s) -> (n, 3)`` mm for ``n`` targets."""

    def __init__(self, n: int, *, seed: int = 0):
        rng = np.random.default_rng([seed, 0x50A7])
        self.n = n
        weights = rng.dirichlet(np.ones(TERMS), size=(n, 3))  # (n, 3 axes, terms), sum 1
        self.amplitude = weights * HALF_RANGE_MM[None, :, None]
        rate = rng.uniform(0.3, 1.0, (n, 3, TERMS))  # relative angular rates
        bound = np.linalg.norm((self.amplitude * rate).sum(axis=2), axis=1)  # (n,) mm/s per unit
        top = rng.uniform(MIN_TOP_SPEED_MM_S, MAX_TOP_SPEED_MM_S, n)
        self.rate = rate * (top / bound)[:, None, None]  # rad/s, so that the bound is ``top``
        self.phase = rng.uniform(0.0, 2 * np.pi, (n, 3, TERMS))
        self.top_speed_mm_s = top

    def positions(self, time_s: float) -> np.ndarray:
        wave = self.amplitude * np.sin(self.rate * time_s + self.phase)
        return CENTER_MM + wave.sum(axis=2)
