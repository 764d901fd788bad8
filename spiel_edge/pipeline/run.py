"""The whole per-acquisition pipeline: frames in, one Result (position or reason) out."""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from spiel_edge.errors import InputError
from spiel_edge.pipeline.associate import GeometricAssociator
from spiel_edge.pipeline.detect import detect
from spiel_edge.pipeline.echo_quality import echo_quality
from spiel_edge.pipeline.features import TOA_COLUMN, echo_features
from spiel_edge.pipeline.locate import locate
from spiel_edge.pipeline.memg import fit_memg
from spiel_edge.pipeline.preprocess import preprocess
from spiel_edge.profile.schema import Profile

log = logging.getLogger(__name__)

Associator = Callable[[np.ndarray, np.ndarray], np.ndarray]
STAGES = ("preprocess", "detect", "memg", "features", "associate", "locate")

# Why a record has no position (the ``reason`` field).
REASON_TOO_FEW_CHANNELS = "fewer than 3 channels with echoes"
REASON_NO_CONSISTENT_ECHOES = "no echo combination consistent with one target"
REASON_SOLVE_FAILED = "ellipsoid intersection did not converge in front of the array"
REASON_FLAT_FRAME = "frame is flat (all samples equal): no signal"
REASON_SATURATED = "frame is saturated"


@dataclass
class Target:
    """One target found in an acquisition (the record's ``targets`` entries, best first)."""

    position_mm: np.ndarray  # (3,)
    covariance_mm2: np.ndarray  # (3, 3), symmetric positive semi-definite
    residual_mm: float
    matched: list[int | None]  # per channel: index into the record's echoes, or None
    score: float  # higher is better; comparable within one acquisition
    track_id: int | None = None  # set by the tracker

    def record(self) -> dict:
        out = {
            "position_mm": [round(float(v), 2) for v in self.position_mm],
            "covariance_mm2": [[round(float(v), 3) for v in row] for row in self.covariance_mm2],
            "residual_mm": round(float(self.residual_mm), 3),
            "matched": self.matched,
            "score": round(float(self.score), 4),
        }
        if self.track_id is not None:
            out["track_id"] = int(self.track_id)
        return out


@dataclass
class Result:
    """What the pipeline makes of one acquisition."""

    position_mm: np.ndarray | None
    reason: str | None
    residual_mm: float | None
    echoes: list[list[float]]  # per channel: echo ToAs in samples, ascending
    matched: list[int | None]  # per channel: index into echoes, or None
    features: np.ndarray = field(repr=False)  # (channels, max_echoes, 8)
    counts: np.ndarray = field(repr=False)
    timings_us: dict[str, float] = field(default_factory=dict, repr=False)
    targets: list[Target] = field(default_factory=list)  # best first; filled by the scene stage

    def record(self) -> dict:
        """JSON-ready fields shared by replay and run records."""
        return {
            "position_mm": None
            if self.position_mm is None
            else [round(float(v), 2) for v in self.position_mm],
            "reason": self.reason,
            "residual_mm": None if self.residual_mm is None else round(float(self.residual_mm), 3),
            "echoes": [[round(t, 3) for t in ch] for ch in self.echoes],
            "matched": self.matched,
            "targets": [t.record() for t in self.targets],
        }


