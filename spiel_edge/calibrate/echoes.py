"""Echo times for calibration: candidates from the pipeline, then the one per channel that
belongs to the known target.

The first four pipeline stages (preprocess, detect, MEMG, features) do not depend on the
geometry, so candidates are extracted once and re-picked as the geometry improves. When the
profile's echo-timing step is on, every candidate is re-timed by it (as the pipeline re-times the
matched echoes, without the learned correction: it knows only the recorded board's echo shapes,
and its mean over the training echoes is zero) and its delay shift taken off, so the fitted
``geometry.delay_samples`` are the ones the pipeline adds that shift to.
"""

from __future__ import annotations

import logging

import numpy as np

from spiel_edge.calibrate.solve import Observations
from spiel_edge.errors import InputError
from spiel_edge.pipeline.staged import Pipeline
from spiel_edge.pipeline.stages.echo_timing import EchoTiming, timing_delays
from spiel_edge.pipeline.stages.features import TOA_COLUMN
from spiel_edge.profile.schema import Profile

log = logging.getLogger(__name__)


def _no_association(features: np.ndarray, counts: np.ndarray) -> np.ndarray:
    return np.full(len(counts), -1, dtype=np.int64)  # stop after features: locate is not needed


def extract_echoes(
    profile: Profile, frames: np.ndarray, backgrounds: np.ndarray | None = None
) -> np.ndarray:
    """Candidate echo times (M, channels, max_echoes) in samples, NaN where there is none."""
    frames = np.asarray(frames, dtype=np.float64)
    if frames.ndim == 2:
        frames = frames[None]
    if backgrounds is not None:
        backgrounds = np.asarray(backgrounds, dtype=np.float64)
        if backgrounds.ndim == 2:
            backgrounds = np.broadcast_to(backgrounds, frames.shape)
        if backgrounds.shape != frames.shape:
            raise InputError(
                f"backgrounds shape {backgrounds.shape} differs from frames {frames.shape}"
            )
    pipeline = Pipeline(profile, _no_association)
    out = np.full((frames.shape[0], profile.geometry.n_channels, profile.detect.max_echoes), np.nan)
    for i, frame in enumerate(frames):
        background = None if backgrounds is None else backgrounds[i]
        result = pipeline.process(frame, background)
        out[i] = _timed(pipeline, profile, frame, background, result.features[:, :, TOA_COLUMN])
    return out


def _timed(pipeline: Pipeline, profile: Profile, frame, background, toa: np.ndarray) -> np.ndarray:
    """Candidates re-timed by the pipeline's echo-timing estimator, minus its delay shift."""
    step = pipeline.echo_timing
    if not step.active:
        return toa
    timing = EchoTiming(step.estimator, step.half_window, step.blind_zone)
    if not profile.preprocess.background_subtraction:
        background = None
    shift = timing_delays(profile) - np.asarray(profile.geometry.delays(), dtype=np.float64)
    cols = [timing(frame, background, toa[:, k]) for k in range(toa.shape[1])]
    return np.stack(cols, axis=1) - shift[:, None]


def channel_offsets(
    candidates: np.ndarray, predicted: np.ndarray, window: float = 8.0, width: float = 1.0
) -> np.ndarray:
    """Per channel the most common (echo - predicted) time within +-window samples.

    A start for the delays when they are unknown: the target's echo sits at a constant offset
    from the prediction while clutter echoes scatter, so the densest ``width`` bin finds it.
    """
    diff = candidates - predicted[:, :, None]
    out = np.zeros(candidates.shape[1])
    for n in range(candidates.shape[1]):
        d = np.sort(diff[:, n][np.abs(diff[:, n]) <= window])
        if d.size == 0:
            continue
        ends = np.searchsorted(d, d + width, side="right")
        best = int(np.argmax(ends - np.arange(d.size)))
        out[n] = float(np.median(d[best : ends[best]]))
    return out


def pick_echoes(candidates: np.ndarray, predicted: np.ndarray, gate: float) -> np.ndarray:
    """Per acquisition and channel the candidate nearest the prediction, NaN beyond ``gate``."""
    dist = np.abs(candidates - predicted[:, :, None])
    dist = np.where(np.isnan(dist), np.inf, dist)
    k = np.argmin(dist, axis=2)
    picked = np.take_along_axis(candidates, k[:, :, None], axis=2)[:, :, 0]
    near = np.take_along_axis(dist, k[:, :, None], axis=2)[:, :, 0] <= gate
    return np.where(near, picked, np.nan)


def to_observations(
    picked: np.ndarray, targets_mm: np.ndarray, listening: np.ndarray
) -> tuple[Observations, np.ndarray]:
    """Flatten picked times (M, channels) into Observations; also the acquisition index of each."""
    ok = np.isfinite(picked) & listening[None, :]
    acq, ch = np.nonzero(ok)
    return Observations(targets_mm[acq], ch.astype(np.int64), picked[acq, ch]), acq
