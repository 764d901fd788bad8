"""The several-target kernel's steps (several_targets.py), each as the staged function it
replaces computes it: the joint choice after the pool (``SceneAssociator._joint``), the
shared echoes (``scene.shared_echoes``) and the double-reflection test
(``scene.is_double_reflection``). Tested against those in tests/core/test_back_scene.py. One
target (``Pipeline._target``) is ``steps.one_target_kernel``, shared with the K = 1 kernel."""

from __future__ import annotations

import logging
import math

import numpy as np

from spiel_edge._jit import jit
from spiel_edge.pipeline.compiled.abi import (
    S_EXTRA_MIN,
    S_KEEP_BEST,
    S_MAX_COST,
    S_MAX_TARGETS,
    S_MISSING_SHIFT,
    S_SHARE_PENALTY,
)
from spiel_edge.pipeline.stages.joint import MAX_NODES, select_kernel
from spiel_edge.pipeline.stages.scene_geometry import height3

log = logging.getLogger(__name__)


@jit
def hypotheses(choices, costs, n_echoes, scene_ints, scene_floats, out_matched, out_cost):
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
    n_chosen = select_kernel(
        kept,
        gains,
        scene_ints[S_MAX_TARGETS],
        scene_floats[S_SHARE_PENALTY],
        int(MAX_NODES),  # an int64, not Literal[int]: one compiled signature
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
def share(matched, pred, paths, taken, listening, tolerance, out):
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
def double_reflection(paths, other_paths, other_position, emitter, facing, tolerance):
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
