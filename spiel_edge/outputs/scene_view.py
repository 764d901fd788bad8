"""What a 3-D view draws of a record's scene, without any viewer library: each target's 95 %
uncertainty ellipsoid and each track's recent trail (used by outputs/foxglove.py)."""

from __future__ import annotations

from collections import deque
from collections.abc import Sequence

import numpy as np

CHI2_3DOF_95 = 7.8147  # 95 % of a 3-D Gaussian lies inside this squared Mahalanobis distance
TRAIL_LENGTH = 25  # positions kept per track (half a second at 50 Hz)
MIN_AXIS_MM = 1.0


def ellipsoid(
    covariance_mm2: Sequence[Sequence[float]], chi2: float = CHI2_3DOF_95
) -> tuple[np.ndarray, np.ndarray]:
    """(diameters along the principal axes in mm (3,), orientation quaternion (x, y, z, w))
    of the ellipsoid holding ``chi2`` of the covariance; a malformed covariance gives a
    small sphere."""
    cov = np.asarray(covariance_mm2, dtype=np.float64)
    if cov.shape != (3, 3) or not np.all(np.isfinite(cov)):
        return np.full(3, 2 * MIN_AXIS_MM), np.array([0.0, 0.0, 0.0, 1.0])
    values, vectors = np.linalg.eigh(0.5 * (cov + cov.T))
    if np.linalg.det(vectors) < 0:
        vectors[:, 2] = -vectors[:, 2]  # a rotation, not a reflection
    diameters = 2.0 * np.sqrt(np.maximum(values, 0.0) * chi2)
    return np.maximum(diameters, 2 * MIN_AXIS_MM), quaternion(vectors)


def quaternion(rotation: np.ndarray) -> np.ndarray:
    """(x, y, z, w) of a 3x3 rotation matrix."""
    r = rotation
    trace = r[0, 0] + r[1, 1] + r[2, 2]
    if trace > 0:
        s = 2.0 * np.sqrt(trace + 1.0)
        q = [(r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s, s / 4]
    elif r[0, 0] > r[1, 1] and r[0, 0] > r[2, 2]:
        s = 2.0 * np.sqrt(1.0 + r[0, 0] - r[1, 1] - r[2, 2])
        q = [s / 4, (r[0, 1] + r[1, 0]) / s, (r[0, 2] + r[2, 0]) / s, (r[2, 1] - r[1, 2]) / s]
    elif r[1, 1] > r[2, 2]:
        s = 2.0 * np.sqrt(1.0 + r[1, 1] - r[0, 0] - r[2, 2])
        q = [(r[0, 1] + r[1, 0]) / s, s / 4, (r[1, 2] + r[2, 1]) / s, (r[0, 2] - r[2, 0]) / s]
    else:
        s = 2.0 * np.sqrt(1.0 + r[2, 2] - r[0, 0] - r[1, 1])
        q = [(r[0, 2] + r[2, 0]) / s, (r[1, 2] + r[2, 1]) / s, s / 4, (r[1, 0] - r[0, 1]) / s]
    q = np.array(q)
    return q / np.linalg.norm(q)


class Trails:
    """The last ``length`` positions of each track; tracks that vanish are forgotten."""

    def __init__(self, length: int = TRAIL_LENGTH):
        self.length = length
        self._trails: dict[int, deque] = {}

    def update(self, tracks: Sequence[dict]) -> dict[int, list]:
        alive = {}
        for track in tracks:
            trail = self._trails.get(track["track_id"]) or deque(maxlen=self.length)
            trail.append(list(track["position_mm"]))
            alive[track["track_id"]] = trail
        self._trails = alive
        return {k: list(v) for k, v in alive.items()}
