"""Stage 5, associate: pick one echo per channel (or none) that all come from the target.

Every associator has the same interface: ``associator(features, counts) -> matched``, where
``features`` is (channels, max_echoes, 8) from :mod:`features`, ``counts`` the echoes per
channel and ``matched`` an int64 (channels,) index into each channel's echoes, -1 for none.

The geometric associator searches the combinations depth-first. Two paths that share the
emitter can differ by at most the distance between their receivers
(| |p - r_i| - |p - r_j| | <= |r_i - r_j|), which prunes almost every combination before any
solve; the survivors are located and scored by

    cost = rms residual + missing_penalty * channels left out
           - strength_weight * mean log(alpha) + range_weight * range

so that, among consistent combinations, strong and near echoes win over weak ones and over
multiple reflections (which arrive later, at about twice the path, and are also consistent). Up to EXHAUSTIVE_MAX_CHANNELS listening channels the search is exhaustive (optimal). Larger
arrays use hypothesise-and-verify, linear in the channel count: every feasible echo triple of
a few well-spread anchor channels gives a position, which predicts every other channel's echo
path; the nearest echo within the tolerance joins, and the joined set is solved and scored.
The learned associator (``associate_onnx``) plugs into the same interface.
"""

from __future__ import annotations

import math

import numpy as np

from spiel_edge._jit import jit
from spiel_edge.errors import InputError
from spiel_edge.pipeline.stages.features import TOA_COLUMN
from spiel_edge.pipeline.stages.locate import locate_kernel
from spiel_edge.profile.schema import Profile

EXHAUSTIVE_MAX_CHANNELS = 6
MAX_SOLVES = 4096  # bound on located combinations per acquisition: time stays bounded in clutter
MAX_ANCHOR_TRIPLES = 3
MAX_POOL = 48  # echo combinations the scene's joint choice keeps (stages/joint.py)
LOCATE_ITER = 20  # Gauss-Newton iterations per candidate (passed as int(): one signature)


def anchor_triples(channels: np.ndarray, emitter: np.ndarray, listening: np.ndarray) -> np.ndarray:
    """Up to MAX_ANCHOR_TRIPLES disjoint channel triples with wide baselines: the first starts
    at the channel nearest the emitter (its range is the most direct), the rest greedily."""
    free = [int(c) for c in listening]
    triples = []
    while len(free) >= 3 and len(triples) < MAX_ANCHOR_TRIPLES:
        first = min(free, key=lambda c: np.linalg.norm(channels[c] - emitter))
        rest = [c for c in free if c != first]
        best = max(
            ((b, c) for i, b in enumerate(rest) for c in rest[i + 1 :]),
            key=lambda bc: np.linalg.norm(
                np.cross(channels[bc[0]] - channels[first], channels[bc[1]] - channels[first])
            ),
        )
        triples.append((first, *best))
        free = [c for c in free if c not in (first, *best)]
    return np.array(triples, dtype=np.int64)


