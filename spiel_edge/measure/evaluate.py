"""Measure the pipeline on labelled recordings: 3-D error, fix rate, association accuracy.

Association accuracy counts, over listening channels, how often the matched echo is the one
nearest the ground-truth echo time (the true path projected with the profile's geometry), with
"no echo" right when no detected echo lies within 1.5 samples of that time; F1 as in
:mod:`spiel_edge.measure.echo_labels`.
"""

from __future__ import annotations

import hashlib
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from spiel_edge.data import EXCLUDED_Z_MM
from spiel_edge.measure.echo_labels import (
    AssociationScore,
    expected_toa,
    label_echoes,
    score_association,
)
from spiel_edge.measure.scenes import SceneTally
from spiel_edge.pipeline.staged import Pipeline, Result
from spiel_edge.profile.schema import Profile
from spiel_edge.recordings.spiel_csv import frame_files, position_key, read_recording, read_truth
from spiel_edge.runtime.parallel import PipelineRecipe, replay_files
from spiel_edge.safety.limits import InputLimits


@dataclass
class Evaluation:
    errors_mm: dict[float, list[float]] = field(default_factory=dict)  # by true z
    frames: dict[float, int] = field(default_factory=dict)
    fixes: dict[float, int] = field(default_factory=dict)
    seen3: dict[float, int] = field(
        default_factory=dict
    )  # frames where >= 3 channels see the target
    fixes_seen3: dict[float, int] = field(default_factory=dict)
    association: AssociationScore = field(default_factory=AssociationScore)
    failed: list[str] = field(default_factory=list)
    scenes: SceneTally = field(default_factory=SceneTally)
    by_position: dict[tuple, list[float]] = field(default_factory=dict)  # (x, y, z): errors

    def add(self, profile: Profile, result: Result, truth: np.ndarray) -> None:
        z = float(truth[2])
        self.scenes.add(result, truth[None, :])
        self.frames[z] = self.frames.get(z, 0) + 1
        at = self.by_position.setdefault(tuple(round(float(v), 1) for v in truth), [])
        labels = label_echoes(result.features, result.counts, expected_toa(profile, truth))
        listening = profile.geometry.listening_mask()
        seen = int(((labels >= 0) & listening).sum()) >= 3
        self.seen3[z] = self.seen3.get(z, 0) + seen
        matched = np.array([-1 if m is None else m for m in result.matched])
        self.association = self.association + score_association(matched, labels, listening)
        if result.position_mm is not None:
            self.fixes[z] = self.fixes.get(z, 0) + 1
            self.fixes_seen3[z] = self.fixes_seen3.get(z, 0) + seen
            error = float(np.linalg.norm(result.position_mm - truth))
            self.errors_mm.setdefault(z, []).append(error)
            at.append(error)

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
                "fix_rate_seen3": round(sum(self.fixes_seen3.get(z, 0) for z in zs) / seen, 4)
                if seen
                else None,
                "mean_mm": round(float(errs.mean()), 2) if errs.size else None,
                "median_mm": round(float(np.median(errs)), 2) if errs.size else None,
                "p95_mm": round(float(np.percentile(errs, 95)), 2) if errs.size else None,
            }

        heights = sorted(self.frames)
        chosen = [z for z in heights if max_z is None or z <= max_z]
        return {
            **stats(chosen),
            "association_accuracy": round(self.association.accuracy, 4)
            if self.association.channels
            else None,
            "association_f1": round(self.association.f1, 4) if self.association.channels else None,
            "failed_inputs": len(self.failed),
            "by_targets": self.scenes.summary(),
            "by_height": {f"{z:g}": stats([z]) for z in heights},
        }


def split_by_position(
    names: Iterable[str], val_fraction: float = 0.3, salt: str = "spiel-edge"
) -> tuple[set, set]:
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
    exclude_z: Iterable[float] = EXCLUDED_Z_MM,
    jobs: int = 1,
    recipe: PipelineRecipe | None = None,
) -> Evaluation:
    """Replay a labelled spiel-csv folder; ``positions`` keeps only those (x, y) positions;
    heights in ``exclude_z`` (default: spiel-icra23's mislabelled z = 90 mm) are left out.
    With ``jobs`` > 1 and the pipeline's ``recipe``, the files go to worker processes
    (:mod:`spiel_edge.runtime.parallel`); the figures are the same."""
    ev = Evaluation()
    limits = InputLimits.for_profile(pipeline.profile)
    chosen = _labelled_files(folder, positions, set(exclude_z))
    if jobs > 1 and recipe is not None and chosen:
        paths = [path for path, _ in chosen]
        items = replay_files(pipeline, recipe, paths, jobs, background=background, limits=limits)
        for item, (_, truth) in zip(items, chosen, strict=True):
            if item.error is not None:
                ev.failed.append(item.error)
            else:
                ev.add(pipeline.profile, item.result, truth)
        return ev
    for path, truth in chosen:
        rec = read_recording(path, background, limits)
        if rec.error is not None:
            ev.failed.append(rec.error)
            continue
        ev.add(pipeline.profile, pipeline.process(rec.frames, rec.background), truth)
    return ev


def evaluate_labelled(pipeline: Pipeline, data) -> Evaluation:
    """The same figures over a labelled set in memory
    (:class:`spiel_edge.recordings.labelled.LabelledArrays`, already filtered)."""
    ev = Evaluation()
    for rec in data.recordings():
        ev.add(pipeline.profile, pipeline.process(rec.frames, rec.background), rec.truth_mm)
    return ev


def _labelled_files(
    folder: str | Path, positions: set | None, skip_z: set
) -> list[tuple[Path, np.ndarray]]:
    """The frames files to evaluate, in file order, with their ground truth."""
    chosen = []
    for path in frame_files(folder):
        key = position_key(path.name)
        if positions is not None and (key is None or key[:2] not in positions):
            continue
        truth = read_truth(path)
        if truth is None or float(truth[2]) in skip_z:
            continue
        chosen.append((path, truth))
    return chosen
