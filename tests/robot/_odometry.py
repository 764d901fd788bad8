"""A nav_msgs/msg/Odometry in CDR written by rosbags (the reference, not our code)."""

from __future__ import annotations

import math

import numpy as np
from rosbags.typesys import Stores, get_typestore

STORE = get_typestore(Stores.ROS2_HUMBLE)


def odometry_cdr(stamp, x, y, yaw, *, frame="odom", child="base_link", little=True) -> bytes:
    """A nav_msgs/msg/Odometry serialised by rosbags (the reference, not our code)."""
    t = STORE.types
    sec = math.floor(stamp)
    pose = t["geometry_msgs/msg/Pose"](
        position=t["geometry_msgs/msg/Point"](x=x, y=y, z=0.25),
        orientation=t["geometry_msgs/msg/Quaternion"](
            x=0.0, y=0.0, z=math.sin(yaw / 2), w=math.cos(yaw / 2)
        ),
    )
    vec = t["geometry_msgs/msg/Vector3"](x=0.1, y=0.0, z=0.0)
    msg = t["nav_msgs/msg/Odometry"](
        header=t["std_msgs/msg/Header"](
            stamp=t["builtin_interfaces/msg/Time"](sec=sec, nanosec=round((stamp - sec) * 1e9)),
            frame_id=frame,
        ),
        child_frame_id=child,
        pose=t["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=np.arange(36.0)),
        twist=t["geometry_msgs/msg/TwistWithCovariance"](
            twist=t["geometry_msgs/msg/Twist"](linear=vec, angular=vec), covariance=np.zeros(36)
        ),
    )
    return bytes(STORE.serialize_cdr(msg, "nav_msgs/msg/Odometry", little_endian=little))
