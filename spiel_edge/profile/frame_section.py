"""The ``[frame]`` section of a profile: the sensor's tf2 frame and its static transform.

``frame_id`` names the sensor frame (the origin and axes of ``[geometry]``) in every ROS 2
message; ``parent`` is the robot frame the sensor is mounted on, and ``translation_m`` with
``rotation_rpy_deg`` (roll about X, then pitch about Y, then yaw about Z, fixed axes, as tf2's
``setRPY``) or ``rotation_xyzw`` (a unit quaternion) is the pose of the sensor frame in it. The
transform is published on ``/tf_static`` (docs/ros2.md). The command line overrides each key
(``--frame-id``, ``--parent-frame``, ...; cli/_ros2.py).
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, fields, replace

from spiel_edge.errors import ConfigError
from spiel_edge.profile.ranges import RANGES, in_range

DEFAULT_FRAME_ID = "spiel"
MAX_FRAME_ID = 128
QUATERNION_NORM_TOLERANCE = 1e-3  # |q| may differ this much from 1 (rounded digits); normalized
_FRAME_ID = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_./-]*")


@dataclass(frozen=True)
class FrameSpec:
    frame_id: str = DEFAULT_FRAME_ID  # header.frame_id of the messages: the sensor frame
    parent: str = ""  # robot frame the sensor is mounted on; "" publishes no transform
    translation_m: tuple = (0.0, 0.0, 0.0)  # sensor origin in parent, metres
    rotation_rpy_deg: tuple = (0.0, 0.0, 0.0)  # roll, pitch, yaw (fixed X, Y, Z), degrees
    rotation_xyzw: tuple = ()  # or a unit quaternion (x, y, z, w) instead of the angles


def frame_id_problem(name: object) -> str | None:
    """Why ``name`` is not a usable tf2 frame id (None when it is)."""
    if not isinstance(name, str) or not name:
        return "must be a non-empty frame id"
    if len(name) > MAX_FRAME_ID:
        return f"must be at most {MAX_FRAME_ID} characters"
    if not _FRAME_ID.fullmatch(name):
        return "must be letters, digits, _ . / - without a leading / (e.g. base_link)"
    return None


def validate_frame(spec: FrameSpec, origin: str, labels: dict[str, str] | None = None) -> None:
    """Every key checked (ranges in profile/ranges.py); one-line ConfigError naming the key,
    or the command-line option in ``labels`` that gave it."""

    def fail(key: str, message: str) -> None:
        where = (labels or {}).get(key) or f"{origin}: frame.{key}"
        raise ConfigError(f"{where} {message}")

    for key in ("frame_id", "parent"):
        value = getattr(spec, key)
        problem = frame_id_problem(value) if key == "frame_id" or value else None
        if problem:
            fail(key, f"{problem}, got {_short(value)}")
    if spec.parent == spec.frame_id:
        fail("parent", f"is the sensor frame itself ({spec.frame_id!r}); name the robot frame")
    if spec.parent == f"{spec.frame_id}_optical":
        fail("parent", f"is the sensor's own optical frame ({spec.parent!r}): a cycle")
    for key, count in (("translation_m", 3), ("rotation_rpy_deg", 3)):
        values = getattr(spec, key)
        if len(values) != count or not all(in_range(f"frame.{key}", v) for v in values):
            fail(key, f"must be {count} numbers in {_range(key)}, got {_short(list(values))}")
    q = spec.rotation_xyzw
    if q:
        norm = math.sqrt(sum(v * v for v in q)) if len(q) == 4 else 0.0
        if not (len(q) == 4 and abs(norm - 1.0) <= QUATERNION_NORM_TOLERANCE):
            fail("rotation_xyzw", f"must be a unit quaternion x, y, z, w, got {_short(list(q))}")
        if any(spec.rotation_rpy_deg):
            fail("rotation_xyzw", "and rotation_rpy_deg both given; give one rotation")
    if not spec.parent and _has_pose(spec):
        fail("parent", "is needed with a translation or rotation (the robot frame, e.g. base_link)")


def _is_pose(key: str) -> bool:
    return key not in ("frame_id", "parent")


def _has_pose(spec: FrameSpec) -> bool:
    return any(getattr(spec, f.name) != f.default for f in fields(FrameSpec) if _is_pose(f.name))


def _range(key: str) -> str:
    low, high = RANGES[f"frame.{key}"]
    return f"[{low:g}, {high:g}]"


def _short(value: object) -> str:
    text = repr(value)
    return text if len(text) <= 80 else text[:60] + "..."


def with_overrides(spec: FrameSpec, **given: object) -> FrameSpec:
    """``spec`` with the keys given (not None) replaced; a rotation given one way replaces
    the profile's rotation given the other way; an empty ``parent`` drops the transform."""
    given = {k: v for k, v in given.items() if v is not None}
    if given.get("parent") == "":  # an empty parent drops the profile's transform
        spec = replace(spec, **{f.name: f.default for f in fields(FrameSpec) if _is_pose(f.name)})
    if "rotation_rpy_deg" in given and "rotation_xyzw" not in given:
        given["rotation_xyzw"] = ()
    if "rotation_xyzw" in given and "rotation_rpy_deg" not in given:
        given["rotation_rpy_deg"] = (0.0, 0.0, 0.0)
    return replace(spec, **given)


def quaternion_from_rpy(roll: float, pitch: float, yaw: float) -> tuple[float, float, float, float]:
    """(x, y, z, w) of the rotation roll about X, then pitch about Y, then yaw about Z
    (radians)."""
    cr, sr = math.cos(roll / 2), math.sin(roll / 2)
    cp, sp = math.cos(pitch / 2), math.sin(pitch / 2)
    cy, sy = math.cos(yaw / 2), math.sin(yaw / 2)
    return (
        sr * cp * cy - cr * sp * sy,
        cr * sp * cy + sr * cp * sy,
        cr * cp * sy - sr * sp * cy,
        cr * cp * cy + sr * sp * sy,
    )


def frame_rotation(spec: FrameSpec) -> tuple[float, float, float, float]:
    """The unit quaternion (x, y, z, w) of a validated spec."""
    if spec.rotation_xyzw:
        norm = math.sqrt(sum(v * v for v in spec.rotation_xyzw))
        return tuple(float(v) / norm for v in spec.rotation_xyzw)  # type: ignore[return-value]
    return quaternion_from_rpy(*(math.radians(v) for v in spec.rotation_rpy_deg))
