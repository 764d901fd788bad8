"""A running estimate of the static scene, for streams without a background capture.

Per sample, the median of the last ``window`` acquisitions (``[track]
running_background_window``; 0 turns it off, the default): the emitter's ring-down, the
crosstalk and every static reflector of the scene, learnt from the stream itself. Where a
confirmed track's echo lies (per channel, the samples within ``running_background_guard_samples``
plus two standard deviations of the track's echo path of its predicted time of arrival) the
acquisition is not taken in: the estimate keeps its previous value there, so a target that
stands still is not learnt as background once it has a track. Until ``window`` acquisitions
are in, the stand-in of the profile (``[scene] static_model``, pipeline/stages/static_scene.py) or
nothing is used, and the samples of those acquisitions at a track are that stand-in too.

A captured background always wins: callers use :meth:`RunningBackground.background` only when
there is none. Usage (runtime/track_records.py, tools/bench/track_scene.py)::

    running = RunningBackground.from_profile(profile)      # None when off
    result = pipeline.process(frames, running.background())
    tracks = tracker.update(result, t_s)
    running.update(frames, tracks)
"""

from __future__ import annotations

import warnings

import numpy as np

from spiel_edge.pipeline.stages.static_scene import load_static_model
from spiel_edge.profile.schema import Profile


class RunningBackground:
    """Per-sample median over recent acquisitions, gated by the confirmed tracks."""

    def __init__(self, profile: Profile, window: int, guard_samples: float, stand_in=None):
        if window < 1:
            raise ValueError(f"window must be >= 1, got {window}")
        g = profile.geometry
        self._shape = (g.n_channels, profile.acquisition.n_samples)
        self._emitter, self._channels = np.asarray(g.emitter_mm), np.asarray(g.channels_mm)
        self._delays = np.asarray(g.delays(), dtype=np.float64)
        self._mm_per_sample = profile.mm_per_sample
        self._guard = float(guard_samples)
        self._stand_in = stand_in
        self._buffer = np.zeros((window, *self._shape))
        self._count = 0  # acquisitions taken in (the ring buffer is full from ``window`` on)
        self._estimate: np.ndarray | None = None
        self._samples = np.arange(self._shape[1], dtype=np.float64)

    @classmethod
    def from_profile(cls, profile: Profile) -> RunningBackground | None:
        spec = profile.track
        if spec.running_background_window <= 0:
            return None
        stand_in = load_static_model(profile)
        return cls(
            profile, spec.running_background_window, spec.running_background_guard_samples, stand_in
        )

    def background(self) -> np.ndarray | None:
        """The estimate once ``window`` acquisitions are in, else the stand-in (or None)."""
        return self._estimate if self._estimate is not None else self._stand_in

    def reset(self) -> None:
        self._count, self._estimate = 0, None

    def update(self, frames: np.ndarray, tracks) -> None:
        """Take in one acquisition (channels, samples), except where a confirmed track's echo
        lies; a frame of another shape or with non-finite samples is skipped."""
        frame = np.array(frames, dtype=np.float64)
        if frame.shape != self._shape or not np.all(np.isfinite(frame)):
            return
        keep = self.background()
        mask = self.track_mask(tracks)
        if mask.any():
            frame[mask] = keep[mask] if keep is not None else np.nan
        window = len(self._buffer)
        self._buffer[self._count % window] = frame
        self._count += 1
        if self._count >= window:
            self._estimate = _median(self._buffer)

    def track_mask(self, tracks) -> np.ndarray:
        """(channels, samples): True where a confirmed track's echo is expected."""
        mask = np.zeros(self._shape, dtype=bool)
        for track in tracks:
            p = np.asarray(track.position_mm, dtype=np.float64)
            paths = np.linalg.norm(p - self._emitter) + np.linalg.norm(p - self._channels, axis=1)
            toa = paths / self._mm_per_sample + self._delays
            # the echo path moves by at most 2 mm per mm of position
            sigma = np.sqrt(max(float(np.trace(track.covariance_mm2)), 0.0) / 3.0)
            half = self._guard + 2.0 * 2.0 * sigma / self._mm_per_sample
            mask |= np.abs(self._samples[None, :] - toa[:, None]) <= half
        return mask


def _median(buffer: np.ndarray) -> np.ndarray:
    """Per-sample median over the first axis; NaN (a track's samples before there was an
    estimate) left out, 0 where every value is NaN."""
    if not np.isnan(buffer).any():
        return np.median(buffer, axis=0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN samples: handled below
        estimate = np.nanmedian(buffer, axis=0)
    return np.where(np.isfinite(estimate), estimate, 0.0)
