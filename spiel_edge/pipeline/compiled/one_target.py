"""The fused path's back kernel: associate, echo timing, echo quality, locate and covariance
of one target (K = 1) in one compiled call on a Workspace's buffers; ``_acquisition_kernel``
runs the front kernel and it in one call.

It computes what ``Pipeline.scene`` + ``Pipeline._locate`` compute for one target, bit for bit
(tests/core/test_back.py), by calling the same kernels in the same order:

1. the learned score prior (``prior``): the association MLP in numba on every echo at once
   (:func:`spiel_edge.pipeline.learned.mlp.mlp_scores`, bit for bit ``OnnxAssociator.score``'s
   per-row :func:`~spiel_edge.pipeline.learned.mlp.mlp_row`), or a bonus the
   caller computed with onnxruntime between the front and the back kernel (a model that is
   not the known MLP), or none (geometric association);
2. the associator's search (``associate._exhaustive_kernel`` / ``_hypothesis_kernel``) with
   the strength and the bonus as ``GeometricAssociator.candidates`` builds them;
3. echo timing (``echo_timing._fused_kernel`` with the numba trees, or clean + refine without
   a correction), ``echo_quality._echo_quality_kernel``, ``locate.locate_kernel`` and
   ``uncertainty._covariance_kernel`` as ``Pipeline._target``.

:func:`back_config` says whether a pipeline can use it (one target, the geometric or the
learned associator in prior mode, echo timing without an onnxruntime correction, no
overridden back methods); otherwise the fused path runs the staged back steps. Its constants
come packed by dtype (``scene_steps.pack_config``, as the several-target kernel's: 21
arguments instead of 41, at about 65 ns of numba's dispatch per array).
"""

from __future__ import annotations

import math

import numpy as np

from spiel_edge._jit import jit
from spiel_edge.pipeline import staged as run
from spiel_edge.pipeline.compiled.front import _packed_front, front_packed, front_scalars, raise_for
from spiel_edge.pipeline.compiled.scene_steps import _back_views, _front_views, pack_config
from spiel_edge.pipeline.compiled.steps import (
    I_EXHAUSTIVE,
    I_MIN_CHANNELS,
    PRIOR_GIVEN,
    PRIOR_MLP,
    PRIOR_NONE,
    TIMING_NONE,
    TIMING_REFINE,
    TIMING_TREES,
    _association_inputs,
    _one_target,
)
from spiel_edge.pipeline.stages.associate import (
    GeometricAssociator,
    _exhaustive_kernel,
    _hypothesis_kernel,
)
from spiel_edge.pipeline.stages.echo_timing import ESTIMATORS, EchoTiming
from spiel_edge.pipeline.stages.features import TOA_COLUMN
from spiel_edge.pipeline.stages.scene import SceneAssociator

BACK_STAGES = ("associate", "echo_timing", "locate")
_NO_TREES = (
    np.zeros((1, 1), np.int64),
    np.zeros((1, 1), np.float32),
    np.zeros((1, 1), np.float32),
    0.0,
)
_NO_MLP = tuple(np.zeros((1,) * n, np.float32) for n in (1, 1, 2, 1, 2, 1, 2, 1, 2, 1))
_NO_SCENE = (np.zeros(0, np.int64), np.zeros(0), np.zeros(0, np.bool_))  # its slots, K = 1


def back_config(pipeline: run.Pipeline) -> tuple | None:
    """The back kernel's constant arguments for this pipeline, packed
    (:func:`~spiel_edge.pipeline.compiled.scene_steps.pack_config`), or None when it must run the
    staged back steps (then the reason is logged by the caller)."""
    if pipeline.scene.max_targets != 1:
        return None
    args = kernel_arguments(pipeline)
    if args is None:
        return None
    front = front_packed(front_scalars(pipeline.profile))
    return pack_config((*args, *_NO_SCENE, *front))


