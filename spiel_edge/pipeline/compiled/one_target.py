"""The one-target acquisition kernel (``max_targets`` = 1): front, then associate, echo
timing, echo quality, locate and covariance of one target, in one compiled call on a
Workspace's buffers.

It computes what ``Pipeline.process`` computes for one target, bit for bit
(tests/core/test_back.py, test_fused.py), by calling the same kernels in the same order:

1. the front kernel (:mod:`spiel_edge.pipeline.compiled.front`);
2. the learned score prior: the association MLP in numba on every echo at once
   (:func:`spiel_edge.pipeline.learned.mlp.mlp_scores`, bit for bit
   ``OnnxAssociator.score``'s per-row :func:`~spiel_edge.pipeline.learned.mlp.mlp_row`), or
   none (geometric association);
3. the associator's search (``associate.exhaustive_kernel`` / ``hypothesis_kernel``) with
   the strength and the bonus as ``GeometricAssociator.search_inputs`` builds them;
4. echo timing (``echo_timing.fused_kernel`` with the numba trees, or clean + refine without
   a correction), ``echo_quality.echo_quality_kernel``, ``locate.locate_kernel`` and
   ``uncertainty.covariance_kernel`` as ``Pipeline._target`` (``steps.one_target_kernel``).

Its constants are the pipeline's (``abi.kernel_config``).
"""

from __future__ import annotations

import math

import numpy as np

from spiel_edge._jit import jit
from spiel_edge.pipeline.compiled.abi import (
    I_EXHAUSTIVE,
    L_ANCHORS,
    KernelConfig,
    back_views,
    front_views,
)
from spiel_edge.pipeline.compiled.front import packed_front, raise_for
from spiel_edge.pipeline.compiled.result import match_list, result
from spiel_edge.pipeline.compiled.steps import (
    association_inputs,
    one_target_kernel,
    search_arguments,
)
from spiel_edge.pipeline.staged import Target
from spiel_edge.pipeline.stages.associate import exhaustive_kernel, hypothesis_kernel


def run(pipeline, config: KernelConfig, ws, y, bg, raw, background):
    """The Result of one acquisition; ``y``/``bg`` the float64 frames and background (empty
    rows when none), ``raw`` the frames as given, ``background`` the one the staged path
    would use (or None)."""
    features, counts = np.empty_like(ws.features), np.empty_like(ws.counts)
    scale = pipeline.covariance_scale(background)
    status, cost, found, rms = _acquisition_kernel(
        y, bg, *ws.front_buffers, features, counts, scale, *config, *ws.back_buffers
    )
    if status:
        raise_for(status)
    first = ws.matched.tolist()
    targets = []
    if found:
        score = -cost if math.isfinite(cost) else 0.0
        position, covariance = ws.position.copy(), ws.covariance.copy()
        targets = [Target(position, covariance, rms, match_list(first), score)]
    return result(pipeline, features, counts, raw, targets, first)


@jit
def _acquisition_kernel(
    y, bg, env, bg_env, cleaned, peaks, ws_counts, params, iterations, unsorted, ws_features,
    features, counts, cov_scale, ints, f64, f32, i64, flags, layout, bonus, matched, picked,
    weights, shift, paths, use, clean, position, covariance,
):  # fmt: skip
    """The front kernel, its features and counts copied into ``features`` and ``counts``,
    then :func:`_back_steps`: (front status, cost, found, rms); status 0 when done."""
    fi, ff = front_views(f64, i64, layout)
    status = packed_front(
        y, bg, fi, ff, env, bg_env, cleaned, peaks, ws_counts, params, iterations, unsorted,
        ws_features, features, counts,
    )  # fmt: skip
    if status != 0:
        return status, math.inf, False, math.inf
    cost, ok, rms = _back_steps(
        features, counts, y, bg, cov_scale, ints, back_views(f64, f32, i64, flags, layout),
        bonus, matched, picked, weights, shift, paths, use, clean, position, covariance,
    )  # fmt: skip
    return 0, cost, ok, rms


@jit
def _back_steps(
    features, counts, y, bg, cov_scale, ints, cs, bonus, matched, picked, weights, shift, paths,
    use, clean, position, covariance,
):  # fmt: skip
    """(association cost, target found, rms mm); matched, position and covariance filled.
    ``cs``: the constants' views (``abi.back_views``), read by their slots."""
    all_paths, allowed, strength = association_inputs(features, counts, ints, cs, bonus)
    matched[:] = -1
    args = search_arguments(all_paths, strength, counts, allowed, ints, cs)
    if ints[I_EXHAUSTIVE] != 0:
        cost = exhaustive_kernel(*args, matched)
    else:
        cost = hypothesis_kernel(*args, matched, cs[L_ANCHORS])
    ok, rms = one_target_kernel(
        features, y, bg, matched, cov_scale, ints, cs, clean, picked, weights, shift, use,
        position, covariance, paths,
    )  # fmt: skip
    return cost, ok, rms