class GeometricAssociator:
    """Association by feasible path differences and the ellipsoid intersection residual."""

    name = "geometric"

    def __init__(self, profile: Profile):
        g = profile.geometry
        self.channels = np.ascontiguousarray(g.channels_mm, dtype=np.float64)
        self.emitter = np.ascontiguousarray(g.emitter_mm, dtype=np.float64)
        self.facing = np.ascontiguousarray(g.facing, dtype=np.float64)
        self.listening = np.ascontiguousarray(g.listening_mask(), dtype=np.bool_)
        self.delays = np.ascontiguousarray(g.delays(), dtype=np.float64)
        self.mm_per_sample = profile.mm_per_sample
        s = profile.associate
        self.tolerance_mm = s.tolerance_mm
        self.max_residual_mm = s.max_residual_mm
        self.missing_penalty_mm = s.missing_penalty_mm
        self.min_channels = s.min_channels
        self.strength_weight_mm = s.strength_weight_mm
        self.range_weight = s.range_weight
        diff = self.channels[:, None, :] - self.channels[None, :, :]
        self.max_path_diff = np.ascontiguousarray(np.sqrt((diff**2).sum(-1)) + self.tolerance_mm)
        listening = np.flatnonzero(self.listening)
        self.anchors = (
            None
            if len(listening) <= EXHAUSTIVE_MAX_CHANNELS
            else anchor_triples(self.channels, self.emitter, listening)
        )

    def paths_mm(self, features: np.ndarray) -> np.ndarray:
        """Echo path length (mm) of every echo, after the per-channel delay."""
        return (features[:, :, TOA_COLUMN] - self.delays[:, None]) * self.mm_per_sample

    def __call__(self, features: np.ndarray, counts: np.ndarray) -> np.ndarray:
        return self.candidates(features, counts)[0]

    def candidates(
        self,
        features: np.ndarray,
        counts: np.ndarray,
        allowed: np.ndarray | None = None,
        bonus_mm: np.ndarray | None = None,
        min_channels: int | None = None,
    ):
        """Best combination as ``(matched, cost)``; ``allowed`` (channels, max_echoes) bool
        restricts the search, ``bonus_mm`` (channels, max_echoes) lowers the cost of
        combinations by the mean bonus of their echoes (both used by the learned associator);
        ``min_channels`` overrides the profile's (the scene stage asks more of extra targets)."""
        args = self.search_inputs(features, counts, allowed, bonus_mm, min_channels)
        matched = np.full(self.channels.shape[0], -1, dtype=np.int64)
        if self.anchors is None:
            cost = exhaustive_kernel(*args, matched)
        else:
            cost = hypothesis_kernel(*args, matched, self.anchors)
        return matched, cost

    def pool(
        self, features: np.ndarray, counts: np.ndarray, bonus_mm=None, max_pool: int = MAX_POOL
    ):
        """``(choices (n, channels) int64, costs (n,))``: the ``max_pool`` cheapest consistent
        combinations of the exhaustive search (up to EXHAUSTIVE_MAX_CHANNELS listening
        channels), cheapest first; the first is :meth:`candidates`' pick."""
        if max_pool < 1:
            raise InputError(f"max_pool must be >= 1, got {max_pool}")
        args = self.search_inputs(features, counts, None, bonus_mm, None)
        choices = np.full((max_pool, self.channels.shape[0]), -1, dtype=np.int64)
        costs = np.full(max_pool, np.inf)
        n = search_kernel(*args, choices, costs)
        return choices[:n], costs[:n]

    def search_inputs(self, features, counts, allowed=None, bonus_mm=None, min_channels=None):
        """The search kernels' arguments before their outputs: paths, strengths, counts,
        allowed echoes, the geometry, the cost weights and the minimum channel count."""
        features = np.asarray(features, dtype=np.float64)
        counts = np.ascontiguousarray(counts, dtype=np.int64)
        if (
            features.ndim != 3
            or features.shape[0] != self.channels.shape[0]
            or counts.shape != features.shape[:1]
        ):
            raise InputError(
                f"features must be ({self.channels.shape[0]}, max_echoes, 8) and counts ({self.channels.shape[0]},)"
            )
        paths = np.ascontiguousarray(self.paths_mm(features))
        if allowed is None:
            allowed = np.isfinite(paths)
        allowed = np.ascontiguousarray(allowed & np.isfinite(paths), dtype=np.bool_)
        alpha = features[:, :, 0]
        strength = self.strength_weight_mm * np.log(
            np.where(np.isfinite(alpha) & (alpha > 1.0), alpha, 1.0)
        )
        if bonus_mm is not None:
            strength = strength + np.where(np.isfinite(bonus_mm), bonus_mm, 0.0)
        strength = np.ascontiguousarray(strength, dtype=np.float64)
        return (
            paths,
            strength,
            counts,
            allowed,
            self.listening,
            self.channels,
            self.emitter,
            self.facing,
            self.max_path_diff,
            self.cost_weights(),
            self.min_channels if min_channels is None else max(3, int(min_channels)),
        )

    def kernel_constants(self) -> dict:
        """This associator's constants for the compiled path (``pipeline/compiled/abi.py``):
        the search's, without a score prior."""
        anchors = self.anchors if self.anchors is not None else np.zeros((0, 3), np.int64)
        return {
            "min_channels": self.min_channels,
            "exhaustive": self.anchors is None,
            "mm_per_sample": self.mm_per_sample,
            "strength": self.strength_weight_mm,
            "prior": "none",
            "score_weight": 0.0,
            "assoc_delays": self.delays,
            "listening": self.listening,
            "max_path_diff": self.max_path_diff,
            "anchors": anchors,
            "cost_weights": self.cost_weights(),
        }

    def cost_weights(self) -> np.ndarray:
        """The cost's weights as the kernels take them: (max residual, missing-channel
        penalty, strength scale, range weight)."""
        return np.array([self.max_residual_mm, self.missing_penalty_mm, 1.0, self.range_weight])


