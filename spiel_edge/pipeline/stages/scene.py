"""Scene stage: up to K targets per acquisition from one multi-hypothesis association.

``[scene] selection = "joint"`` (default): the set of targets is chosen jointly among the
cheapest consistent echo combinations (:mod:`spiel_edge.pipeline.stages.joint`). ``"greedy"``, and
the cases the joint search does not cover (more than 6 listening channels, the learned
associator's ``reference`` mode), hypothesise-and-verify greedily (docs/scene.md):

1. The best consistent echo combination (the associator's own search: geometric cost with the
   learned score prior when the model is loaded) is the first target, exactly as with K = 1.
2. Its echoes are removed and the search runs again on the rest; a combination becomes a
   further target while its cost (the associator's cost: rms residual + missing-channel
   penalty - strength and score bonus + range term, lower is better) is at most
   ``[scene] max_cost_mm`` and it uses at least ``extra_min_channels`` channels (on
   spiel-icra23 most 3-channel extra combinations are ghosts: 3 paths always intersect,
   while 4 must agree). At most K searches run, each bounded by the associator's
   MAX_SOLVES located combinations, so an acquisition with hundreds of echo candidates
   (``detect.max_echoes`` <= 16 per channel) costs at most K * MAX_SOLVES solves.
3. After locating (:func:`shared_echoes`): a target that lacks a channel takes an echo
   already used by another target when that echo lies within ``share_tolerance_mm`` of the
   path its position predicts: two targets at nearly one range on a channel share the echo.
4. :func:`is_double_reflection`: a target whose paths are another (nearer) target's paths
   plus twice that target's distance from the board plane (target -> board -> target) is that
   target's double reflection, not a target; it is dropped.
"""

from __future__ import annotations

import math

import numpy as np

from spiel_edge.pipeline.stages.associate import EXHAUSTIVE_MAX_CHANNELS
from spiel_edge.pipeline.stages.joint import combination_pool, drop_variants, select_subset
from spiel_edge.pipeline.stages.scene_geometry import height3, predicted_paths_kernel


class SceneAssociator:
    """``(features, counts) -> [(matched, cost), ...]``: best first, at most ``max_targets``."""

    def __init__(
        self,
        associator,
        max_targets: int,
        max_cost_mm: float,
        share_penalty_mm: float = 40.0,
        extra_min_channels: int = 3,
        selection: str = "joint",
        missing_penalty_mm: float | None = None,
        keep_best: bool = True,
    ):
        self.associator = associator
        self.geometric = getattr(associator, "geometric", associator)
        self.max_targets = int(max_targets)
        self.max_cost_mm = float(max_cost_mm)
        self.share_penalty_mm = float(share_penalty_mm)
        listening = getattr(self.geometric, "listening", None)
        n_listening = 3 if listening is None else int(np.sum(listening))
        self.extra_min_channels = max(3, min(int(extra_min_channels), n_listening))
        own = getattr(self.geometric, "missing_penalty_mm", 0.0)
        self.missing_shift_mm = 0.0 if missing_penalty_mm is None else missing_penalty_mm - own
        self.keep_best = bool(keep_best)
        self.joint = (
            selection == "joint"
            and hasattr(self.geometric, "candidates")
            and n_listening <= EXHAUSTIVE_MAX_CHANNELS
        )

    def kernel_constants(self) -> dict | None:
        """The compiled path's constants for this scene (``pipeline/compiled/abi.py``); None
        for several targets chosen greedily (then the staged path runs)."""
        if self.max_targets > 1 and not self.joint:
            return None
        return {
            "max_targets": self.max_targets,
            "extra_min": self.extra_min_channels,
            "keep_best": self.keep_best,
            "max_cost": self.max_cost_mm,
            "share_penalty": self.share_penalty_mm,
            "missing_shift": self.missing_shift_mm,
        }

    def _bonus(self, features: np.ndarray, counts: np.ndarray) -> np.ndarray | None:
        """The learned score prior as a per-echo cost bonus (None for geometric association)."""
        if not hasattr(self.associator, "bonus") or getattr(self.associator, "mode", "") != "prior":
            return None
        return self.associator.bonus(features, counts)

    def first(self, features: np.ndarray, counts: np.ndarray, bonus) -> tuple[np.ndarray, float]:
        if hasattr(self.associator, "candidates") or bonus is not None:
            return self.geometric.candidates(features, counts, bonus_mm=bonus)
        return np.asarray(self.associator(features, counts)), math.nan

    def __call__(self, features: np.ndarray, counts: np.ndarray):
        reference_mode = hasattr(self.associator, "bonus") and self.associator.mode != "prior"
        bonus = None if reference_mode else self._bonus(features, counts)
        if reference_mode:
            hyps = [(np.asarray(self.associator(features, counts)), math.nan)]
        elif self.joint and self.max_targets > 1:
            return self._joint(features, counts, bonus)  # its cheapest is the K = 1 pick
        else:
            hyps = [self.first(features, counts, bonus)]
        if (
            self.max_targets == 1
            or (hyps[0][0] < 0).all()
            or not hasattr(self.geometric, "candidates")
        ):
            return hyps
        used = np.zeros(np.shape(features)[:2], dtype=np.bool_)
        _mark(used, hyps[0][0])
        base = np.zeros(used.shape) if bonus is None else bonus
        for _ in range(self.max_targets - 1):
            # echoes already taken stay available (two targets at one range share an echo)
            # but cost share_penalty_mm each (spread over the combination's channels)
            matched, cost = self.geometric.candidates(
                features,
                counts,
                None,
                base - self.share_penalty_mm * used,
                min_channels=self.extra_min_channels,
            )
            if (
                not math.isfinite(cost)
                or cost > self.max_cost_mm
                or (matched < 0).all()
                or any((matched == m).all() for m, _ in hyps)
            ):
                break
            hyps.append((matched, cost))
            _mark(used, matched)
        return hyps

    def _joint(self, features, counts, bonus):
        """The subset of the cheapest combinations chosen jointly (module joint); the K = 1
        pick (the cheapest, found by the same search) alone when no combination is worth its
        birth cost."""
        choices, costs = combination_pool(self.geometric, features, counts, bonus)
        if len(costs) == 0:
            return [(np.full(len(counts), -1, dtype=np.int64), math.inf)]
        hyps = [(choices[0].copy(), float(costs[0]))]
        n_used = (choices >= 0).sum(axis=1)
        # the joint choice's own cost of a channel left out: one wrong echo should not buy a
        # target its fourth channel
        costs = costs + self.missing_shift_mm * (len(counts) - n_used)
        first = 1 if self.keep_best else 0  # the K = 1 pick stays first
        order = np.concatenate([np.arange(first), first + np.argsort(costs[first:], kind="stable")])
        choices, costs, n_used = choices[order], costs[order], n_used[order]
        keep = (n_used >= self.extra_min_channels) & drop_variants(choices)
        keep[:1] = True  # the K = 1 pick may use fewer channels, as before
        choices, costs = choices[keep], costs[keep]
        gains = self.max_cost_mm - costs
        if self.keep_best:
            gains[0] = max(gains[0], 0.0) + 1e6  # always chosen
        chosen = select_subset(choices, gains, self.max_targets, self.share_penalty_mm)
        if chosen.size == 0:
            return hyps
        return [(choices[i].copy(), float(costs[i])) for i in chosen]


