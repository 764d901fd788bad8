"""The fused path's back kernel for several targets (``max_targets`` > 1, joint selection):
the score prior, the combination pool, the joint subset choice, and per chosen combination
echo timing, echo quality, locate, covariance and the after-locating checks (shared echoes,
minimum separation, double reflections), in one compiled call on a Workspace's buffers.

It computes what ``Pipeline.scene`` (``SceneAssociator._joint``) + ``Pipeline._locate``
compute, bit for bit (tests/core/test_fused.py, K = 2, 4, 8 with and without a background),
by calling the same kernels in the same order:

1. the score prior and the strength as :mod:`spiel_edge.pipeline.compiled.one_target` (K = 1);
2. ``joint._pool_kernel`` (as ``joint.combination_pool``), then the joint choice's glue in
   numba (``scene_steps._hypotheses``: the missing-channel shift, the stable order by cost
   with the K = 1 pick first, ``drop_variants``, the birth gains) and
   ``joint._select_kernel``;
3. per hypothesis ``back_steps._one_target`` (as ``Pipeline._target``), ``_share`` (as
   ``scene.shared_echoes``), the separation and the double-reflection test (as
   ``Pipeline._targets`` with ``scene.is_double_reflection``), using the fixed-order sums of
   :mod:`spiel_edge.pipeline.stages.scene_geometry` that the staged path uses too.

Only the Target and Result objects are built in Python, once per acquisition. The call
takes 15 arguments, not 45 (numba's dispatch costs about 65 ns per array argument): the
constants are packed by dtype into four buffers (:func:`pack_config`), the outputs into two
(:class:`SceneBuffers`), and ``_scene_kernel`` hands their views to ``_scene_steps``;
``_scene_acquisition_kernel`` runs the front kernel and it in one call. The staged
path stays the reference: :func:`scene_config` returns None (staged back steps) for greedy
selection, the learned associator's reference mode, more than 6 listening channels, or
anything :func:`spiel_edge.pipeline.compiled.one_target.kernel_arguments` does not cover.
"""

from __future__ import annotations

import math

import numpy as np

from spiel_edge._jit import jit
from spiel_edge.pipeline import staged as run
from spiel_edge.pipeline.compiled import one_target as back
from spiel_edge.pipeline.compiled.front import _packed_front, front_packed, front_scalars, raise_for
from spiel_edge.pipeline.compiled.scene_steps import (
    S_DOUBLE_TOL,
    S_MAX_TARGETS,
    S_MIN_SEPARATION,
    S_SHARE_TOL,
    _back_views,
    _double_reflection,
    _front_views,
    _hypotheses,
    _outputs,
    _scene_views,
    _share,
    pack_config,
)
from spiel_edge.pipeline.compiled.steps import (
    F_MM_PER_SAMPLE,
    I_MIN_CHANNELS,
    _association_inputs,
    _one_target,
)
from spiel_edge.pipeline.stages.features import TOA_COLUMN
from spiel_edge.pipeline.stages.joint import MAX_POOL, _pool_kernel
from spiel_edge.pipeline.stages.scene_geometry import distance3, predicted_paths_into
from spiel_edge.profile.specs import MAX_TARGETS_LIMIT


def scene_config(pipeline: run.Pipeline) -> tuple | None:
    """The several-target kernel's constant arguments (packed, :func:`pack_config`), or None
    when the pipeline must run the staged back steps."""
    args = scene_arguments(pipeline)
    return None if args is None else pack_config(args)


def scene_arguments(pipeline: run.Pipeline) -> tuple | None:
    """The kernel's constant arguments one by one: ``back.kernel_arguments``, then the
    scene's ints, floats and listening mask, then the front kernel's scalars
    (:data:`~spiel_edge.pipeline.compiled.scene_steps._SLOTS` after ``ints``)."""
    scene = pipeline.scene
    if scene.max_targets < 2 or not scene.joint:
        return None
    base = back.kernel_arguments(pipeline)
    if base is None:
        return None
    sc, g = pipeline.profile.scene, pipeline.profile.geometry
    ints = np.array([scene.max_targets, scene.extra_min_channels, scene.keep_best], dtype=np.int64)
    floats = np.array(
        [
            scene.max_cost_mm,
            scene.share_penalty_mm,
            scene.missing_shift_mm,
            sc.share_tolerance_mm,
            sc.min_separation_mm,
            sc.double_tolerance_mm,
        ]
    )
    listening = np.ascontiguousarray(g.listening_mask(), dtype=np.bool_)
    return (*base, ints, floats, listening, *front_packed(front_scalars(pipeline.profile)))


