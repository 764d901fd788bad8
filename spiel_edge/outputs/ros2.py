"""ROS 2 output settings shared by the sinks: the sensor frame id and static transforms.

A static transform is given as ``PARENT:X,Y,Z[,ROLL,PITCH,YAW]``: the pose of the sensor frame
(``--frame-id``, default ``spiel``) in the robot frame PARENT, metres and radians (fixed axes
X, then Y, then Z, as tf2's ``setRPY``). It goes to ``/tf_static`` in a ros2 MCAP recording and
on Zenoh with ``--zenoh-encoding cdr``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from spiel_edge.errors import ConfigError
from spiel_edge.io.cdr import StaticTransform

DEFAULT_FRAME_ID = "spiel"
RECORD_PROFILES = ("json", "ros2")
ZENOH_ENCODINGS = ("json", "cdr")


@dataclass(frozen=True)
class Ros2Settings:
    frame_id: str = DEFAULT_FRAME_ID
    transforms: tuple[StaticTransform, ...] = ()


def quaternion_from_rpy(roll: float, pitch: float, yaw: float) -> tuple[float, float, float, float]:
    """(x, y, z, w) of the rotation roll about X, then pitch about Y, then yaw about Z."""
    cr, sr = math.cos(roll / 2), math.sin(roll / 2)
    cp, sp = math.cos(pitch / 2), math.sin(pitch / 2)
    cy, sy = math.cos(yaw / 2), math.sin(yaw / 2)
    return (
        sr * cp * cy - cr * sp * sy,
        cr * sp * cy + sr * cp * sy,
        cr * cp * sy - sr * sp * cy,
        cr * cp * cy + sr * sp * sy,
    )


def parse_static_tf(text: str, child: str = DEFAULT_FRAME_ID) -> StaticTransform:
    """``PARENT:X,Y,Z[,ROLL,PITCH,YAW]`` -> StaticTransform (ConfigError when malformed)."""
    parent, sep, numbers = text.partition(":")
    parent = parent.strip()
    try:
        values = [float(v) for v in numbers.split(",")] if sep else []
    except ValueError:
        values = []
    if not parent or len(values) not in (3, 6) or not all(map(math.isfinite, values)):
        raise ConfigError(
            f"--static-tf {text!r}: expected PARENT:X,Y,Z[,ROLL,PITCH,YAW] (metres, radians), "
            "e.g. base_link:0.10,0,0.25"
        )
    if parent == child:
        raise ConfigError(f"--static-tf {text!r}: the parent frame is the sensor frame {child!r}")
    rotation = quaternion_from_rpy(*values[3:]) if len(values) == 6 else (0.0, 0.0, 0.0, 1.0)
    return StaticTransform(parent, child, tuple(values[:3]), rotation)  # type: ignore[arg-type]


def settings(frame_id: str = DEFAULT_FRAME_ID, static_tf: tuple[str, ...] = ()) -> Ros2Settings:
    """Ros2Settings from the command-line values; ConfigError on a bad frame id or transform."""
    if not frame_id or "\x00" in frame_id or frame_id.startswith("/"):
        raise ConfigError(f"--frame-id {frame_id!r}: a non-empty tf2 frame id without leading /")
    return Ros2Settings(frame_id, tuple(parse_static_tf(t, frame_id) for t in static_tf))