def _mark(used: np.ndarray, matched: np.ndarray) -> None:
    for c, k in enumerate(matched):
        if k >= 0:
            used[c, k] = True


def predicted_paths(position_mm: np.ndarray, channels_mm: np.ndarray, emitter_mm: np.ndarray):
    """Echo path (mm) per channel of a point target (summed in a fixed order: scene_geometry)."""
    p = np.ascontiguousarray(position_mm, dtype=np.float64)
    ch = np.ascontiguousarray(channels_mm, dtype=np.float64)
    return predicted_paths_kernel(p, ch, np.ascontiguousarray(emitter_mm, dtype=np.float64))


def shared_echoes(
    matched: np.ndarray,
    position_mm: np.ndarray,
    paths_mm: np.ndarray,
    taken: np.ndarray,
    channels_mm: np.ndarray,
    emitter_mm: np.ndarray,
    listening: np.ndarray,
    tolerance_mm: float,
) -> np.ndarray:
    """``matched`` plus, on each listening channel it leaves out, the already taken echo
    (``taken`` (channels, max_echoes) bool) nearest the predicted path, if within tolerance."""
    out = np.array(matched, dtype=np.int64)
    pred = predicted_paths(position_mm, channels_mm, emitter_mm)
    for c in np.flatnonzero((out < 0) & listening):
        err = np.where(taken[c] & np.isfinite(paths_mm[c]), np.abs(paths_mm[c] - pred[c]), np.inf)
        k = int(np.argmin(err)) if err.size else -1
        if k >= 0 and err[k] <= tolerance_mm:
            out[c] = k
    return out


def is_double_reflection(
    paths_mm: np.ndarray,
    other_paths_mm: np.ndarray,
    other_position_mm: np.ndarray,
    emitter_mm: np.ndarray,
    facing: np.ndarray,
    tolerance_mm: float,
) -> bool:
    """True when every used path (finite entries of ``paths_mm``) is the other target's path
    plus twice its distance from the board plane, within ``tolerance_mm``."""
    height = float(
        height3(
            np.asarray(other_position_mm, dtype=np.float64),
            np.asarray(emitter_mm, dtype=np.float64),
            np.asarray(facing, dtype=np.float64),
        )
    )
    used = np.isfinite(paths_mm) & np.isfinite(other_paths_mm)
    if used.sum() < 3 or height <= 0:
        return False
    gap = paths_mm[used] - (other_paths_mm[used] + 2.0 * height)
    return bool(np.all(np.abs(gap) <= tolerance_mm))