class SceneBuffers:
    """The several-target kernel's outputs and pool for one Workspace shape: views of one
    int64 and one float64 buffer (the kernel takes the two)."""

    def __init__(self, n_channels: int):
        k, n = MAX_TARGETS_LIMIT, n_channels
        self.ints = np.full(MAX_POOL * n + n + k * n, -1, dtype=np.int64)
        self.floats = np.full(MAX_POOL + k * (3 + 9 + 1 + 1 + n), np.inf)
        (
            self.pool_choices,
            self.pool_costs,
            self.first,
            self.matched,
            self.position,
            self.covariance,
            self.rms,
            self.score,
            self.paths,
        ) = _outputs(self.ints, self.floats, n)
        self.buffers = (self.ints, self.floats)


@jit
def _scene_kernel(
    features, counts, y, bg, cov_scale, ints, f64, f32, i64, flags, layout, bonus, clean,
    out_ints, out_floats,
):  # fmt: skip
    """:func:`_scene_steps` on the packed constants (:func:`pack_config`) and the two output
    buffers (:class:`SceneBuffers`); returns the number of targets."""
    outs = _outputs(out_ints, out_floats, features.shape[0])
    return _scene_steps(
        features, counts, y, bg, cov_scale, ints, *_back_views(f64, f32, i64, flags, layout),
        *_scene_views(f64, i64, flags, layout), bonus, clean, *outs,
    )  # fmt: skip


def run_scene(pipeline, config, ws, features, counts, y, bg, raw, background, bonus_given):
    """The Result of one acquisition with up to ``max_targets`` targets, from the front
    kernel's features (a fresh copy) and counts (as :func:`spiel_edge.pipeline.compiled.one_target.run_back`)."""
    if bonus_given is not None:
        ws.bonus[:, :] = bonus_given
    scale = back.covariance_scale(pipeline, background)
    buffers = _scene_buffers(ws)
    n = _scene_kernel(features, counts, y, bg, scale, *config, ws.bonus, ws.clean, *buffers.buffers)
    return _result(pipeline, buffers, features, counts, raw, n)


def run_scene_acquisition(pipeline, config, ws, y, bg, raw, background):
    """The Result of one acquisition in one compiled call, front and back (as the front
    kernel followed by :func:`run_scene` without a bonus)."""
    features, counts = np.empty_like(ws.features), np.empty_like(ws.counts)
    scale = back.covariance_scale(pipeline, background)
    buffers = _scene_buffers(ws)
    n = _scene_acquisition_kernel(
        y, bg, *ws.front_buffers, features, counts, scale, *config, ws.bonus, ws.clean,
        *buffers.buffers,
    )  # fmt: skip
    if n < 0:
        raise_for(-n)
    return _result(pipeline, buffers, features, counts, raw, n)


def _scene_buffers(ws) -> SceneBuffers:
    buffers = getattr(ws, "scene", None)
    if buffers is None:  # made once per thread's Workspace
        buffers = ws.scene = SceneBuffers(ws.n_channels)
    return buffers


def _result(pipeline, buffers: SceneBuffers, features, counts, raw, n: int) -> run.Result:
    toa = features[:, :, TOA_COLUMN]  # tolist: Python floats and ints, as the staged lists
    echoes = [toa[c, :k].tolist() for c, k in enumerate(counts.tolist())]
    base = {"features": features, "counts": counts}
    if n == 0:
        match_list = [m if m >= 0 else None for m in buffers.first.tolist()]
        used = sum(m is not None for m in match_list)
        reason = run.REASON_SOLVE_FAILED if used >= 3 else pipeline._why_empty(raw, counts)
        return run.Result(None, reason, None, echoes, match_list, **base)
    positions = buffers.position[:n].copy()
    covariances = buffers.covariance[:n].copy()
    rms, score = buffers.rms[:n].tolist(), buffers.score[:n].tolist()
    targets = [
        run.Target(
            positions[i],
            covariances[i],
            rms[i],
            [m if m >= 0 else None for m in row],
            score[i],
        )
        for i, row in enumerate(buffers.matched[:n].tolist())
    ]
    best = targets[0]
    return run.Result(
        best.position_mm, None, best.residual_mm, echoes, best.matched, targets=targets, **base
    )


@jit
def _scene_acquisition_kernel(
    y, bg, env, bg_env, cleaned, peaks, ws_counts, params, iterations, unsorted, ws_features,
    features, counts, cov_scale, ints, f64, f32, i64, flags, layout, bonus, clean, out_ints,
    out_floats,
):  # fmt: skip
    """The front kernel, its features and counts copied into ``features`` and ``counts``,
    then :func:`_scene_kernel`: the number of targets, or minus the front's status."""
    fi, ff = _front_views(f64, i64, layout)
    status = _packed_front(
        y, bg, fi, ff, env, bg_env, cleaned, peaks, ws_counts, params, iterations, unsorted,
        ws_features, features, counts,
    )  # fmt: skip
    if status != 0:
        return -status
    return _scene_kernel(
        features, counts, y, bg, cov_scale, ints, f64, f32, i64, flags, layout, bonus, clean,
        out_ints, out_floats,
    )  # fmt: skip