@jit
def _score(choice, paths, strength, use, d, unit, e, ch, facing, weights, pos):
    """Locate the chosen echoes; cost as in the module docstring, inf when infeasible."""
    max_res, penalty, strength_weight, range_weight = weights[0], weights[1], weights[2], weights[3]
    n_ch = paths.shape[0]
    n_used = 0
    mean_strength = 0.0
    for j in range(n_ch):
        use[j] = choice[j] >= 0
        d[j] = paths[j, choice[j]] if choice[j] >= 0 else 0.0
        if use[j]:
            n_used += 1
            mean_strength += strength[j, choice[j]]
    ok, rms = locate_kernel(d, use, unit, e, ch, facing, int(LOCATE_ITER), pos)
    if not ok or rms > max_res:
        return math.inf
    distance = math.sqrt((pos[0] - e[0]) ** 2 + (pos[1] - e[1]) ** 2 + (pos[2] - e[2]) ** 2)
    return (
        rms
        + penalty * (n_ch - n_used)
        - strength_weight * mean_strength / n_used
        + range_weight * distance
    )


@jit
def _feasible(paths, choice, c, k, max_diff):
    for j in range(c):
        if choice[j] >= 0 and abs(paths[c, k] - paths[j, choice[j]]) > max_diff[c, j]:
            return False
    return True


@jit
def exhaustive_kernel(
    paths, strength, counts, allowed, listening, ch, e, facing, max_diff, weights, min_ch, best
):
    """The best combination into ``best`` (untouched when none is consistent): its cost,
    inf when none."""
    costs = np.full(1, math.inf)
    search_kernel(
        paths, strength, counts, allowed, listening, ch, e, facing, max_diff, weights, min_ch,
        best.reshape((1, best.shape[0])), costs,
    )  # fmt: skip
    return costs[0]


@jit
def search_kernel(
    paths,
    strength,
    counts,
    allowed,
    listening,
    ch,
    e,
    facing,
    max_diff,
    weights,
    min_ch,
    out_choices,
    out_costs,
):
    """The depth-first search over echo combinations, the one both the associator (keeping
    the best: one row) and the scene's joint choice (keeping a pool: MAX_POOL rows)
    run: the cheapest combinations by sorted insertion into ``out_*``, the first found first
    among equal costs; returns how many are kept. At most MAX_SOLVES combinations located."""
    n_ch = paths.shape[0]
    cap = out_costs.shape[0]
    choice = np.full(n_ch, -1, dtype=np.int64)
    d = np.empty(n_ch)
    use = np.zeros(n_ch, dtype=np.bool_)
    unit = np.ones(n_ch)  # the search weighs every channel alike
    pos = np.empty(3)
    kept = 0
    solves = 0
    # iterative depth-first search: choice[c] runs over -1 (no echo), 0 .. counts[c] - 1
    c = int(0)  # noqa: UP018 (an int64, not Literal[int]: one compiled signature)
    choice[0] = -2
    while c >= 0 and solves < MAX_SOLVES:
        choice[c] += 1
        if choice[c] >= counts[c] or (choice[c] >= 0 and not listening[c]):
            choice[c] = -2
            c -= 1
            continue
        k = choice[c]
        if k >= 0 and not (allowed[c, k] and _feasible(paths, choice, c, k, max_diff)):
            continue
        n_used = 0
        for j in range(c + 1):
            if choice[j] >= 0:
                n_used += 1
        if n_used + (n_ch - c - 1) < min_ch:
            continue  # too few channels left to reach min_ch
        if c < n_ch - 1:
            c += 1
            choice[c] = -2
            continue
        solves += 1
        cost = _score(choice, paths, strength, use, d, unit, e, ch, facing, weights, pos)
        if not cost < math.inf or (kept == cap and cost >= out_costs[cap - 1]):
            continue
        # strict '<': among equal costs the first found stays first
        i = kept if kept < cap else cap - 1
        while i > 0 and cost < out_costs[i - 1]:
            out_costs[i] = out_costs[i - 1]
            out_choices[i, :] = out_choices[i - 1, :]
            i -= 1
        out_costs[i] = cost
        out_choices[i, :] = choice
        if kept < cap:
            kept += 1
    return kept


