"""The several-target acquisition kernel (``max_targets`` > 1, joint selection): front, the
score prior, the combination pool, the joint subset choice, and per chosen combination echo
timing, echo quality, locate, covariance and the after-locating checks (shared echoes,
minimum separation, double reflections), in one compiled call on a Workspace's buffers.

It computes what ``Pipeline.process`` computes with ``SceneAssociator._joint``, bit for bit
(tests/core/test_fused.py, K = 2, 4, 8 with and without a background), by calling the same
kernels in the same order:

1. the front kernel, the score prior and the strength as the one-target kernel;
2. the pool search ``associate.search_kernel`` (as ``joint.combination_pool``), then the
   joint choice's glue in numba (``scene_steps.hypotheses``: the missing-channel shift, the
   stable order by cost with the K = 1 pick first, ``drop_variants``, the birth gains) and
   ``joint.select_kernel``;
3. per hypothesis ``steps.one_target_kernel`` (as ``Pipeline._target``), ``share`` (as
   ``scene.shared_echoes``), the separation and the double-reflection test (as
   ``Pipeline._targets`` with ``scene.is_double_reflection``), using the fixed-order sums of
   :mod:`spiel_edge.pipeline.stages.scene_geometry` that the staged path uses too.

Only the Target and Result objects are built in Python, once per acquisition. Its constants
are the pipeline's (``abi.kernel_config``), its outputs two buffers (:class:`SceneBuffers`).
"""

from __future__ import annotations

import math

import numpy as np

from spiel_edge._jit import jit
from spiel_edge.pipeline.compiled.abi import (
    F_MM_PER_SAMPLE,
    L_CHANNELS,
    L_DELAYS,
    L_EMITTER,
    L_FACING,
    L_FLOATS,
    S_DOUBLE_TOL,
    S_MAX_TARGETS,
    S_MIN_SEPARATION,
    S_SHARE_TOL,
    KernelConfig,
    back_views,
    front_views,
    scene_views,
)
from spiel_edge.pipeline.compiled.front import packed_front, raise_for
from spiel_edge.pipeline.compiled.result import match_list, result
from spiel_edge.pipeline.compiled.scene_steps import double_reflection, hypotheses, share
from spiel_edge.pipeline.compiled.steps import (
    association_inputs,
    one_target_kernel,
    search_arguments,
)
from spiel_edge.pipeline.staged import Target
from spiel_edge.pipeline.stages.associate import MAX_POOL, search_kernel
from spiel_edge.pipeline.stages.features import TOA_COLUMN
from spiel_edge.pipeline.stages.scene_geometry import distance3, predicted_paths_into
from spiel_edge.profile.specs import MAX_TARGETS_LIMIT


class SceneBuffers:
    """The kernel's outputs and pool for one Workspace shape: views of one int64 and one
    float64 buffer (the kernel takes the two)."""

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


def run(pipeline, config: KernelConfig, ws, y, bg, raw, background):
    """The Result of one acquisition with up to ``max_targets`` targets (arguments as
    ``one_target.run``)."""
    features, counts = np.empty_like(ws.features), np.empty_like(ws.counts)
    scale = pipeline.covariance_scale(background)
    if ws.scene is None:  # made once per thread's Workspace
        ws.scene = SceneBuffers(ws.n_channels)
    out = ws.scene
    n = _scene_acquisition_kernel(
        y, bg, *ws.front_buffers, features, counts, scale, *config, ws.bonus, ws.clean,
        *out.buffers,
    )  # fmt: skip
    if n < 0:
        raise_for(-n)
    positions, covariances = out.position[:n].copy(), out.covariance[:n].copy()
    rms, score = out.rms[:n].tolist(), out.score[:n].tolist()
    targets = [
        Target(positions[i], covariances[i], rms[i], match_list(row), score[i])
        for i, row in enumerate(out.matched[:n].tolist())
    ]
    return result(pipeline, features, counts, raw, targets, out.first.tolist())


