"""The compiled steps both back kernels share (back.py for one target, back_scene.py for
several) and the layout of their ``ints`` / ``floats`` argument arrays: the association
search's inputs (score prior, paths, strengths), the MLP prior, echo timing, and one target
from its matched echoes (as ``Pipeline._target``: echo timing, echo quality, locate,
covariance)."""

from __future__ import annotations

import math

import numpy as np

from spiel_edge._jit import jit
from spiel_edge.pipeline.learned.mlp import mlp_scores
from spiel_edge.pipeline.stages.echo_quality import _echo_quality_kernel
from spiel_edge.pipeline.stages.echo_timing import _clean_kernel, _fused_kernel, _refine_kernel
from spiel_edge.pipeline.stages.features import TOA_COLUMN
from spiel_edge.pipeline.stages.locate import locate_kernel
from spiel_edge.pipeline.stages.uncertainty import _covariance_kernel

PRIOR_NONE, PRIOR_MLP, PRIOR_GIVEN = 0, 1, 2
TIMING_NONE, TIMING_REFINE, TIMING_TREES = 0, 1, 2
# ints[] slots
I_MIN_CHANNELS, I_EXHAUSTIVE, I_PRIOR, I_TIMING, I_BLIND, I_HALF_WINDOW, I_LOG = range(7)
# floats[] slots
F_MM_PER_SAMPLE, F_STRENGTH, F_SCORE_WEIGHT, F_LIMIT, F_COV_FLOOR = range(5)


@jit
def _one_target(
    features,
    y,
    bg,
    matched,
    cov_scale,
    ints,
    floats,
    quality,
    delays,
    channels,
    emitter,
    facing,
    feature,
    threshold,
    value,
    base,
    clean,
    picked,
    weights,
    shift,
    mask,
    position,
    covariance,
    paths,
):
    """As ``Pipeline._target``, for the K = 1 back kernel after association and for each target
    of the several-target kernel (back_scene.py): (ok, rms);
    position, covariance and paths filled."""
    n_ch = features.shape[0]
    mm = floats[F_MM_PER_SAMPLE]
    n_use = 0
    for c in range(n_ch):
        use = matched[c] >= 0
        n_use += use
        picked[c] = features[c, max(matched[c], 0), TOA_COLUMN] if use else np.nan
    if n_use < 3:
        return False, math.inf
    timed = _echo_timing(y, bg, picked, ints, floats, feature, threshold, value, base, clean)
    alpha_matched = np.empty(n_ch)
    for c in range(n_ch):
        alpha_matched[c] = features[c, max(matched[c], 0), 0]
    _echo_quality_kernel(y, bg, timed, alpha_matched, quality, weights, shift)
    for c in range(n_ch):
        s = 0.0 if ints[I_TIMING] != TIMING_NONE else shift[c]
        paths[c] = (timed[c] + s - delays[c]) * mm
    for c in range(n_ch):
        mask[c] = matched[c] >= 0 and math.isfinite(paths[c])
    ok, rms = locate_kernel(paths, mask, weights, emitter, channels, facing, 30, position)
    if not ok:
        return False, rms
    sigma = np.empty(n_ch)
    for c in range(n_ch):
        sigma[c] = mm / weights[c]
    _covariance_kernel(
        position, paths, sigma, mask, channels, emitter, cov_scale, floats[F_COV_FLOOR], covariance
    )
    return True, rms


@jit
def _association_inputs(
    features, counts, listening, ints, floats, assoc_delays, mean, std, w0, b0, w1, b1, w2, b2,
    wh, bh, bonus, all_paths, allowed, strength,
):  # fmt: skip
    """The association search's inputs, as the staged associator builds them: the score
    prior into ``bonus`` (the MLP's, or zeros), each echo's path (mm) into ``all_paths``,
    whether it is finite into ``allowed``, and its strength (log amplitude plus prior)."""
    n_ch, k_max = features.shape[0], features.shape[1]
    mm = floats[F_MM_PER_SAMPLE]
    if ints[I_PRIOR] == PRIOR_MLP:
        _score_bonus(
            features,
            counts,
            listening,
            floats[F_SCORE_WEIGHT],
            mean,
            std,
            w0,
            b0,
            w1,
            b1,
            w2,
            b2,
            wh,
            bh,
            bonus,
        )
    elif ints[I_PRIOR] == PRIOR_NONE:
        bonus[:, :] = 0.0
    for c in range(n_ch):
        for k in range(k_max):
            all_paths[c, k] = (features[c, k, TOA_COLUMN] - assoc_delays[c]) * mm
            allowed[c, k] = math.isfinite(all_paths[c, k])
            alpha = features[c, k, 0]
            a = alpha if math.isfinite(alpha) and alpha > 1.0 else 1.0
            strength[c, k] = floats[F_STRENGTH] * np.log(a)
            if ints[I_PRIOR] != PRIOR_NONE:
                strength[c, k] = strength[c, k] + (
                    bonus[c, k] if math.isfinite(bonus[c, k]) else 0.0
                )


@jit
def _score_bonus(
    features, counts, listening, weight, mean, std, w0, b0, w1, b1, w2, b2, wh, bh, bonus
):
    """As OnnxAssociator.bonus: weight * logit(score) per present, listening, finite echo
    (the echoes scored together by :func:`spiel_edge.pipeline.learned.mlp.mlp_scores`)."""
    n_ch, k_max, n_f = features.shape
    x = np.empty((n_ch * k_max, n_f), dtype=np.float32)
    at = np.empty(n_ch * k_max, dtype=np.int64)
    n = 0
    for c in range(n_ch):
        for k in range(k_max):
            bonus[c, k] = 0.0
            if k >= counts[c] or not listening[c] or not math.isfinite(features[c, k, TOA_COLUMN]):
                continue
            for j in range(n_f):
                x[n, j] = features[c, k, j]
            at[n] = c * k_max + k
            n += 1
    scores = np.empty(n, dtype=np.float32)
    mlp_scores(x, n, mean, std, w0, b0, w1, b1, w2, b2, wh, bh, scores)
    for r in range(n):
        p = np.float64(scores[r])
        p = min(max(p, 1e-4), 1.0 - 1e-4)
        bonus[at[r] // k_max, at[r] % k_max] = weight * np.log(p / (1.0 - p))


@jit
def _echo_timing(y, bg, picked, ints, floats, feature, threshold, value, base, clean):
    """As EchoTiming.__call__ for one target's picked ToAs."""
    if ints[I_TIMING] == TIMING_NONE:
        return picked.copy()
    if ints[I_TIMING] == TIMING_TREES:
        out = np.empty(y.shape[0])
        _fused_kernel(
            y,
            bg,
            ints[I_BLIND],
            picked,
            ints[I_HALF_WINDOW],
            ints[I_LOG] != 0,
            feature,
            threshold,
            value,
            base,
            floats[F_LIMIT],
            out,
        )
        return out
    _clean_kernel(y, bg, ints[I_BLIND], clean)
    out = picked.copy()
    _refine_kernel(clean, picked, ints[I_HALF_WINDOW], ints[I_LOG] != 0, out)
    return out