@jit
def _join_predicted(paths, counts, allowed, listening, ch, e, pos, gate, choice):
    """Give every channel the echo nearest the path the position predicts (within gate)."""
    n_used = 0
    for j in range(paths.shape[0]):
        choice[j] = -1
        if not listening[j]:
            continue
        pred = math.sqrt(
            (pos[0] - e[0]) ** 2 + (pos[1] - e[1]) ** 2 + (pos[2] - e[2]) ** 2
        ) + math.sqrt(
            (pos[0] - ch[j, 0]) ** 2 + (pos[1] - ch[j, 1]) ** 2 + (pos[2] - ch[j, 2]) ** 2
        )
        best_err = gate
        for k in range(counts[j]):
            err = abs(paths[j, k] - pred)
            if allowed[j, k] and err <= best_err:
                best_err = err
                choice[j] = k
        if choice[j] >= 0:
            n_used += 1
    return n_used


@jit
def hypothesis_kernel(
    paths,
    strength,
    counts,
    allowed,
    listening,
    ch,
    e,
    facing,
    max_diff,
    weights,
    min_ch,
    best,
    anchors,
):
    n_ch = paths.shape[0]
    gate = max_diff[0, 0]  # the tolerance: the diagonal holds |r_i - r_i| + tolerance
    unit = np.ones(n_ch)
    choice = np.full(n_ch, -1, dtype=np.int64)
    d = np.zeros(n_ch)
    use = np.zeros(n_ch, dtype=np.bool_)
    pos = np.empty(3)
    best_cost = math.inf
    solves = 0
    for t in range(anchors.shape[0]):
        a, b, c = anchors[t, 0], anchors[t, 1], anchors[t, 2]
        for ka in range(counts[a]):
            for kb in range(counts[b]):
                if (
                    not (allowed[a, ka] and allowed[b, kb])
                    or abs(paths[a, ka] - paths[b, kb]) > max_diff[a, b]
                ):
                    continue
                for kc in range(counts[c]):
                    if (
                        not allowed[c, kc]
                        or abs(paths[c, kc] - paths[a, ka]) > max_diff[c, a]
                        or abs(paths[c, kc] - paths[b, kb]) > max_diff[c, b]
                    ):
                        continue
                    if solves >= MAX_SOLVES:
                        return best_cost
                    solves += 1
                    use[:] = False
                    use[a] = use[b] = use[c] = True
                    d[a], d[b], d[c] = paths[a, ka], paths[b, kb], paths[c, kc]
                    ok, rms = locate_kernel(d, use, unit, e, ch, facing, int(LOCATE_ITER), pos)
                    if not ok:
                        continue
                    if (
                        _join_predicted(paths, counts, allowed, listening, ch, e, pos, gate, choice)
                        < min_ch
                    ):
                        continue
                    cost = _score(
                        choice, paths, strength, use, d, unit, e, ch, facing, weights, pos
                    )
                    if cost < best_cost:
                        best_cost = cost
                        best[:] = choice
    return best_cost