@jit
def _scene_acquisition_kernel(
    y, bg, env, bg_env, cleaned, peaks, ws_counts, params, iterations, unsorted, ws_features,
    features, counts, cov_scale, ints, f64, f32, i64, flags, layout, bonus, clean, out_ints,
    out_floats,
):  # fmt: skip
    """The front kernel, its features and counts copied into ``features`` and ``counts``,
    then :func:`_scene_steps`: the number of targets, or minus the front's status."""
    fi, ff = front_views(f64, i64, layout)
    status = packed_front(
        y, bg, fi, ff, env, bg_env, cleaned, peaks, ws_counts, params, iterations, unsorted,
        ws_features, features, counts,
    )  # fmt: skip
    if status != 0:
        return -status
    return _scene_steps(
        features, counts, y, bg, cov_scale, ints, back_views(f64, f32, i64, flags, layout),
        scene_views(f64, i64, flags, layout), bonus, clean,
        *_outputs(out_ints, out_floats, features.shape[0]),
    )  # fmt: skip


@jit
def _outputs(ints, floats, n):
    """Views of the two output buffers: pool choices, first, matched (ints); pool costs,
    positions, covariances, rms, scores, paths (floats)."""
    k = MAX_TARGETS_LIMIT
    o = MAX_POOL * n
    pool_choices = ints[:o].reshape((MAX_POOL, n))
    first = ints[o : o + n]
    matched = ints[o + n : o + n + k * n].reshape((k, n))
    pool_costs = floats[:MAX_POOL]
    o = MAX_POOL
    position = floats[o : o + 3 * k].reshape((k, 3))
    o += 3 * k
    covariance = floats[o : o + 9 * k].reshape((k, 3, 3))
    o += 9 * k
    rms = floats[o : o + k]
    score = floats[o + k : o + 2 * k]
    o += 2 * k
    paths = floats[o : o + k * n].reshape((k, n))
    return pool_choices, pool_costs, first, matched, position, covariance, rms, score, paths


@jit
def _scene_steps(
    features, counts, y, bg, cov_scale, ints, cs, scene, bonus, clean, pool_choices, pool_costs,
    first, out_matched, out_position, out_covariance, out_rms, out_score, out_paths,
):  # fmt: skip
    """The kernel's steps: the number of targets found; their matched echoes, positions,
    covariances, rms, scores and paths in ``out_*`` (best first); ``first`` the first
    hypothesis's echoes. ``cs``: the constants' views (``abi.back_views``), ``scene`` the
    scene's (``abi.scene_views``)."""
    n_ch, k_max = features.shape[0], features.shape[1]
    scene_ints, scene_floats, share_listening = scene
    mm = cs[L_FLOATS][F_MM_PER_SAMPLE]
    delays, channels, emitter, facing = cs[L_DELAYS], cs[L_CHANNELS], cs[L_EMITTER], cs[L_FACING]
    all_paths, allowed, strength = association_inputs(features, counts, ints, cs, bonus)
    pool_choices[:, :] = -1
    pool_costs[:] = np.inf
    args = search_arguments(all_paths, strength, counts, allowed, ints, cs)
    n_pool = search_kernel(*args, pool_choices, pool_costs)
    if n_pool == 0:
        first[:] = -1
        return 0
    hyp_matched = np.empty((scene_ints[S_MAX_TARGETS], n_ch), dtype=np.int64)
    hyp_cost = np.empty(scene_ints[S_MAX_TARGETS])
    n_hyp = hypotheses(
        pool_choices[:n_pool], pool_costs[:n_pool], k_max, scene_ints, scene_floats, hyp_matched,
        hyp_cost,
    )  # fmt: skip
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
        ok, rms = one_target_kernel(
            features, y, bg, matched, cov_scale, ints, cs, clean, *scratch, position,
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
            changed = share(
                matched, pred, toa_paths, taken, share_listening, scene_floats[S_SHARE_TOL], more
            )
            if changed:
                ok2, rms2 = one_target_kernel(
                    features, y, bg, more, cov_scale, ints, cs, clean, *scratch, position2,
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
                if double_reflection(
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