@jit
def _scene_steps(
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
    scene_ints,
    scene_floats,
    share_listening,
    bonus,
    clean,
    pool_choices,
    pool_costs,
    first,
    out_matched,
    out_position,
    out_covariance,
    out_rms,
    out_score,
    out_paths,
):
    """The kernel's steps on the unpacked arguments: the number of targets found; their
    matched echoes, positions, covariances, rms, scores and paths in ``out_*`` (best
    first); ``first`` the first hypothesis's echoes."""
    n_ch, k_max = features.shape[0], features.shape[1]
    mm = floats[F_MM_PER_SAMPLE]
    all_paths = np.empty((n_ch, k_max))
    allowed = np.empty((n_ch, k_max), dtype=np.bool_)
    strength = np.empty((n_ch, k_max))
    _association_inputs(
        features, counts, listening, ints, floats, assoc_delays, mean, std, w0, b0, w1, b1, w2,
        b2, wh, bh, bonus, all_paths, allowed, strength,
    )  # fmt: skip
    pool_choices[:, :] = -1
    pool_costs[:] = np.inf
    n_pool = _pool_kernel(
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
        pool_choices,
        pool_costs,
    )
    if n_pool == 0:
        first[:] = -1
        return 0
    hyp_matched = np.empty((scene_ints[S_MAX_TARGETS], n_ch), dtype=np.int64)
    hyp_cost = np.empty(scene_ints[S_MAX_TARGETS])
    n_hyp = _hypotheses(
        pool_choices[:n_pool],
        pool_costs[:n_pool],
        k_max,
        scene_ints,
        scene_floats,
        hyp_matched,
        hyp_cost,
    )
    first[:] = hyp_matched[0]
    # Pipeline._targets
    toa_paths = np.empty((n_ch, k_max))
    taken = np.zeros((n_ch, k_max), dtype=np.bool_)
    for c in range(n_ch):
        for k in range(k_max):
            toa_paths[c, k] = (features[c, k, TOA_COLUMN] - delays[c]) * mm
    for h in range(n_hyp):
        for c in range(n_ch):
            if hyp_matched[h, c] >= 0:
                taken[c, hyp_matched[h, c]] = True
    position = np.empty(3)
    covariance = np.empty((3, 3))
    paths = np.empty(n_ch)
    position2 = np.empty(3)
    covariance2 = np.empty((3, 3))
    paths2 = np.empty(n_ch)
    more = np.empty(n_ch, dtype=np.int64)
    pred = np.empty(n_ch)
    scratch = (np.empty(n_ch), np.empty(n_ch), np.empty(n_ch), np.empty(n_ch, dtype=np.bool_))
    n_out = 0
    for h in range(n_hyp):
        matched = hyp_matched[h]
        ok, rms = _one_target(
            features, y, bg, matched, cov_scale, ints, floats, quality, delays, channels,
            emitter, facing, feature, threshold, value, base, clean, *scratch, position,
            covariance, paths,
        )  # fmt: skip
        if not ok:
            continue
        final = matched
        missing = False
        for c in range(n_ch):
            missing = missing or matched[c] < 0
        if h > 0 and missing:
            predicted_paths_into(position, channels, emitter, pred)
            changed = _share(
                matched, pred, toa_paths, taken, share_listening, scene_floats[S_SHARE_TOL], more
            )
            if changed:
                ok2, rms2 = _one_target(
                    features, y, bg, more, cov_scale, ints, floats, quality, delays, channels,
                    emitter, facing, feature, threshold, value, base, clean, *scratch, position2,
                    covariance2, paths2,
                )  # fmt: skip
                if ok2:
                    final, rms = more, rms2
                    position[:] = position2
                    covariance[:, :] = covariance2
                    paths[:] = paths2
        drop = False
        for j in range(n_out):
            if distance3(position, out_position[j]) < scene_floats[S_MIN_SEPARATION]:
                drop = True  # the same target again, from a partly different combination
                break
        if not drop:
            for j in range(n_out):
                if _double_reflection(
                    paths,
                    out_paths[j],
                    out_position[j],
                    emitter,
                    facing,
                    scene_floats[S_DOUBLE_TOL],
                ):
                    drop = True
                    break
        if drop:
            continue
        out_matched[n_out] = final
        out_position[n_out] = position
        out_covariance[n_out] = covariance
        out_rms[n_out] = rms
        cost = hyp_cost[h]
        out_score[n_out] = -cost if math.isfinite(cost) else 0.0
        out_paths[n_out] = paths
        n_out += 1
    return n_out
