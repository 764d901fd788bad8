"""Data for the learned ToA correction (``tools.train.train_toa_correction``): per acquisition, the
runtime's matched echoes, their refined ToA and features, with and without the background.

Workstation tool. Each labelled acquisition of ``<data>/train_val`` (z = 90 mm excluded,
``spiel_edge.data.EXCLUDED_Z_MM``) goes through the runtime stages up to association (the
shipped associator), once with its background capture and once without; the matched echoes'
ToA is refined by ``spiel_edge.pipeline.stages.echo_timing`` (the runtime's own functions, so training
and runtime features are identical). Target per echo: refined ToA - delay - ideal ToA (the
true position's echo path / mm per sample), in samples.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from spiel_edge.data import EXCLUDED_Z_MM
from spiel_edge.measure.evaluate import split_by_position
from spiel_edge.pipeline.factory import build_associator
from spiel_edge.pipeline.staged import Pipeline
from spiel_edge.pipeline.stages.echo_timing import (
    EchoTiming,
    clean_envelope,
    refine_toa,
    toa_features,
)
from spiel_edge.pipeline.stages.features import TOA_COLUMN
from spiel_edge.profile.schema import Profile
from spiel_edge.recordings.spiel_csv import iter_recordings, position_key, read_truth

INLIER_SAMPLES = 1.5  # a matched echo further than this from the truth is a wrong association


@dataclass
class Case:
    """One acquisition processed with (``has_background``) or without its background."""

    name: str
    xy: tuple[float, float]
    truth_mm: np.ndarray
    has_background: bool
    frames: np.ndarray
    background: np.ndarray | None
    feats: np.ndarray  # the pipeline's echo features (for echo quality)
    counts: np.ndarray
    matched: np.ndarray  # (channels,) echo index or -1
    memg_toa: np.ndarray  # (channels,) matched ToA, NaN where none
    clean: np.ndarray  # power-domain background-free envelope
    refined: np.ndarray  # (channels,) after the estimator
    features: np.ndarray  # (channels, n_toa_features), NaN rows where none
    ideal: np.ndarray  # (channels,) true echo path / mm per sample


def load_cases(data: Path, profile: Profile, estimator: str, half_window: int) -> list[Case]:
    pipe = Pipeline(profile, build_associator(profile), echo_timing=EchoTiming("none"))
    blind = profile.preprocess.blind_zone_samples
    cases = []
    for rec in iter_recordings(data / "train_val", data / "train_val_bg"):
        key = position_key(rec.source)
        if rec.error is not None or key is None or key[2] in EXCLUDED_Z_MM:
            continue
        truth = read_truth(data / "train_val" / rec.source)
        ideal = profile.geometry.echo_paths_mm(truth) / profile.mm_per_sample
        for bg in (rec.background, None):
            r = pipe.process(rec.frames, bg)
            matched = np.array([-1 if m is None else m for m in r.matched])
            rows = np.arange(len(matched)), np.maximum(matched, 0)
            toa = np.where(matched >= 0, r.features[:, :, TOA_COLUMN][rows], np.nan)
            clean = clean_envelope(rec.frames, bg, blind)
            refined = refine_toa(clean, toa, half_window, estimator)
            feats = toa_features(rec.frames, bg, clean, refined)
            cases.append(
                Case(
                    rec.source,
                    key[:2],
                    truth,
                    bg is not None,
                    rec.frames,
                    bg,
                    r.features,
                    r.counts,
                    matched,
                    toa,
                    clean,
                    refined,
                    feats,
                    ideal,
                )
            )
    return cases


def split(cases: list[Case], val_fraction: float = 0.3, salt: str = "spiel-edge"):
    _, val_xy = split_by_position([c.name for c in cases], val_fraction, salt)
    return [c for c in cases if c.xy not in val_xy], [c for c in cases if c.xy in val_xy]


def residuals(cases: list[Case], toa_of, delays: np.ndarray) -> np.ndarray:
    """(n, channels) ToA - delay - ideal for ``toa_of(case)``, NaN where unmatched."""
    return np.array([toa_of(c) - delays - c.ideal for c in cases])


def fit_delay_shift(cases: list[Case], base_delays: np.ndarray) -> np.ndarray:
    """Per channel, the median residual of the refined ToA over inlier echoes (with background)."""
    res = residuals([c for c in cases if c.has_background], lambda c: c.refined, base_delays)
    res = np.where(np.abs(res) < INLIER_SAMPLES, res, np.nan)
    return np.nanmedian(res, axis=0)


def training_rows(cases: list[Case], delays: np.ndarray):
    """(X float32, y, group) over inlier echoes with finite features; group = (x, y) index."""
    xys = sorted({c.xy for c in cases})
    X, y, g = [], [], []
    for c in cases:
        res = c.refined - delays - c.ideal
        ok = np.isfinite(res) & (np.abs(res) < INLIER_SAMPLES) & np.all(np.isfinite(c.features), 1)
        X.append(c.features[ok])
        y.append(res[ok])
        g.append(np.full(int(ok.sum()), xys.index(c.xy)))
    return np.vstack(X).astype(np.float32), np.concatenate(y), np.concatenate(g)


class _GivenToa:
    """Stands in for the echo-timing step: returns the ToAs under test."""

    def __init__(self, active: bool):
        self.active = active
        self.toa = np.zeros(0)

    def __call__(self, frames, background, toa):
        return self.toa


def locate_errors(profile: Profile, cases: list[Case], toa_of, echo_timing_on: bool) -> np.ndarray:
    """3-D error (mm, NaN: no fix) per case with the runtime's locate step on ``toa_of(case)``
    (delays and echo-quality shift as the runtime applies them with the step on or off)."""
    given = _GivenToa(echo_timing_on)
    pipe = Pipeline(profile, echo_timing=given)
    out = np.full(len(cases), np.nan)
    for i, c in enumerate(cases):
        given.toa = toa_of(c)
        located = pipe.locate_target(c.feats, c.matched, 0.0, c.frames, c.background)
        if located is not None:
            out[i] = float(np.linalg.norm(located[0].position_mm - c.truth_mm))
    return out


def re_refine(cases: list[Case], estimator: str, half_window: int) -> None:
    """Recompute each case's refined ToA and features with another estimator (in place)."""
    for c in cases:
        c.refined = refine_toa(c.clean, c.memg_toa, half_window, estimator)
        c.features = toa_features(c.frames, c.background, c.clean, c.refined)


def inlier_rms(cases: list[Case], toa_of, delays: np.ndarray) -> float:
    """RMS (samples) of ToA - delay - ideal over echoes within INLIER_SAMPLES of the truth."""
    res = residuals(cases, toa_of, delays)
    res = res[np.isfinite(res) & (np.abs(res) < INLIER_SAMPLES)]
    return float(np.sqrt(np.mean(res**2)))
