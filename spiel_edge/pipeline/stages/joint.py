"""Joint choice of the set of targets in one acquisition (``[scene] selection = "joint"``).

Instead of taking the best echo combination, removing it and searching again (greedy), the
scene stage

1. collects the ``MAX_POOL`` cheapest consistent echo combinations in ONE search
   (:func:`combination_pool`: the geometric associator's depth-first search and cost, with
   the learned score prior as a per-echo bonus, so the cheapest is exactly the K = 1 pick);
2. chooses the subset of at most K of them (:func:`select_subset`) that maximises

       sum over chosen (birth_cost_mm - cost)  -  share_penalty_mm * (echo uses beyond one)

   with exclusivity: an echo explains one target, and a second target using it pays the
   share penalty (two targets at nearly one range on a channel), a combination whose every
   echo is already used by chosen targets (a ghost: other targets' echoes that happen to
   intersect, or a sub-combination of a chosen one) is never chosen, and a target must be
   worth its birth cost. Exact branch and bound: combinations sorted by cost, the bound is
   the current value plus the best K - n remaining gains (penalties only subtract), so a
   branch is cut as soon as it cannot beat the best set found so far.

Bounds (an acquisition with hundreds of echo candidates): the pool search locates at most
the associator's MAX_SOLVES combinations, keeps at most MAX_POOL, and the subset search
visits at most MAX_NODES nodes (then it returns the best set found so far, which the
include-first order makes at least as good as a greedy pick). Arrays with more than
EXHAUSTIVE_MAX_CHANNELS listening channels, and the learned associator's ``reference``
mode, keep the greedy search.
"""

from __future__ import annotations

import numpy as np

from spiel_edge._jit import jit
from spiel_edge.errors import InputError
from spiel_edge.pipeline.stages.associate import MAX_POOL

MAX_NODES = 20000  # subset-search nodes per acquisition
ADD, REMOVE = 1, -1  # _apply's step, passed as int(): numba compiles int64, not Literal[int]


def combination_pool(associator, features, counts, bonus_mm=None, max_pool: int = MAX_POOL):
    """``(choices (n, channels) int64, costs (n,))``: the ``max_pool`` cheapest consistent
    combinations of ``associator`` (a GeometricAssociator with <= 6 listening channels),
    cheapest first, each using at least the associator's ``min_channels``."""
    return associator.pool(features, counts, bonus_mm, max_pool)


def drop_variants(choices: np.ndarray) -> np.ndarray:
    """Mask of the combinations to keep: one that agrees with a cheaper (earlier) one on
    every echo it uses is a variant of that target (a channel left out), not a target."""
    choices = np.asarray(choices)
    agree = (choices[None, :, :] < 0) | (choices[:, None, :] == choices[None, :, :])
    variant = np.tril(agree.all(axis=2), k=-1)  # [i, j]: j agrees with the cheaper i
    return ~variant.any(axis=0)


def select_subset(
    choices: np.ndarray,
    gains: np.ndarray,
    max_targets: int,
    share_penalty: float,
    max_nodes: int = MAX_NODES,
) -> np.ndarray:
    """Indices (ascending) of the subset of at most ``max_targets`` combinations maximising
    total gain minus ``share_penalty`` per extra use of an echo, where no chosen combination
    is made only of the other chosen ones' echoes (``-1`` entries: no echo on that channel).
    ``gains`` must be sorted in descending order. Empty when no gain is positive."""
    choices = np.ascontiguousarray(choices, dtype=np.int64)
    gains = np.ascontiguousarray(gains, dtype=np.float64)
    if choices.ndim != 2 or gains.shape != choices.shape[:1]:
        raise InputError("choices must be (n, channels) and gains (n,)")
    if not np.all(np.isfinite(gains)) or np.any(np.diff(gains) > 0):
        raise InputError("gains must be finite and sorted in descending order")
    if max_targets < 1 or max_nodes < 1 or not share_penalty >= 0:
        raise InputError("max_targets and max_nodes must be >= 1, share_penalty >= 0")
    n_echoes = int(choices.max()) + 1 if choices.size else 0
    out = np.empty(max_targets, dtype=np.int64)
    n = select_kernel(
        choices, gains, int(max_targets), float(share_penalty), int(max_nodes), n_echoes, out
    )
    return out[:n].copy()


@jit
def _added_penalty(choices, j, uses, share_penalty):
    """Share penalty of adding combination j; -1 when every echo of it is already used."""
    shared = 0
    n_used = 0
    for c in range(choices.shape[1]):
        k = choices[j, c]
        if k >= 0:
            n_used += 1
            if uses[c, k] > 0:
                shared += 1
    if shared == n_used:
        return -1.0
    return share_penalty * shared


@jit
def _covers_one(choices, stack, n, uses):
    """True when one of the first n chosen combinations has every echo used twice or more
    (it is made only of the other chosen ones' echoes)."""
    for t in range(n):
        i = stack[t]
        covered = True
        for c in range(choices.shape[1]):
            k = choices[i, c]
            if k >= 0 and uses[c, k] < 2:
                covered = False
                break
        if covered:
            return True
    return False


@jit
def _apply(choices, j, uses, step):
    for c in range(choices.shape[1]):
        k = choices[j, c]
        if k >= 0:
            uses[c, k] += step


@jit
def select_kernel(choices, gains, max_k, share_penalty, max_nodes, n_echoes, best):
    m = gains.shape[0]
    positive = np.zeros(m + 1)  # prefix sums of the positive gains (the bound)
    for i in range(m):
        positive[i + 1] = positive[i] + max(gains[i], 0.0)
    uses = np.zeros((choices.shape[1], max(n_echoes, 1)), dtype=np.int64)
    stack = np.empty(max_k, dtype=np.int64)
    values = np.zeros(max_k + 1)  # values[n]: objective of the first n on the stack
    best_value = 0.0
    n_best = 0
    n = int(0)  # noqa: UP018 (an int64, not Literal[int]: one compiled signature)
    start = 0
    nodes = 0
    while True:
        pushed = False
        if n < max_k:
            for j in range(start, m):
                nodes += 1
                if nodes > max_nodes:
                    return n_best
                bound = values[n] + positive[min(m, j + max_k - n)] - positive[j]
                if bound <= best_value:
                    break  # gains are sorted: no later j can do better either
                pen = _added_penalty(choices, j, uses, share_penalty)
                # a combination worth nothing when added is worth nothing in any superset
                # (later additions only raise its penalty): skip it
                if pen < 0 or gains[j] - pen <= 0:
                    continue
                _apply(choices, j, uses, int(ADD))
                if _covers_one(choices, stack, n, uses):
                    _apply(choices, j, uses, int(REMOVE))  # j would make a chosen one a ghost
                    continue
                stack[n] = j
                values[n + 1] = values[n] + gains[j] - pen
                n += 1
                if values[n] > best_value:
                    best_value = values[n]
                    n_best = n
                    best[:n] = stack[:n]
                start = j + 1
                pushed = True
                break
        if pushed:
            continue
        if n == 0:
            return n_best
        n -= 1
        _apply(choices, stack[n], uses, int(REMOVE))
        start = stack[n] + 1
