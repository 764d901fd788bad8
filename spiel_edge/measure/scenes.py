"""Scene metrics per number of true targets, and the scene file ``evaluate`` reads.

Per acquisition the reported targets are matched one-to-one to the true targets, nearest
pair first, within MATCH_MM. Per number of true targets n:

- ``recall``: matched true targets / true targets; ``all_found``: acquisitions with every
  true target matched; ``precision``: matched reported targets / reported targets;
- ``mean_mm``: mean error of the matched targets; ``targets_per_frame``: reported targets;
- ``coverage``: share of matched targets whose truth lies in their reported 95 % ellipsoid
  (Mahalanobis^2 <= 7.815); ``coverage_best`` the same for the best target of every
  acquisition with one true target, matched or not (the headline calibration figure).

Scene file (``tools/train/build_scenes.py``): an ``.npz`` with ``frames`` (N, channels, samples),
``backgrounds`` (N, channels, samples; rows without a background are all NaN),
``truth_mm`` (N, max_targets, 3; NaN rows pad), ``names`` (N,) and ``split``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from spiel_edge.errors import InputError
from spiel_edge.pipeline.staged import Pipeline, Result
from spiel_edge.pipeline.stages.uncertainty import CHI2_95_3DOF, mahalanobis2

MATCH_MM = 30.0


def match_targets(truths: np.ndarray, found: np.ndarray, gate: float = MATCH_MM):
    """One-to-one (truth index, found index, distance) pairs, nearest first, within gate."""
    if len(truths) == 0 or len(found) == 0:
        return []
    d = np.linalg.norm(truths[:, None, :] - found[None, :, :], axis=2)
    pairs = []
    while True:
        i, j = np.unravel_index(int(np.argmin(d)), d.shape)
        if not d[i, j] <= gate:
            return pairs
        pairs.append((int(i), int(j), float(d[i, j])))
        d[i, :] = np.inf
        d[:, j] = np.inf


@dataclass
class _Group:
    frames: int = 0
    truths: int = 0
    reported: int = 0
    matched: int = 0
    all_found: int = 0
    errors: list = field(default_factory=list)
    inside: int = 0
    best_inside: int = 0
    best_total: int = 0


class SceneTally:
    """Accumulates the per-number-of-targets metrics."""

    def __init__(self):
        self.groups: dict[int, _Group] = {}

    def add(self, result: Result, truths: np.ndarray) -> None:
        truths = np.asarray(truths, dtype=np.float64).reshape(-1, 3)
        g = self.groups.setdefault(len(truths), _Group())
        found = np.array([t.position_mm for t in result.targets]).reshape(-1, 3)
        pairs = match_targets(truths, found)
        g.frames += 1
        g.truths += len(truths)
        g.reported += len(found)
        g.matched += len(pairs)
        g.all_found += len(pairs) == len(truths)
        for i, j, dist in pairs:
            g.errors.append(dist)
            cov = result.targets[j].covariance_mm2
            g.inside += mahalanobis2(found[j] - truths[i], cov) <= CHI2_95_3DOF
        if len(truths) == 1 and result.targets:
            best = result.targets[0]
            g.best_total += 1
            err = best.position_mm - truths[0]
            g.best_inside += mahalanobis2(err, best.covariance_mm2) <= CHI2_95_3DOF

    def summary(self) -> dict:
        out = {}
        for n, g in sorted(self.groups.items()):
            out[str(n)] = {
                "frames": g.frames,
                "recall": _ratio(g.matched, g.truths),
                "all_found": _ratio(g.all_found, g.frames),
                "precision": _ratio(g.matched, g.reported),
                "mean_mm": round(float(np.mean(g.errors)), 2) if g.errors else None,
                "targets_per_frame": _ratio(g.reported, g.frames),
                "coverage": _ratio(g.inside, g.matched),
                "coverage_best": _ratio(g.best_inside, g.best_total),
            }
        return out


def _ratio(a: float, b: float) -> float | None:
    return round(a / b, 4) if b else None


def load_scenes(path: str | Path) -> dict[str, np.ndarray]:
    from spiel_edge.safety.limits import load_npz_bounded

    data = load_npz_bounded(path, "scenes", text_ok=True)  # sizes before decompression
    try:
        scenes = {k: data[k] for k in ("frames", "backgrounds", "truth_mm", "names")}
        scenes["split"] = str(data["split"]) if "split" in data else "unknown"
    except KeyError as exc:
        raise InputError(f"{path}: not a scene file (no {exc} array)") from None
    n = len(scenes["frames"])
    if scenes["backgrounds"].shape != scenes["frames"].shape or len(scenes["truth_mm"]) != n:
        raise InputError(f"{path}: frames, backgrounds and truth_mm disagree in shape")
    return scenes


def evaluate_scenes(pipeline: Pipeline, path: str | Path) -> SceneTally:
    """Run the pipeline over a scene file; the tally per number of true targets."""
    s = load_scenes(path)
    tally = SceneTally()
    for frames, bg, truth in zip(s["frames"], s["backgrounds"], s["truth_mm"], strict=True):
        background = None if np.isnan(bg).all() else bg
        truths = truth[np.isfinite(truth).all(axis=1)]
        tally.add(pipeline.process(frames, background), truths)
    return tally
