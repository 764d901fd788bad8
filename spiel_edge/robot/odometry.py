"""The robot's pose in ``odom`` for the fuser (robot/fusion.py): a planar pose as (R, t), and a
buffer of poses from an odometry stream, interpolated at a time."""

from __future__ import annotations

import math

import numpy as np


def planar_pose(x_mm: float, y_mm: float, yaw_rad: float) -> tuple[np.ndarray, np.ndarray]:
    """(R, t) of base_link in odom for a pose on the floor."""
    c, s = math.cos(yaw_rad), math.sin(yaw_rad)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]), np.array([x_mm, y_mm, 0.0])


class OdometryBuffer:
    """The robot's planar pose in ``odom`` over time, from an odometry stream: ``add`` poses
    (time s, x mm, y mm, yaw rad) in time order, call it at a time for (R, t), linearly
    interpolated (yaw the short way round); None outside the poses held (more than
    ``MAX_EXTRAPOLATION_S`` beyond the newest, or before the oldest)."""

    MAX_POSES = 512
    MAX_EXTRAPOLATION_S = 0.2

    def __init__(self) -> None:
        self._poses: list[tuple[float, float, float, float]] = []

    def add(self, t: float, x_mm: float, y_mm: float, yaw_rad: float) -> bool:
        values = (t, x_mm, y_mm, yaw_rad)
        if not all(math.isfinite(v) for v in values):
            return False
        if self._poses and t <= self._poses[-1][0]:
            return False  # out of order or repeated: kept out
        self._poses.append(values)
        del self._poses[: -self.MAX_POSES]
        return True

    def __call__(self, t: float) -> tuple[np.ndarray, np.ndarray] | None:
        poses = self._poses
        if not poses or t < poses[0][0] or t > poses[-1][0] + self.MAX_EXTRAPOLATION_S:
            return None
        if t >= poses[-1][0]:
            _, x, y, yaw = poses[-1]
            return planar_pose(x, y, yaw)
        lo, hi = 0, len(poses) - 1
        while hi - lo > 1:
            mid = (lo + hi) // 2
            lo, hi = (mid, hi) if poses[mid][0] <= t else (lo, mid)
        (t0, x0, y0, a0), (t1, x1, y1, a1) = poses[lo], poses[hi]
        w = (t - t0) / (t1 - t0)
        da = math.remainder(a1 - a0, 2 * math.pi)
        return planar_pose(x0 + w * (x1 - x0), y0 + w * (y1 - y0), a0 + w * da)
