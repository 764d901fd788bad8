"""The several-target kernel's steps (pipeline/compiled/several_targets.py), each as the staged function it
replaces computes it: the joint choice after the pool (``SceneAssociator._joint``), the
shared echoes (``scene.shared_echoes``) and the double-reflection test
(``scene.is_double_reflection``). Tested against those in tests/core/test_back_scene.py. One
target (``Pipeline._target``) is ``back_steps._one_target``, shared with the K = 1 kernel."""

from __future__ import annotations

import logging
import math

import numpy as np

from spiel_edge._jit import jit
from spiel_edge.pipeline.stages.joint import MAX_NODES, MAX_POOL, _select_kernel
from spiel_edge.pipeline.stages.scene_geometry import height3
from spiel_edge.profile.specs import MAX_TARGETS_LIMIT

log = logging.getLogger(__name__)

# scene ints[] slots
S_MAX_TARGETS, S_EXTRA_MIN, S_KEEP_BEST = range(3)
# scene floats[] slots
S_MAX_COST, S_SHARE_PENALTY, S_MISSING_SHIFT, S_SHARE_TOL, S_MIN_SEPARATION, S_DOUBLE_TOL = range(6)


@jit
def _hypotheses(choices, costs, n_echoes, scene_ints, scene_floats, out_matched, out_cost):
    """As ``SceneAssociator._joint`` after the pool (``choices``/``costs`` its cheapest
    first): the chosen combinations and their costs into ``out_*``; returns how many."""
    n, n_ch = choices.shape
    shifted = np.empty(n)
    n_used = np.empty(n, dtype=np.int64)
    for i in range(n):
        u = 0
        for c in range(n_ch):
            if choices[i, c] >= 0:
                u += 1
        n_used[i] = u
        shifted[i] = costs[i] + scene_floats[S_MISSING_SHIFT] * (n_ch - u)
    keep_best = scene_ints[S_KEEP_BEST] != 0
    first = 1 if keep_best else 0
    order = np.empty(n, dtype=np.int64)
    for i in range(min(first, n)):
        order[i] = i
    for i in range(first, n):  # a stable insertion sort by shifted cost (np.argsort "stable")
        j = i
        while j > first and shifted[order[j - 1]] > shifted[i]:
            order[j] = order[j - 1]
            j -= 1
        order[j] = i
    keep = np.empty(n, dtype=np.bool_)
    for r in range(n):
        keep[r] = n_used[order[r]] >= scene_ints[S_EXTRA_MIN] and not _is_variant(choices, order, r)
    keep[0] = True  # the K = 1 pick may use fewer channels
    m = 0
    for r in range(n):
        m += keep[r]
    kept = np.empty((m, n_ch), dtype=np.int64)
    kept_cost = np.empty(m)
    gains = np.empty(m)
    i = 0
    for r in range(n):
        if keep[r]:
            kept[i] = choices[order[r]]
            kept_cost[i] = shifted[order[r]]
            gains[i] = scene_floats[S_MAX_COST] - kept_cost[i]
            i += 1
    if keep_best:
        g = gains[0]
        gains[0] = (0.0 if g < 0.0 else g) + 1e6  # always chosen (Python's max(g, 0.0))
    chosen = np.empty(scene_ints[S_MAX_TARGETS], dtype=np.int64)
    n_chosen = _select_kernel(
        kept,
        gains,
        scene_ints[S_MAX_TARGETS],
        scene_floats[S_SHARE_PENALTY],
        MAX_NODES,
        n_echoes,
        chosen,
    )
    if n_chosen == 0:
        out_matched[0] = choices[0]
        out_cost[0] = costs[0]
        return 1
    for t in range(n_chosen):
        out_matched[t] = kept[chosen[t]]
        out_cost[t] = kept_cost[chosen[t]]
    return n_chosen


