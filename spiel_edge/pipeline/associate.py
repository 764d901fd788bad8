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
multiple reflections (which arrive later, at about twice the path, and are also consistent). The learned associator (``spiel_edge.association``) plugs into the same interface.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from spiel_edge.errors import InputError
from spiel_edge.pipeline.features import TOA_COLUMN
from spiel_edge.pipeline.locate import _locate_kernel
from spiel_edge.profile import Profile


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

    def paths_mm(self, features: np.ndarray) -> np.ndarray:
        """Echo path length (mm) of every echo, after the per-channel delay."""
        return (features[:, :, TOA_COLUMN] - self.delays[:, None]) * self.mm_per_sample

    def __call__(self, features: np.ndarray, counts: np.ndarray) -> np.ndarray:
        return self.candidates(features, counts)[0]

    def candidates(self, features: np.ndarray, counts: np.ndarray, allowed: np.ndarray | None = None):
        """Best combination as ``(matched, cost)``; ``allowed`` (channels, max_echoes) bool
        restricts the search (used by the learned associator as a feasibility guard)."""
        features = np.asarray(features, dtype=np.float64)
        counts = np.ascontiguousarray(counts, dtype=np.int64)
        if features.ndim != 3 or features.shape[0] != self.channels.shape[0] or counts.shape != features.shape[:1]:
            raise InputError(
                f"features must be ({self.channels.shape[0]}, max_echoes, 8) and counts ({self.channels.shape[0]},)"
            )
        paths = np.ascontiguousarray(self.paths_mm(features))
        if allowed is None:
            allowed = np.isfinite(paths)
        allowed = np.ascontiguousarray(allowed & np.isfinite(paths), dtype=np.bool_)
        alpha = features[:, :, 0]
        strength = np.ascontiguousarray(np.log(np.where(np.isfinite(alpha) & (alpha > 1.0), alpha, 1.0)))
        weights = np.array([self.max_residual_mm, self.missing_penalty_mm, self.strength_weight_mm, self.range_weight])
        matched = np.full(self.channels.shape[0], -1, dtype=np.int64)
        cost = _search_kernel(
            paths, strength, counts, allowed, self.listening, self.channels, self.emitter, self.facing,
            self.max_path_diff, weights, self.min_channels, matched,
        )
        return matched, cost


@njit(cache=True, nogil=True)
def _search_kernel(paths, strength, counts, allowed, listening, ch, e, facing, max_diff, weights, min_ch, best):
    max_res, penalty, strength_weight, range_weight = weights[0], weights[1], weights[2], weights[3]
    n_ch = paths.shape[0]
    choice = np.full(n_ch, -1, dtype=np.int64)
    d = np.empty(n_ch)
    use = np.zeros(n_ch, dtype=np.bool_)
    pos = np.empty(3)
    best_cost = math.inf
    # iterative depth-first search: choice[c] runs over -1 (no echo), 0 .. counts[c] - 1
    c = 0
    choice[0] = -2
    while c >= 0:
        choice[c] += 1
        if choice[c] >= counts[c] or (choice[c] >= 0 and not listening[c]):
            choice[c] = -2
            c -= 1
            continue
        k = choice[c]
        if k >= 0:
            if not allowed[c, k]:
                continue
            feasible = True
            for j in range(c):
                if choice[j] >= 0 and abs(paths[c, k] - paths[j, choice[j]]) > max_diff[c, j]:
                    feasible = False
                    break
            if not feasible:
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
        for j in range(n_ch):
            use[j] = choice[j] >= 0
            d[j] = paths[j, choice[j]] if choice[j] >= 0 else 0.0
        ok, rms = _locate_kernel(d, use, e, ch, facing, 20, pos)
        if not ok or rms > max_res:
            continue
        mean_strength = 0.0
        for j in range(n_ch):
            if choice[j] >= 0:
                mean_strength += strength[j, choice[j]]
        mean_strength /= n_used
        distance = math.sqrt((pos[0] - e[0]) ** 2 + (pos[1] - e[1]) ** 2 + (pos[2] - e[2]) ** 2)
        cost = rms + penalty * (n_ch - n_used) - strength_weight * mean_strength + range_weight * distance
        if cost < best_cost:
            best_cost = cost
            best[:] = choice
    return best_cost