def kernel_arguments(pipeline: run.Pipeline) -> tuple | None:
    """The constant arguments of a back kernel for one target (the several-target kernel,
    pipeline/compiled/several_targets.py, takes them too), whatever ``max_targets``; None when the
    pipeline has a step they do not describe."""
    scene, assoc, timing = pipeline.scene, pipeline.associator, pipeline.echo_timing
    methods = ("_locate", "_targets", "_target")
    if (
        tuple(run.STAGES[-3:]) != BACK_STAGES
        or any(getattr(type(pipeline), m) is not getattr(run.Pipeline, m) for m in methods)
        or type(scene) is not SceneAssociator
        or type(scene.geometric) is not GeometricAssociator
        or type(timing) is not EchoTiming
    ):
        return None
    prior, mlp, score_weight = _prior(assoc)
    if prior is None:
        return None
    timing_mode, trees = _timing(timing)
    if timing_mode is None:
        return None
    geo, p = scene.geometric, pipeline.profile
    loc, sc = p.locate, p.scene
    ints = np.array(
        [
            geo.min_channels,
            geo.anchors is None,
            prior,
            timing_mode,
            timing.blind_zone,
            timing.half_window,
            ESTIMATORS[timing.estimator] == ESTIMATORS["log_parabola"],
        ],
        dtype=np.int64,
    )
    floats = np.array(
        [
            geo.mm_per_sample,
            geo.strength_weight_mm,
            score_weight,
            float(getattr(timing.correction, "max_correction", 0.0)),
            sc.covariance_floor_mm,
        ]
    )
    anchors = geo.anchors if geo.anchors is not None else np.zeros((0, 3), np.int64)
    cost_weights = np.array(
        [geo.max_residual_mm, geo.missing_penalty_mm, 1.0, geo.range_weight], dtype=np.float64
    )
    quality = np.array(
        [
            loc.toa_sigma_samples,
            loc.toa_sigma_per_background,
            loc.toa_sigma_alpha_counts,
            loc.toa_shift_background_after,
            loc.toa_shift_background_before,
        ]
    )
    geometry = (
        geo.delays,
        geo.listening,
        geo.max_path_diff,
        anchors,
        cost_weights,
        pipeline._delays,
        pipeline._channels,
        pipeline._emitter,
        pipeline._facing,
    )
    return (ints, floats, quality, *geometry, *mlp, *trees)


def _prior(assoc) -> tuple:
    """(prior mode or None when unsupported, MLP weights, score weight)."""
    if type(assoc) is GeometricAssociator:
        return PRIOR_NONE, _NO_MLP, 0.0
    from spiel_edge.pipeline.learned.associate_onnx import OnnxAssociator  # only when it is in use

    if type(assoc) is not OnnxAssociator or assoc.mode != "prior":
        return None, _NO_MLP, 0.0
    if assoc.mlp is None:
        return PRIOR_GIVEN, _NO_MLP, assoc.score_weight_mm
    return PRIOR_MLP, assoc.mlp, assoc.score_weight_mm


def _timing(timing: EchoTiming) -> tuple:
    if not timing.active:
        return TIMING_NONE, _NO_TREES
    if timing.correction is None:
        return TIMING_REFINE, _NO_TREES
    trees = getattr(timing.correction, "trees", None)
    return (None, _NO_TREES) if trees is None else (TIMING_TREES, trees)


def run_back(pipeline, config, ws, features, counts, y, bg, raw, background, bonus_given):
    """The Result of one acquisition from the front kernel's features (a fresh copy) and
    counts; ``y``/``bg`` the float64 frames and background (empty rows when none)."""
    if bonus_given is not None:
        ws.bonus[:, :] = bonus_given
    scale = covariance_scale(pipeline, background)
    cost, found, rms = _back_kernel(features, counts, y, bg, scale, *config, *ws.back_buffers)
    return _result(pipeline, ws, features, counts, raw, cost, found, rms)


def run_acquisition(pipeline, config, ws, y, bg, raw, background):
    """The Result of one acquisition in one compiled call, front and back; the same as the
    front kernel followed by :func:`run_back` (without a bonus)."""
    features, counts = np.empty_like(ws.features), np.empty_like(ws.counts)
    scale = covariance_scale(pipeline, background)
    status, cost, found, rms = _acquisition_kernel(
        y, bg, *ws.front_buffers, features, counts, scale, *config, *ws.back_buffers
    )
    if status:
        raise_for(status)
    return _result(pipeline, ws, features, counts, raw, cost, found, rms)


def covariance_scale(pipeline, background) -> float:
    """As Pipeline._target: the scale for a captured background, or for none (the static
    model standing in)."""
    sc = pipeline.profile.scene
    captured = background is not None and background is not pipeline.static_model
    return float(sc.covariance_scale if captured else sc.covariance_scale_no_background)


