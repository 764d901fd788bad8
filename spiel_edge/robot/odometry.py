"""The robot's pose in ``odom`` for the fuser (robot/fusion.py): a planar pose as (R, t), a
buffer of poses from an odometry stream, interpolated at a time, and the messages that carry
them: JSON ``{"stamp": Unix s, "x": m, "y": m, "yaw": rad}`` or a ROS 2 nav_msgs/msg/Odometry
in CDR (as rmw_zenoh publishes it, or rosbag2 records it). Where they come from (a file, a
Zenoh key) is robot/odometry_sources.py's."""

from __future__ import annotations

import json
import logging
import math

import numpy as np

from spiel_edge.errors import InputError

log = logging.getLogger(__name__)


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
    MAX_STAMP_SKEW_S = 1.0  # a message's stamp this far from its arrival: the arrival is used

    def __init__(self, max_poses: int | None = MAX_POSES) -> None:
        self._poses: list[tuple[float, float, float, float]] = []
        self.max_poses = max_poses  # None: every pose (a recording)
        self.rejected = 0  # messages not used (malformed or out of order)

    def add(self, t: float, x_mm: float, y_mm: float, yaw_rad: float) -> bool:
        values = (t, x_mm, y_mm, yaw_rad)
        if not all(math.isfinite(v) for v in values):
            return False
        if self._poses and t <= self._poses[-1][0]:
            return False  # out of order or repeated: kept out
        self._poses.append(values)
        if self.max_poses is not None:
            del self._poses[: -self.max_poses]
        return True

    def __len__(self) -> int:
        return len(self._poses)

    def add_message(self, payload: bytes, arrived: float, shift_s: float = 0.0) -> bool:
        """One odometry message (:func:`parse_odometry`) that arrived at ``arrived`` (Unix s):
        its stamp when within ``MAX_STAMP_SKEW_S`` of the arrival, else the arrival, plus
        ``shift_s`` (onto the caller's clock). A message not used is counted and said (the
        1st, 100th, 10000th)."""
        try:
            stamp, x, y, yaw = parse_odometry(payload)
        except InputError:
            return self._reject()
        if stamp is None or not abs(stamp - arrived) <= self.MAX_STAMP_SKEW_S:
            stamp = arrived
        return self.add(stamp + shift_s, 1000.0 * x, 1000.0 * y, yaw) or self._reject()

    def _reject(self) -> bool:
        self.rejected += 1
        if self.rejected in (1, 100, 10000):
            log.warning("odometry: %d messages not used (malformed or out of order)", self.rejected)
        return False

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


def parse_odometry(payload: bytes) -> tuple[float | None, float, float, float]:
    """(stamp s or None, x m, y m, yaw rad) of one odometry message: JSON (``stamp``
    optional) or a nav_msgs/msg/Odometry in CDR; InputError when it is neither."""
    from spiel_edge.messages.cdr import decode_odometry

    data = bytes(payload)
    if data[:2] in (b"\x00\x01", b"\x00\x00"):
        return decode_odometry(data)
    try:
        msg = json.loads(data)
        x, y, yaw = (float(msg[k]) for k in ("x", "y", "yaw"))
        stamp = msg.get("stamp")
        stamp = None if stamp is None else float(stamp)
    except (ValueError, KeyError, TypeError, AttributeError) as exc:
        raise InputError(
            f"not an odometry message (JSON x, y, yaw or nav_msgs/Odometry): {exc}"
        ) from exc
    if not all(math.isfinite(v) for v in (x, y, yaw)):
        raise InputError("odometry pose not finite")
    return stamp, x, y, yaw
