"""Tracking on the virtual board's moving targets: coverage, id switches, tracked vs
per-acquisition error (``python -m tools.bench.track_movers``).

Per acquisition after ``warmup`` acquisitions, the true targets are matched one-to-one to the
confirmed tracks (and, separately, to the acquisition's targets) by the least total distance,
pairs farther than ``cover_mm`` left out. A true target is covered when it has a track; an id
switch is a covered target whose track id differs from the one it last had.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from spiel_edge.link.sim_options import SimOptions
from spiel_edge.pipeline.staged import Pipeline, Target
from spiel_edge.runtime.static_scene import RunningBackground
from spiel_edge.runtime.track_records import ResultTracker
from spiel_edge.sim.scenes import build_scene
from spiel_edge.track.assign import INFEASIBLE, assign

COVER_MM = 40.0


def match(truth: np.ndarray, points: np.ndarray, cover_mm: float = COVER_MM) -> np.ndarray:
    """Per true target the index of its point, or -1."""
    if not len(truth) or not len(points):
        return np.full(len(truth), -1, dtype=np.int64)
    dist = np.linalg.norm(truth[:, None, :] - points[None, :, :], axis=2)
    return assign(np.where(dist <= cover_mm, dist, INFEASIBLE))


@dataclass
class MoverScore:
    warmup: int = 20
    cover_mm: float = COVER_MM
    acquisitions: int = 0
    covered: list[int] = field(default_factory=list)  # per true target
    found: list[int] = field(default_factory=list)  # per true target, by a per-acquisition target
    switches: int = 0
    tracked_errors: list[float] = field(default_factory=list)
    raw_errors: list[float] = field(default_factory=list)
    paired: list[tuple[float, float]] = field(default_factory=list)  # (tracked, raw), both found
    _last_ids: list[int | None] = field(default_factory=list)

    def add(self, index: int, truth: np.ndarray, tracks, target_positions: np.ndarray) -> None:
        if index < self.warmup:
            return
        if not self.covered:
            self.covered, self.found = [0] * len(truth), [0] * len(truth)
            self._last_ids = [None] * len(truth)
        self.acquisitions += 1
        track_pos = np.array([t.position_mm for t in tracks]).reshape(-1, 3)
        tracked = np.full(len(truth), np.nan)
        for i, k in enumerate(match(truth, track_pos, self.cover_mm)):
            if k < 0:
                continue
            self.covered[i] += 1
            tracked[i] = float(np.linalg.norm(track_pos[k] - truth[i]))
            self.tracked_errors.append(tracked[i])
            track_id = tracks[k].track_id
            self.switches += self._last_ids[i] is not None and self._last_ids[i] != track_id
            self._last_ids[i] = track_id
        for i, k in enumerate(match(truth, target_positions, self.cover_mm)):
            if k >= 0:
                self.found[i] += 1
                self.raw_errors.append(float(np.linalg.norm(target_positions[k] - truth[i])))
                if np.isfinite(tracked[i]):
                    self.paired.append((float(tracked[i]), self.raw_errors[-1]))

    def summary(self) -> dict:
        n = max(self.acquisitions, 1)
        return {
            "acquisitions_scored": self.acquisitions,
            "coverage_per_target": [round(c / n, 4) for c in self.covered],
            "min_coverage": round(min(self.covered, default=0) / n, 4),
            "per_acquisition_recall_per_target": [round(c / n, 4) for c in self.found],
            "id_switches": int(self.switches),
            "tracked_mean_mm": _mean(self.tracked_errors),
            "per_acquisition_mean_mm": _mean(self.raw_errors),
            # the same target-acquisitions (a track and a target within cover_mm): the tracked
            # figures above also count acquisitions where only the track covers the target
            "paired_acquisitions": len(self.paired),
            "paired_tracked_mean_mm": _mean([t for t, _ in self.paired]),
            "paired_per_acquisition_mean_mm": _mean([r for _, r in self.paired]),
        }


def run_movers(
    pipeline: Pipeline,
    url: str,
    acquisitions: int = 1000,
    rate_hz: float = 50.0,
    warmup: int = 20,
    oracle_sigma_mm: float | None = None,
    background: str = "scene",
) -> dict:
    """Replay the virtual board's scene of ``url`` (model scene with movers) at ``rate_hz``.
    With ``oracle_sigma_mm`` the targets are the truths plus Gaussian noise of that std (each
    missed with probability 0.05) instead of the pipeline's: the tracker alone.
    ``background``: "scene" (the scene's own target-free background, as a capture), "none"
    (the profile's stand-in) or "running" (runtime/static_scene.py, with the profile's
    window, 16 when it is off)."""
    rng = np.random.default_rng(0)
    options = SimOptions.from_url(url)
    scene = build_scene(options)
    tracker = ResultTracker(pipeline.profile.track, pipeline.profile.scene)
    score = MoverScore(warmup=warmup)
    n_samples = pipeline.profile.acquisition.n_samples
    running = _running(pipeline.profile) if background == "running" else None
    targets_seen = 0
    for k in range(acquisitions):
        t = k / rate_hz
        frame = scene.frame(k, n_samples, t)
        samples = frame.samples.astype(np.float64)
        if background == "scene":
            used = frame.background.astype(np.float64)
        else:
            used = running.background() if running is not None else None
        result = pipeline.process(samples, used)
        if oracle_sigma_mm is not None:
            result.targets = _oracle_targets(frame.truth_targets_mm, oracle_sigma_mm, rng)
        captured = used is not None and pipeline.profile.preprocess.background_subtraction
        if oracle_sigma_mm is not None:
            captured = None  # the oracle's covariance is its own noise, not the pipeline's
        tracks = tracker.update(result, t, captured)
        if running is not None:
            running.update(samples, tracks)
        positions = np.array([tg.position_mm for tg in tracker.last_targets]).reshape(-1, 3)
        targets_seen += len(positions)
        score.add(k, frame.truth_targets_mm, tracks, positions)
    return {
        "url": url,
        "acquisitions": acquisitions,
        "rate_hz": rate_hz,
        "targets": "pipeline" if oracle_sigma_mm is None else f"truth + {oracle_sigma_mm} mm noise",
        "background": background,
        "mean_targets_per_acquisition": round(targets_seen / max(acquisitions, 1), 3),
        **score.summary(),
    }


def _running(profile) -> RunningBackground:
    spec = profile.track
    if spec.running_background_window <= 0:
        profile = profile.replace(track=replace(spec, running_background_window=16))
    return RunningBackground.from_profile(profile)


def _oracle_targets(truth: np.ndarray, sigma: float, rng: np.random.Generator) -> list[Target]:
    cov = np.eye(3) * sigma**2
    return [
        Target(p + rng.normal(0.0, sigma, 3), cov, 0.0, [], 1.0)
        for p in truth
        if rng.random() >= 0.05
    ]


def _mean(values: list[float]) -> float | None:
    return round(float(np.mean(values)), 2) if values else None