@jit
def _is_variant(choices, order, r):
    """As ``joint.drop_variants`` on the reordered choices: row r is dropped when a later
    row agrees with it on every echo r uses."""
    n, n_ch = choices.shape
    a = order[r]
    for i in range(r + 1, n):
        b = order[i]
        agree = True
        for c in range(n_ch):
            if not (choices[a, c] < 0 or choices[b, c] == choices[a, c]):
                agree = False
                break
        if agree:
            return True
    return False


@jit
def _share(matched, pred, paths, taken, listening, tolerance, out):
    """As ``scene.shared_echoes``: ``matched`` plus the nearest taken echo on each listening
    channel it leaves out, within tolerance, into ``out``; True when that changed anything."""
    changed = False
    for c in range(matched.shape[0]):
        out[c] = matched[c]
        if matched[c] >= 0 or not listening[c]:
            continue
        best, best_err = -1, math.inf
        for k in range(paths.shape[1]):
            if taken[c, k] and math.isfinite(paths[c, k]):
                err = abs(paths[c, k] - pred[c])
                if err < best_err:
                    best, best_err = k, err
        if best >= 0 and best_err <= tolerance:
            out[c] = best
            changed = True
    return changed


@jit
def _double_reflection(paths, other_paths, other_position, emitter, facing, tolerance):
    """As ``scene.is_double_reflection``."""
    height = height3(other_position, emitter, facing)
    n_used = 0
    for c in range(paths.shape[0]):
        if math.isfinite(paths[c]) and math.isfinite(other_paths[c]):
            n_used += 1
    if n_used < 3 or height <= 0:
        return False
    for c in range(paths.shape[0]):
        both = math.isfinite(paths[c]) and math.isfinite(other_paths[c])
        if both and not abs(paths[c] - (other_paths[c] + 2.0 * height)) <= tolerance:
            return False
    return True


# The constant arguments after ``ints`` (back.kernel_arguments' order, then the scene's
# ints, floats and listening mask (empty for one target), then the front kernel's scalars,
# front.front_packed), each in one of four buffers by dtype; the kernels take views of them
# (numba's call costs about 65 ns per array argument: 45 arguments took 3 us).
_SLOTS = (
    "floats", "quality", "assoc_delays", "listening", "max_path_diff", "anchors",
    "cost_weights", "delays", "channels", "emitter", "facing", "mean", "std", "w0", "b0",
    "w1", "b1", "w2", "b2", "wh", "bh", "feature", "threshold", "value", "base",
    "scene_ints", "scene_floats", "share_listening", "front_ints", "front_floats",
)  # fmt: skip
(
    L_FLOATS, L_QUALITY, L_ASSOC_DELAYS, L_LISTENING, L_MAX_DIFF, L_ANCHORS, L_COST_WEIGHTS,
    L_DELAYS, L_CHANNELS, L_EMITTER, L_FACING, L_MEAN, L_STD, L_W0, L_B0, L_W1, L_B1, L_W2,
    L_B2, L_WH, L_BH, L_FEATURE, L_THRESHOLD, L_VALUE, L_BASE, L_SCENE_INTS, L_SCENE_FLOATS,
    L_SHARE_LISTENING, L_FRONT_INTS, L_FRONT_FLOATS,
) = range(len(_SLOTS))  # fmt: skip
_BUFFERS = (np.float64, np.float32, np.int64, np.bool_)
_F64, _F32, _I64, _FLAGS = range(4)
# the buffer (dtype) each slot's array is read from in the back kernels (_back_views, ...)
_KINDS = (
    _F64, _F64, _F64, _FLAGS, _F64, _I64, _F64, _F64, _F64, _F64, _F64, _F32, _F32, _F32,
    _F32, _F32, _F32, _F32, _F32, _F32, _F32, _I64, _F32, _F32, _F64, _I64, _F64, _FLAGS,
    _I64, _F64,
)  # fmt: skip


