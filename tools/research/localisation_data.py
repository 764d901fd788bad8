"""Data for the localisation study (``tools.research.localisation_study``, docs/localisation.md).

Every labelled acquisition of ``<data>/train_val`` (z = 90 mm excluded) goes through the shipped
pipeline twice: with its background capture, and without (the static-scene stand-in, as the
runtime does). Kept per acquisition and channel: the matched echo's MEMG ToA, the estimator's
ToA (no learned correction), the shipped pipeline's ToA (with it), the echo-quality weight,
the ideal ToA of the labelled position, the pipeline's position, and the learned correction's
features (to retrain it out of fold). Cached as one npz (about a minute to build).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from spiel_edge.data import EXCLUDED_Z_MM
from spiel_edge.measure.evaluate import split_by_position
from spiel_edge.pipeline.factory import build_associator
from spiel_edge.pipeline.staged import Pipeline
from spiel_edge.pipeline.stages.echo_quality import echo_quality
from spiel_edge.pipeline.stages.echo_timing import clean_envelope, refine_toa, toa_features
from spiel_edge.pipeline.stages.features import TOA_COLUMN
from spiel_edge.pipeline.stages.locate import locate
from spiel_edge.profile.schema import Profile
from spiel_edge.recordings.spiel_csv import iter_recordings, position_key, read_truth

FIELDS = [
    "bg",
    "truth",
    "xy",
    "ideal",
    "memg",
    "refined",
    "corrected",
    "feats",
    "weights",
    "alpha",
    "pos",
]


def collect(data: Path, profile: Profile) -> dict[str, np.ndarray]:
    pipe = Pipeline(profile, build_associator(profile))
    timing = pipe.echo_timing
    rows: dict[str, list] = {k: [] for k in FIELDS}
    names = []
    for rec in iter_recordings(data / "train_val", data / "train_val_bg"):
        key = position_key(rec.source)
        if rec.error is not None or key is None or key[2] in EXCLUDED_Z_MM:
            continue
        truth = read_truth(data / "train_val" / rec.source)
        ideal = profile.geometry.echo_paths_mm(truth) / profile.mm_per_sample
        for has_bg in (True, False):
            result = pipe.process(rec.frames, rec.background if has_bg else None)
            bg = rec.background if has_bg else pipe.static_model  # what the runtime times with
            m = np.array([-1 if v is None else v for v in result.matched])
            at = np.arange(len(m)), np.maximum(m, 0)
            toa = np.where(m >= 0, result.features[:, :, TOA_COLUMN][at], np.nan)
            clean = clean_envelope(rec.frames, bg, profile.preprocess.blind_zone_samples)
            refined = refine_toa(clean, toa, timing.half_window, timing.estimator)
            corrected = timing(rec.frames, bg, toa)
            alpha = result.features[at][:, 0]
            weights, _ = echo_quality(rec.frames, bg, corrected, alpha, profile.locate)
            pos = result.position_mm if result.position_mm is not None else np.full(3, np.nan)
            values = (has_bg, truth, key[:2], ideal, toa, refined, corrected)
            values += (toa_features(rec.frames, bg, clean, refined), weights, alpha, pos)
            for k, v in zip(FIELDS, values, strict=True):
                rows[k].append(v)
            names.append(rec.source)
    out = {k: np.array(v) for k, v in rows.items()}
    _, val = split_by_position(names)
    out["is_val"] = np.array([tuple(xy) in val for xy in out["xy"]])
    out["delays"] = pipe.delays
    return out


def load_or_collect(data: Path, profile: Profile, cache: Path) -> dict[str, np.ndarray]:
    if cache.exists():
        return dict(np.load(cache))
    cases = collect(data, profile)
    np.savez(cache, **cases)
    return cases


def solve_all(
    profile: Profile,
    toa_minus_delay: np.ndarray,
    weights: np.ndarray | None,
    use: np.ndarray | None = None,
    scale: float = 1.0,
) -> np.ndarray:
    """Positions (NaN where the solve fails) from per-channel ToA minus delay (samples)."""
    g = profile.geometry
    ch, em, fa = (np.asarray(a, dtype=np.float64) for a in (g.channels_mm, g.emitter_mm, g.facing))
    out = np.full((len(toa_minus_delay), 3), np.nan)
    for i, t in enumerate(toa_minus_delay):
        paths = t * profile.mm_per_sample / scale
        mask = np.isfinite(paths) if use is None else use[i] & np.isfinite(paths)
        if mask.sum() < 3:
            continue
        p, _, ok = locate(paths, ch, em, fa, mask, weights=None if weights is None else weights[i])
        if ok:
            out[i] = p
    return out
