"""Does a calibration help? The 3-D error before and after, on positions it did not fit.

The calibration data is split by the target's (x, y) position into folds (every height of a
position in the same fold, as ``evaluate --split`` does). For each fold the geometry is solved
again from the other folds, and the full pipeline locates the held-out fold's acquisitions
with the starting geometry and with that fold's calibration. The figures pooled over the
folds say what the calibration does on positions it has not seen; ``calibrate`` refuses to
write a calibration whose cross-validated median error is worse than the start's
(:attr:`Validation.worse`).

Also reported, but not used to decide: the error on the very acquisitions the final
calibration was solved from (in-sample, which flatters it).
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from spiel_edge.errors import SpielError
from spiel_edge.profile.schema import Geometry, Profile

log = logging.getLogger(__name__)

MAX_FOLDS = 5


@dataclass
class ErrorFigures:
    """3-D errors of the acquisitions that got a position, and how many did."""

    errors_mm: list[float] = field(default_factory=list)
    acquisitions: int = 0

    def add(self, errors: list[float], acquisitions: int) -> None:
        self.errors_mm += errors
        self.acquisitions += acquisitions

    @property
    def fixes(self) -> int:
        return len(self.errors_mm)

    @property
    def mean_mm(self) -> float | None:
        return float(np.mean(self.errors_mm)) if self.errors_mm else None

    @property
    def median_mm(self) -> float | None:
        return float(np.median(self.errors_mm)) if self.errors_mm else None

    @property
    def fix_rate(self) -> float | None:
        return self.fixes / self.acquisitions if self.acquisitions else None

    def as_dict(self) -> dict:
        def r(v):
            return None if v is None else round(v, 2)

        return {
            "acquisitions": self.acquisitions,
            "fixes": self.fixes,
            "mean_mm": r(self.mean_mm),
            "median_mm": r(self.median_mm),
        }


@dataclass
class Validation:
    folds: int
    positions: int
    before: ErrorFigures  # held-out acquisitions, starting geometry
    after: ErrorFigures  # the same acquisitions, each with the calibration of the other folds
    in_sample_before: ErrorFigures
    in_sample_after: ErrorFigures
    failed_folds: list[str] = field(default_factory=list)

    @property
    def worse(self) -> bool:
        """The calibration makes unseen positions worse: a higher median error, or fewer
        fixes (more than 2 % of the acquisitions lost). The median, not the mean: a fold
        solved from fewer positions can extrapolate badly to a few held-out edge positions
        (on the virtual board's perturbed geometry: median 22.1 -> 11.9 mm, in-sample mean
        28.1 -> 13.9 mm, yet a cross-validated mean of 28.1 -> 47.5 mm); both are reported."""
        b, a = self.before, self.after
        if a.median_mm is None:
            return b.median_mm is not None
        if b.median_mm is None:
            return False
        return a.median_mm > b.median_mm or (a.fix_rate or 0.0) < (b.fix_rate or 0.0) - 0.02

    def as_dict(self) -> dict:
        return {
            "folds": self.folds,
            "positions": self.positions,
            "cross_validated": {"before": self.before.as_dict(), "after": self.after.as_dict()},
            "in_sample": {
                "before": self.in_sample_before.as_dict(),
                "after": self.in_sample_after.as_dict(),
            },
            "failed_folds": self.failed_folds,
            "worse": self.worse,
        }


def position_folds(truth_mm: np.ndarray, folds: int = MAX_FOLDS) -> tuple[np.ndarray, int]:
    """(fold index per acquisition, number of folds): (x, y) positions (rounded to 0.1 mm) in
    sorted order dealt round-robin, so neighbouring positions land in different folds."""
    xy = np.round(np.asarray(truth_mm, dtype=np.float64)[:, :2], 1)
    unique, inverse = np.unique(xy, axis=0, return_inverse=True)
    k = min(folds, len(unique))
    return np.asarray(inverse).reshape(-1) % max(k, 1), k


def localisation_errors(
    profile: Profile,
    geometry: Geometry,
    frames: np.ndarray,
    backgrounds: np.ndarray | None,
    truth_mm: np.ndarray,
    build: Callable[[Profile], object],
) -> tuple[list[float], int]:
    """The pipeline with ``geometry``: 3-D errors of the acquisitions it fixed, and their count."""
    pipeline = build(profile.replace(geometry=geometry))
    errors = []
    for i in range(len(frames)):
        bg = (
            None
            if backgrounds is None
            else (backgrounds if backgrounds.ndim == 2 else backgrounds[i])
        )
        pos = pipeline.process(frames[i], bg).position_mm
        if pos is not None:
            errors.append(float(np.linalg.norm(np.asarray(pos) - truth_mm[i])))
    return errors, len(frames)


def cross_validate(
    profile: Profile,
    final: Geometry,
    frames: np.ndarray,
    backgrounds: np.ndarray | None,
    truth_mm: np.ndarray,
    solve: Callable[[np.ndarray], Geometry],
    build: Callable[[Profile], object],
    folds: int = MAX_FOLDS,
) -> Validation:
    """``solve(mask)`` calibrates from the acquisitions in ``mask``; ``build(profile)`` makes
    a pipeline. Needs at least two (x, y) positions."""
    fold, k = position_folds(truth_mm, folds)
    positions = len(np.unique(np.round(truth_mm[:, :2], 1), axis=0))
    v = Validation(k, positions, ErrorFigures(), ErrorFigures(), ErrorFigures(), ErrorFigures())
    start = profile.geometry

    def errors(geometry: Geometry, mask: np.ndarray) -> tuple[list[float], int]:
        bg = backgrounds
        if bg is not None and bg.ndim == 3:  # one per acquisition (else one for all)
            bg = bg[mask]
        return localisation_errors(profile, geometry, frames[mask], bg, truth_mm[mask], build)

    if k >= 2:
        for f in range(k):
            held = fold == f
            try:
                geometry = solve(~held)
            except SpielError as exc:  # too few positions left to separate the parameters
                v.failed_folds.append(f"fold {f + 1}: {exc}")
                log.warning("cross-validation fold %d: %s", f + 1, exc)
                continue
            v.before.add(*errors(start, held))
            v.after.add(*errors(geometry, held))
    everything = np.ones(len(frames), dtype=bool)
    v.in_sample_before.add(*errors(start, everything))
    v.in_sample_after.add(*errors(final, everything))
    return v