class Pipeline:
    """preprocess -> detect -> memg -> features -> associate -> locate for one profile."""

    def __init__(
        self, profile: Profile, associator: Associator | None = None, *, saturation: float = 65535.0
    ):
        self.profile = profile
        self.associator = associator or GeometricAssociator(profile)
        self.saturation = saturation  # full scale of the board's samples (u16 envelopes)
        g = profile.geometry
        self._channels = np.ascontiguousarray(g.channels_mm, dtype=np.float64)
        self._emitter = np.ascontiguousarray(g.emitter_mm, dtype=np.float64)
        self._facing = np.ascontiguousarray(g.facing, dtype=np.float64)
        self._delays = g.delays()

    def check_shape(self, frames: np.ndarray, what: str = "frames") -> None:
        n_ch, n_t = self.profile.geometry.n_channels, self.profile.acquisition.n_samples
        if np.shape(frames) != (n_ch, n_t):
            raise InputError(
                f"{what} has shape {np.shape(frames)}, profile {self.profile.name!r} expects ({n_ch}, {n_t})"
            )

    def process(
        self, frames: np.ndarray, background: np.ndarray | None = None, *, timed: bool = False
    ) -> Result:
        """Run every stage on one acquisition (channels, samples)."""
        p = self.profile
        self.check_shape(frames)
        if background is not None:
            self.check_shape(background, "background")
        clock = time.perf_counter_ns if timed else _no_clock
        t0 = clock()
        acq = p.acquisition
        if not p.preprocess.background_subtraction:
            background = None
        y = preprocess(
            frames,
            background,
            blind_zone=p.preprocess.blind_zone_samples,
            rf=acq.signal == "rf",
            carrier_cycles_per_sample=acq.carrier_hz / acq.sample_rate_hz,
        )
        t1 = clock()
        d = p.detect
        peaks, counts = detect(
            y,
            threshold=d.threshold,
            hysteresis=d.hysteresis,
            min_amplitude=d.min_amplitude,
            max_echoes=d.max_echoes,
            first_sample=p.preprocess.blind_zone_samples,
        )
        t2 = clock()
        params = fit_memg(
            y, peaks, counts, mu_window=p.memg.mu_window, max_iterations=p.memg.max_iterations
        )
        t3 = clock()
        feats = echo_features(y, params, peaks, p.memg.toa)
        t4 = clock()
        matched = self.associator(feats, counts)
        t5 = clock()
        result = self._locate(feats, counts, matched, np.asarray(frames), background)
        t6 = clock()
        if timed:
            stamps = (t0, t1, t2, t3, t4, t5, t6)
            result.timings_us = {s: (stamps[i + 1] - stamps[i]) / 1e3 for i, s in enumerate(STAGES)}
            result.timings_us["end_to_end"] = (t6 - t0) / 1e3
        return result

    def _locate(
        self,
        feats: np.ndarray,
        counts: np.ndarray,
        matched: np.ndarray,
        raw: np.ndarray,
        background: np.ndarray | None,
    ) -> Result:
        toa = feats[:, :, TOA_COLUMN]
        echoes = [[float(v) for v in toa[c, : counts[c]]] for c in range(len(counts))]
        match_list = [int(m) if m >= 0 else None for m in matched]
        base = {"echoes": echoes, "matched": match_list, "features": feats, "counts": counts}
        use = matched >= 0
        if use.sum() < 3:
            return Result(None, self._why_empty(raw, counts), None, **base)
        rows = np.arange(len(matched)), np.maximum(matched, 0)
        picked = np.where(use, toa[rows], np.nan)
        weights, shift = echo_quality(
            raw, background, picked, feats[rows][:, 0], self.profile.locate
        )
        paths = (picked + shift - self._delays) * self.profile.mm_per_sample
        pos, rms, ok = locate(
            paths, self._channels, self._emitter, self._facing, use, weights=weights
        )
        if not ok:
            return Result(None, REASON_SOLVE_FAILED, None, **base)
        return Result(pos, None, rms, **base)

    def _why_empty(self, raw: np.ndarray, counts: np.ndarray) -> str:
        if raw.size and np.mean(raw >= self.saturation) > 0.5:
            return REASON_SATURATED
        if raw.size and np.ptp(raw) == 0:
            return REASON_FLAT_FRAME
        if int((counts > 0).sum()) < 3:
            return REASON_TOO_FEW_CHANNELS
        return REASON_NO_CONSISTENT_ECHOES


def _no_clock() -> int:
    return 0
