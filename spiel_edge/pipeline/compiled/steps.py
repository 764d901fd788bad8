"""The compiled steps both acquisition kernels share (one_target.py, several_targets.py): the
association search's inputs (score prior, paths, strengths), the MLP prior, echo timing, and
one target from its matched echoes (as ``Pipeline._target``: echo timing, echo quality,
locate, covariance). Their ``ints`` / ``floats`` entries are declared in abi.py."""

from __future__ import annotations

import math

import numpy as np

from spiel_edge._jit import jit
from spiel_edge.pipeline.compiled.abi import (
    F_COV_FLOOR,
    F_LIMIT,
    F_MM_PER_SAMPLE,
    F_SCORE_WEIGHT,
    F_STRENGTH,
    I_BLIND,
    I_HALF_WINDOW,
    I_LOG,
    I_MIN_CHANNELS,
    I_PRIOR,
    I_TIMING,
    L_ASSOC_DELAYS,
    L_B0,
    L_B1,
    L_B2,
    L_BASE,
    L_BH,
    L_CHANNELS,
    L_COST_WEIGHTS,
    L_DELAYS,
    L_EMITTER,
    L_FACING,
    L_FEATURE,
    L_FLOATS,
    L_LISTENING,
    L_MAX_PATH_DIFF,
    L_MEAN,
    L_QUALITY,
    L_STD,
    L_THRESHOLD,
    L_VALUE,
    L_W0,
    L_W1,
    L_W2,
    L_WH,
    PRIOR_MLP,
    PRIOR_NONE,
    TIMING_NONE,
    TIMING_TREES,
)
from spiel_edge.pipeline.learned.mlp import mlp_scores
from spiel_edge.pipeline.stages.echo_quality import echo_quality_kernel
from spiel_edge.pipeline.stages.echo_timing import clean_kernel, fused_kernel, refine_kernel
from spiel_edge.pipeline.stages.features import TOA_COLUMN
from spiel_edge.pipeline.stages.locate import locate_kernel
from spiel_edge.pipeline.stages.uncertainty import covariance_kernel

LOCATE_ITER = 30  # Gauss-Newton iterations of the final position (passed as int(): one signature)


@jit
def one_target_kernel(
    features, y, bg, matched, cov_scale, ints, cs, clean, picked, weights, shift, mask, position,
    covariance, paths,
):  # fmt: skip
    """As ``Pipeline._target``, for the K = 1 back kernel after association and for each target
    of the several-target kernel (several_targets.py): (ok, rms);
    position, covariance and paths filled."""
    n_ch = features.shape[0]
    floats, delays, channels = cs[L_FLOATS], cs[L_DELAYS], cs[L_CHANNELS]
    emitter, facing = cs[L_EMITTER], cs[L_FACING]
    mm = floats[F_MM_PER_SAMPLE]
    n_use = 0
    for c in range(n_ch):
        use = matched[c] >= 0
        n_use += use
        picked[c] = features[c, max(matched[c], 0), TOA_COLUMN] if use else np.nan
    if n_use < 3:
        return False, math.inf
    timed = _echo_timing(
        y, bg, picked, ints, floats, cs[L_FEATURE], cs[L_THRESHOLD], cs[L_VALUE], cs[L_BASE], clean
    )
    alpha_matched = np.empty(n_ch)
    for c in range(n_ch):
        alpha_matched[c] = features[c, max(matched[c], 0), 0]
    echo_quality_kernel(y, bg, timed, alpha_matched, cs[L_QUALITY], weights, shift)
    for c in range(n_ch):
        s = 0.0 if ints[I_TIMING] != TIMING_NONE else shift[c]
        paths[c] = (timed[c] + s - delays[c]) * mm
    for c in range(n_ch):
        mask[c] = matched[c] >= 0 and math.isfinite(paths[c])
    ok, rms = locate_kernel(
        paths, mask, weights, emitter, channels, facing, int(LOCATE_ITER), position
    )
    if not ok:
        return False, rms
    sigma = np.empty(n_ch)
    for c in range(n_ch):
        sigma[c] = mm / weights[c]
    covariance_kernel(
        position, paths, sigma, mask, channels, emitter, cov_scale, floats[F_COV_FLOOR], covariance
    )
    return True, rms


@jit
def association_inputs(features, counts, ints, cs, bonus):
    """The association search's inputs, as the staged associator builds them: the score
    prior into ``bonus`` (the MLP's, or zeros), and (each echo's path in mm, whether it is
    finite, its strength: log amplitude plus prior)."""
    n_ch, k_max = features.shape[0], features.shape[1]
    all_paths = np.empty((n_ch, k_max))
    allowed = np.empty((n_ch, k_max), dtype=np.bool_)
    strength = np.empty((n_ch, k_max))
    floats, assoc_delays = cs[L_FLOATS], cs[L_ASSOC_DELAYS]
    mm = floats[F_MM_PER_SAMPLE]
    if ints[I_PRIOR] == PRIOR_MLP:
        _score_bonus(
            features, counts, cs[L_LISTENING], floats[F_SCORE_WEIGHT], cs[L_MEAN], cs[L_STD],
            cs[L_W0], cs[L_B0], cs[L_W1], cs[L_B1], cs[L_W2], cs[L_B2], cs[L_WH], cs[L_BH], bonus,
        )  # fmt: skip
    else:
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
    return all_paths, allowed, strength


@jit(inline="always")
def search_arguments(all_paths, strength, counts, allowed, ints, cs):
    """The search kernels' arguments before their outputs (``associate.search_kernel``)."""
    return (
        all_paths, strength, counts, allowed, cs[L_LISTENING], cs[L_CHANNELS], cs[L_EMITTER],
        cs[L_FACING], cs[L_MAX_PATH_DIFF], cs[L_COST_WEIGHTS], ints[I_MIN_CHANNELS],
    )  # fmt: skip


@jit
def _score_bonus(
    features, counts, listening, weight, mean, std, w0, b0, w1, b1, w2, b2, wh, bh, bonus
):
    """As OnnxAssociator.bonus: weight * logit(score) per present, listening, finite echo
    (the echoes scored together by :func:`spiel_edge.pipeline.learned.mlp.mlp_scores`)."""
    n_ch, k_max, n_f = features.shape
    x = np.empty((n_ch * k_max, n_f), dtype=np.float32)
    at = np.empty(n_ch * k_max, dtype=np.int64)
    n = int(0)  # noqa: UP018 (an int64, not Literal[int]: one compiled signature)
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
        fused_kernel(
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
    clean_kernel(y, bg, ints[I_BLIND], clean)
    out = picked.copy()
    refine_kernel(clean, picked, ints[I_HALF_WINDOW], ints[I_LOG] != 0, out)
    return out
