"""Calibration end to end: candidate echoes + known target positions -> geometry.

Rounds of pick-then-solve: the echo of the known target is the candidate nearest the time
the current geometry predicts; the solve improves the geometry, which sharpens the next pick.
Unknown delays are first seeded by the per-channel mode of (echo - predicted) so that the
gate can be narrow from the start.
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass

import numpy as np

from spiel_edge.calibrate.echoes import (
    channel_offsets,
    extract_echoes,
    pick_echoes,
    to_observations,
)
from spiel_edge.calibrate.solve import (
    DEFAULT_FIX,
    CalibrationResult,
    Observations,
    predict_toa,
    solve,
)
from spiel_edge.errors import InputError
from spiel_edge.profile.schema import Geometry, Profile

log = logging.getLogger(__name__)

FIRST_GATE = 1.5  # samples around the seeded prediction: 5 mm of receiver error is 0.3
MIN_GATE = 0.6
MAX_ROUNDS = 6


@dataclass(frozen=True)
class Calibration:
    """A solved calibration with what it was solved from."""

    start: Geometry
    result: CalibrationResult
    observations: Observations
    acquisition: np.ndarray  # (N,) acquisition index of each observation
    n_acquisitions: int
    expected: int  # acquisitions x listening channels: echoes that could have been picked
    sample_rate_hz: float
    rounds: int

    @property
    def geometry(self) -> Geometry:
        return self.result.geometry

    def per_channel(self) -> list[dict]:
        return self.result.per_channel(self.observations.channels, self.start.n_channels)


def calibrate_echoes(
    candidates: np.ndarray,
    targets_mm: np.ndarray,
    profile: Profile,
    *,
    fix: frozenset[str] | set[str] = DEFAULT_FIX,
    reject_sigma: float = 4.0,
) -> Calibration:
    """Solve the geometry from candidate echo times (M, channels, K) of targets (M, 3)."""
    targets_mm = np.asarray(targets_mm, dtype=np.float64)
    m, n_ch = candidates.shape[:2]
    if targets_mm.shape != (m, 3) or n_ch != profile.geometry.n_channels:
        raise InputError(
            f"need one target position per acquisition ({m}, 3) and {profile.geometry.n_channels} channels"
        )
    fs = profile.acquisition.sample_rate_hz
    start = profile.geometry
    listening = start.listening_mask()
    all_ch = np.tile(np.arange(n_ch), m)
    flat_targets = np.repeat(targets_mm, n_ch, axis=0)

    def predicted(g: Geometry) -> np.ndarray:
        return predict_toa(g, flat_targets, all_ch, fs).reshape(m, n_ch)

    geometry = start
    if "delays" not in fix:
        geometry = dataclasses.replace(
            start, delay_samples=start.delays() + channel_offsets(candidates, predicted(start))
        )
    gate, previous, result = FIRST_GATE, None, None
    for rounds in range(1, MAX_ROUNDS + 1):
        picked = pick_echoes(candidates, predicted(geometry), gate)
        obs, acq = to_observations(picked, targets_mm, listening)
        if (
            previous is not None
            and np.array_equal(np.isnan(picked), np.isnan(previous))
            and np.allclose(picked, previous, equal_nan=True)
        ):
            break
        result = solve(obs, geometry, fs, fix=fix, reject_sigma=reject_sigma)
        geometry, previous = result.geometry, picked
        gate = max(MIN_GATE, min(FIRST_GATE, (reject_sigma + 1.0) * result.scale))
        log.info(
            "round %d: %d echoes, scale %.3f samples, next gate %.2f",
            rounds,
            len(obs),
            result.scale,
            gate,
        )
    assert result is not None
    return Calibration(start, result, obs, acq, m, m * int(listening.sum()), fs, rounds)


def calibrate_frames(
    profile: Profile,
    frames: np.ndarray,
    backgrounds: np.ndarray | None,
    targets_mm: np.ndarray,
    **kwargs,
) -> Calibration:
    """Extract echoes from acquisitions (M, channels, samples), then :func:`calibrate_echoes`."""
    return calibrate_echoes(
        extract_echoes(profile, frames, backgrounds), targets_mm, profile, **kwargs
    )