def pack_config(args: tuple) -> tuple | None:
    """``(ints, f64, f32, i64, flags, layout)`` from a back kernel's unpacked constant
    arguments (``ints`` first, then :data:`_SLOTS`): every array's
    values in the buffer of its dtype, ``layout[3 * slot : 3 * slot + 3]`` its offset there
    and its (at most two) dimensions. None (the staged steps) when an array does not have
    the dtype the kernel reads it as: values are never converted."""
    ints, rest = args[0], args[1:]
    if len(rest) != len(_SLOTS):
        raise ValueError(f"expected {len(_SLOTS) + 1} kernel arguments, got {len(args)}")
    parts: list[list[np.ndarray]] = [[] for _ in _BUFFERS]
    sizes = [0] * len(_BUFFERS)
    layout = np.zeros(3 * len(_SLOTS), dtype=np.int64)
    for slot, value in enumerate(rest):
        a = np.asarray(value)
        kind = _KINDS[slot]
        if a.dtype != _BUFFERS[kind] or a.ndim > 2:
            log.debug("back kernel off: %s is %s %dd", _SLOTS[slot], a.dtype, a.ndim)
            return None
        shape = (*a.shape, 1, 1)[:2] if a.ndim else (1, 1)
        layout[3 * slot : 3 * slot + 3] = (sizes[kind], *shape)
        parts[kind].append(a.ravel())
        sizes[kind] += a.size
    buffers = [
        np.ascontiguousarray(np.concatenate(p) if p else np.zeros(0), dtype=t)
        for p, t in zip(parts, _BUFFERS, strict=True)
    ]
    return (ints, *buffers, layout)


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


@jit(inline="always")
def _v1(buf, layout, slot):
    o = layout[3 * slot]
    return buf[o : o + layout[3 * slot + 1]]


@jit(inline="always")
def _v2(buf, layout, slot):
    o, d0, d1 = layout[3 * slot], layout[3 * slot + 1], layout[3 * slot + 2]
    return buf[o : o + d0 * d1].reshape((d0, d1))


@jit(inline="always")
def _back_views(f64, f32, i64, flags, layout):
    """The packed constants one by one, in ``back._back_steps``' order (``floats`` ..
    ``base``: :data:`_SLOTS` up to ``base``), as both back kernels pass them on."""
    return (
        _v1(f64, layout, L_FLOATS), _v1(f64, layout, L_QUALITY),
        _v1(f64, layout, L_ASSOC_DELAYS), _v1(flags, layout, L_LISTENING),
        _v2(f64, layout, L_MAX_DIFF), _v2(i64, layout, L_ANCHORS),
        _v1(f64, layout, L_COST_WEIGHTS), _v1(f64, layout, L_DELAYS),
        _v2(f64, layout, L_CHANNELS), _v1(f64, layout, L_EMITTER), _v1(f64, layout, L_FACING),
        _v1(f32, layout, L_MEAN), _v1(f32, layout, L_STD), _v2(f32, layout, L_W0),
        _v1(f32, layout, L_B0), _v2(f32, layout, L_W1), _v1(f32, layout, L_B1),
        _v2(f32, layout, L_W2), _v1(f32, layout, L_B2), _v2(f32, layout, L_WH),
        _v1(f32, layout, L_BH), _v2(i64, layout, L_FEATURE), _v2(f32, layout, L_THRESHOLD),
        _v2(f32, layout, L_VALUE), f64[layout[3 * L_BASE]],
    )  # fmt: skip


@jit(inline="always")
def _scene_views(f64, i64, flags, layout):
    """The scene's ints, floats and listening mask (empty for one target)."""
    return (
        _v1(i64, layout, L_SCENE_INTS),
        _v1(f64, layout, L_SCENE_FLOATS),
        _v1(flags, layout, L_SHARE_LISTENING),
    )


@jit(inline="always")
def _front_views(f64, i64, layout):
    """The front kernel's packed scalars (``front.front_packed``): (ints, floats)."""
    return _v1(i64, layout, L_FRONT_INTS), _v1(f64, layout, L_FRONT_FLOATS)