def _result(pipeline, ws, features, counts, raw, cost, found, rms) -> run.Result:
    toa = features[:, :, TOA_COLUMN]  # tolist: Python floats and ints, as the staged lists
    echoes = [toa[c, :n].tolist() for c, n in enumerate(counts.tolist())]
    match_list = [m if m >= 0 else None for m in ws.matched.tolist()]
    base = {"features": features, "counts": counts}
    if not found:
        used = sum(m is not None for m in match_list)
        reason = run.REASON_SOLVE_FAILED if used >= 3 else pipeline._why_empty(raw, counts)
        return run.Result(None, reason, None, echoes, match_list, **base)
    score = -cost if math.isfinite(cost) else 0.0
    target = run.Target(ws.position.copy(), ws.covariance.copy(), rms, match_list, score)
    return run.Result(target.position_mm, None, rms, echoes, match_list, targets=[target], **base)


@jit
def _acquisition_kernel(
    y, bg, env, bg_env, cleaned, peaks, ws_counts, params, iterations, unsorted, ws_features,
    features, counts, cov_scale, ints, f64, f32, i64, flags, layout, bonus, matched, picked,
    weights, shift, paths, use, clean, position, covariance,
):  # fmt: skip
    """The front kernel, its features and counts copied into ``features`` and ``counts``,
    then :func:`_back_kernel`: (front status, cost, found, rms); status 0 when done."""
    fi, ff = _front_views(f64, i64, layout)
    status = _packed_front(
        y, bg, fi, ff, env, bg_env, cleaned, peaks, ws_counts, params, iterations, unsorted,
        ws_features, features, counts,
    )  # fmt: skip
    if status != 0:
        return status, math.inf, False, math.inf
    cost, ok, rms = _back_kernel(
        features, counts, y, bg, cov_scale, ints, f64, f32, i64, flags, layout, bonus, matched,
        picked, weights, shift, paths, use, clean, position, covariance,
    )  # fmt: skip
    return 0, cost, ok, rms


@jit
def _back_kernel(
    features, counts, y, bg, cov_scale, ints, f64, f32, i64, flags, layout, bonus, matched,
    picked, weights, shift, paths, use, clean, position, covariance,
):  # fmt: skip
    """:func:`_back_steps` on the packed constants (:func:`back_config`): (cost, found, rms)."""
    return _back_steps(
        features, counts, y, bg, cov_scale, ints, *_back_views(f64, f32, i64, flags, layout),
        bonus, matched, picked, weights, shift, paths, use, clean, position, covariance,
    )  # fmt: skip


@jit
def _back_steps(
    features,
    counts,
    y,
    bg,
    cov_scale,
    ints,
    floats,
    quality,
    assoc_delays,
    listening,
    max_path_diff,
    anchors,
    cost_weights,
    delays,
    channels,
    emitter,
    facing,
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
    feature,
    threshold,
    value,
    base,
    bonus,
    matched,
    picked,
    weights,
    shift,
    paths,
    use,
    clean,
    position,
    covariance,
):
    """(association cost, target found, rms mm); matched, position and covariance filled."""
    n_ch, k_max = features.shape[0], features.shape[1]
    all_paths = np.empty((n_ch, k_max))
    allowed = np.empty((n_ch, k_max), dtype=np.bool_)
    strength = np.empty((n_ch, k_max))
    _association_inputs(
        features, counts, listening, ints, floats, assoc_delays, mean, std, w0, b0, w1, b1, w2,
        b2, wh, bh, bonus, all_paths, allowed, strength,
    )  # fmt: skip
    matched[:] = -1
    args = (
        all_paths,
        strength,
        counts,
        allowed,
        listening,
        channels,
        emitter,
        facing,
        max_path_diff,
        cost_weights,
        ints[I_MIN_CHANNELS],
        matched,
    )
    exhaustive = ints[I_EXHAUSTIVE] != 0
    cost = _exhaustive_kernel(*args) if exhaustive else _hypothesis_kernel(*args, anchors)
    ok, rms = _one_target(
        features, y, bg, matched, cov_scale, ints, floats, quality, delays, channels, emitter,
        facing, feature, threshold, value, base, clean, picked, weights, shift, use, position,
        covariance, paths,
    )  # fmt: skip
    return cost, ok, rms
