"""Measure the pipeline on labelled recordings: 3-D error, fix rate, association accuracy.

Association accuracy counts, over channels, how often the matched echo is the one nearest
the ground-truth echo time (the true path projected with the profile's geometry), with "no
echo" right when no detected echo lies within ``gt_tolerance`` samples of that time.
"""

from __future__ import annotations

import hashlib
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from spiel_edge.io.spiel_csv import iter_recordings, position_key, read_truth
from spiel_edge.pipeline.run import Pipeline, Result
from spiel_edge.profile import Profile

GT_TOLERANCE_SAMPLES = 1.5


def expected_toa(profile: Profile, position_mm: np.ndarray) -> np.ndarray:
    """Per-channel echo time (samples) of a point target at ``position_mm``."""
    g = profile.geometry
    p = np.asarray(position_mm, dtype=np.float64)
    path = np.linalg.norm(p - g.emitter_mm) + np.linalg.norm(p - g.channels_mm, axis=1)
    return path / profile.mm_per_sample + g.delays()


def truth_echo_indices(profile: Profile, result: Result, truth_mm: np.ndarray, tol: float = GT_TOLERANCE_SAMPLES) -> list[int | None]:
    """Per channel the index of the detected echo nearest the true echo time, if within tol."""
    t = expected_toa(profile, truth_mm)
    out: list[int | None] = []
    for c, echoes in enumerate(result.echoes):
        if not echoes:
            out.append(None)
            continue
        dist = np.abs(np.asarray(echoes) - t[c])
        k = int(np.argmin(dist))
        out.append(k if dist[k] <= tol else None)
    return out


@dataclass
class Evaluation:
    errors_mm: dict[float, list[float]] = field(default_factory=dict)  # by true z
    frames: dict[float, int] = field(default_factory=dict)
    fixes: dict[float, int] = field(default_factory=dict)
    seen3: dict[float, int] = field(default_factory=dict)  # frames where >= 3 channels see the target
    fixes_seen3: dict[float, int] = field(default_factory=dict)
    channels: int = 0
    channels_correct: int = 0
    failed: list[str] = field(default_factory=list)

    def add(self, profile: Profile, result: Result, truth: np.ndarray) -> None:
        z = float(truth[2])
        self.frames[z] = self.frames.get(z, 0) + 1
        gt = truth_echo_indices(profile, result, truth)
        listening = profile.geometry.listening_mask()
        seen = sum(1 for c, k in enumerate(gt) if k is not None and listening[c]) >= 3
        self.seen3[z] = self.seen3.get(z, 0) + seen
        for c in range(len(gt)):
            if listening[c]:
                self.channels += 1
                self.channels_correct += gt[c] == result.matched[c]
        if result.position_mm is not None:
            self.fixes[z] = self.fixes.get(z, 0) + 1
            self.fixes_seen3[z] = self.fixes_seen3.get(z, 0) + seen
            self.errors_mm.setdefault(z, []).append(float(np.linalg.norm(result.position_mm - truth)))

    def summary(self, max_z: float | None = None) -> dict:
        """Metrics over all heights (or those <= max_z), and per height."""
        def stats(zs: Iterable[float]) -> dict:
            zs = list(zs)
            errs = np.array([e for z in zs for e in self.errors_mm.get(z, [])])
            n = sum(self.frames.get(z, 0) for z in zs)
            seen = sum(self.seen3.get(z, 0) for z in zs)
            return {
                "frames": n,
                "fix_rate": round(sum(self.fixes.get(z, 0) for z in zs) / n, 4) if n else None,
                "fix_rate_seen3": round(sum(self.fixes_seen3.get(z, 0) for z in zs) / seen, 4) if seen else None,
                "mean_mm": round(float(errs.mean()), 2) if errs.size else None,
                "median_mm": round(float(np.median(errs)), 2) if errs.size else None,
                "p95_mm": round(float(np.percentile(errs, 95)), 2) if errs.size else None,
            }

        heights = sorted(self.frames)
        chosen = [z for z in heights if max_z is None or z <= max_z]
        return {
            **stats(chosen),
            "association_accuracy": round(self.channels_correct / self.channels, 4) if self.channels else None,
            "failed_inputs": len(self.failed),
            "by_height": {f"{z:g}": stats([z]) for z in heights},
        }


def split_by_position(names: Iterable[str], val_fraction: float = 0.3, salt: str = "spiel-edge") -> tuple[set, set]:
    """Deterministic train/validation split of (x, y) positions (every height of an xy goes to
    the same side, so validation positions are unseen laterally too)."""
    xys = sorted({position_key(n)[:2] for n in names if position_key(n)})
    def bucket(xy: tuple) -> float:
        h = hashlib.sha256(f"{salt}:{xy[0]:g}:{xy[1]:g}".encode()).digest()
        return int.from_bytes(h[:8], "little") / 2**64
    val = {xy for xy in xys if bucket(xy) < val_fraction}
    return set(xys) - val, val


def evaluate_folder(
    pipeline: Pipeline,
    folder: str | Path,
    background: str | Path | None = None,
    *,
    positions: set | None = None,
    exclude_z: Iterable[float] = (),
) -> Evaluation:
    """Replay a labelled spiel-csv folder; ``positions`` keeps only those (x, y) positions."""
    ev = Evaluation()
    skip_z = set(exclude_z)
    for rec in iter_recordings(folder, background):
        key = position_key(rec.source)
        if positions is not None and (key is None or key[:2] not in positions):
            continue
        truth = read_truth(Path(folder) / rec.source)
        if truth is None or float(truth[2]) in skip_z:
            continue
        if rec.error is not None:
            ev.failed.append(rec.error)
            continue
        ev.add(pipeline.profile, pipeline.process(rec.frames, rec.background), truth)
    return ev
