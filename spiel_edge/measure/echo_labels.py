"""Ground truth for echo association: which echo of each channel came from the target.

A known target position p projects to one echo time per channel,
``ToA_n = (|p - e| + |p - r_n|) / mm_per_sample + delay_n`` (samples, as the features' ToA
column). The echo nearest that time is the target's if it lies within ``tolerance`` samples;
otherwise the channel has no target echo (label -1). Used to label training data and to score
any associator (pure functions, no I/O).

Association scores (per listening channel of each acquisition, ``matched`` vs ``labels``):
- accuracy: share of channels where ``matched == labels`` (both -1 counts as correct);
- true positive: a matched echo that is the labelled one; false positive: a matched echo that
  is not; false negative: a labelled echo that was not matched; F1 = 2TP / (2TP + FP + FN).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from spiel_edge.pipeline.stages.features import TOA_COLUMN
from spiel_edge.profile.schema import Profile

# the ground truth of `spiel-edge evaluate` and of training (1.5 samples = 23 mm of path)
DEFAULT_TOLERANCE = 1.5
__all__ = [
    "DEFAULT_TOLERANCE",
    "AssociationScore",
    "expected_toa",
    "label_echoes",
    "score_association",
]


def expected_toa(profile: Profile, position_mm: np.ndarray) -> np.ndarray:
    """Per-channel echo time (samples) of a point target at ``position_mm``."""
    g = profile.geometry
    return g.echo_paths_mm(position_mm) / profile.mm_per_sample + g.delays()


def label_echoes(
    features: np.ndarray,
    counts: np.ndarray,
    expected: np.ndarray,
    tolerance: float = DEFAULT_TOLERANCE,
) -> np.ndarray:
    """Index of the target echo per channel (nearest ``expected`` within ``tolerance``), or -1."""
    toa = np.asarray(features)[:, :, TOA_COLUMN]
    labels = np.full(toa.shape[0], -1, dtype=np.int64)
    for c in range(toa.shape[0]):
        n = int(counts[c])
        if n == 0:
            continue
        dev = np.abs(toa[c, :n] - expected[c])
        k = int(np.nanargmin(dev)) if np.any(np.isfinite(dev)) else -1
        if k >= 0 and dev[k] <= tolerance:
            labels[c] = k
    return labels


@dataclass
class AssociationScore:
    """Counts over channels; add them up across acquisitions with ``+``."""

    correct: int = 0
    channels: int = 0
    tp: int = 0
    fp: int = 0
    fn: int = 0

    def __add__(self, other: AssociationScore) -> AssociationScore:
        return AssociationScore(
            *(a + b for a, b in zip(self.astuple(), other.astuple(), strict=True))
        )

    def astuple(self) -> tuple[int, int, int, int, int]:
        return (self.correct, self.channels, self.tp, self.fp, self.fn)

    @property
    def accuracy(self) -> float:
        return self.correct / self.channels if self.channels else float("nan")

    @property
    def f1(self) -> float:
        den = 2 * self.tp + self.fp + self.fn
        return 2 * self.tp / den if den else float("nan")


def score_association(
    matched: np.ndarray, labels: np.ndarray, listening: np.ndarray | None = None
) -> AssociationScore:
    """Compare one acquisition's ``matched`` (channels,) with its ``labels`` (channels,)."""
    m = np.asarray(matched, dtype=np.int64)
    y = np.asarray(labels, dtype=np.int64)
    use = np.ones(m.shape, dtype=bool) if listening is None else np.asarray(listening, dtype=bool)
    m, y = m[use], y[use]
    hit = (m >= 0) & (m == y)
    return AssociationScore(
        correct=int((m == y).sum()),
        channels=int(m.size),
        tp=int(hit.sum()),
        fp=int(((m >= 0) & ~hit).sum()),
        fn=int(((y >= 0) & ~hit).sum()),
    )
