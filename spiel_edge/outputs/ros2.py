"""ROS 2 output settings shared by the sinks: the sensor frame id and static transforms.

The profile's ``[frame]`` section (profile/frame_section.py) gives the frame id and one static
transform; the command line overrides it key by key (:func:`frame_settings`). ``--static-tf``
adds further transforms, each ``PARENT:X,Y,Z[,ROLL,PITCH,YAW]``: the pose of the sensor frame
(``--frame-id``, default ``spiel``) in the robot frame PARENT, metres and radians (fixed axes
X, then Y, then Z, as tf2's ``setRPY``). They go to ``/tf_static`` in a ros2 MCAP recording
and on Zenoh with ``--zenoh-encoding cdr``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from spiel_edge.errors import ConfigError
from spiel_edge.messages.cdr import StaticTransform
from spiel_edge.messages.settings import Ros2Settings, default_limits  # noqa: F401 (re-exported)
from spiel_edge.profile.frame_section import (
    DEFAULT_FRAME_ID,
    FrameSpec,
    frame_id_problem,
    frame_rotation,
    quaternion_from_rpy,
    validate_frame,
    with_overrides,
)
from spiel_edge.profile.ranges import RANGES, in_range

RECORD_PROFILES = ("json", "ros2")
ZENOH_ENCODINGS = ("json", "cdr", "rmw_zenoh")
ZENOH_MODES = ("peer", "client")


@dataclass(frozen=True)
class ZenohSettings:
    """How the Zenoh session meets the others: mode, routers or peers to connect to, the ROS
    domain (rmw_zenoh), and a Zenoh configuration file under them (None: $ZENOH_CONFIG)."""

    mode: str = "peer"
    connect: tuple[str, ...] = ()
    domain_id: int = 0
    config_file: str | None = None
    auth_key: bytes | None = field(default=None, repr=False)  # tag JSON records (record_auth)
    ros_distro: str = "jazzy"  # rmw_zenoh's key format: humble has no type hashes (wire.py)


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
    if parent in (child, f"{child}_optical"):
        raise ConfigError(f"--static-tf {text!r}: the parent frame is the sensor's own {parent!r}")
    if problem := frame_id_problem(parent):
        raise ConfigError(f"--static-tf {text[:80]!r}: the parent frame {problem}")
    if not all(in_range("frame.translation_m", v) for v in values[:3]):
        low, high = RANGES["frame.translation_m"]
        raise ConfigError(f"--static-tf {text[:80]!r}: X, Y, Z must be in [{low:g}, {high:g}] m")
    rotation = quaternion_from_rpy(*values[3:]) if len(values) == 6 else (0.0, 0.0, 0.0, 1.0)
    return StaticTransform(parent, child, tuple(values[:3]), rotation)  # type: ignore[arg-type]


def settings(frame_id: str = DEFAULT_FRAME_ID, static_tf: tuple[str, ...] = ()) -> Ros2Settings:
    """Ros2Settings from the command-line values; ConfigError on a bad frame id or transform."""
    problem = frame_id_problem(frame_id)
    if problem:
        raise ConfigError(f"--frame-id {frame_id!r}: {problem}")
    return Ros2Settings(frame_id, tuple(parse_static_tf(t, frame_id) for t in static_tf))


# command-line option -> [frame] key (cli/_ros2.py)
FRAME_OPTIONS = {
    "frame_id": "--frame-id",
    "parent": "--parent-frame",
    "translation_m": "--translation-m",
    "rotation_rpy_deg": "--rotation-rpy-deg",
    "rotation_xyzw": "--rotation-xyzw",
}


def frame_settings(
    profile_frame: FrameSpec | None,
    static_tf: tuple[str, ...] = (),
    origin: str = "profile",
    limits: object = None,
    **given: object,
) -> Ros2Settings:
    """Ros2Settings from the profile's ``[frame]`` with the options ``given`` (keys of
    FRAME_OPTIONS, None when not given) over it, plus the ``--static-tf`` transforms."""
    spec = with_overrides(profile_frame or FrameSpec(), **given)
    labels = {key: FRAME_OPTIONS[key] for key, value in given.items() if value is not None}
    validate_frame(spec, origin, labels)
    transforms = [frame_transform(spec)] if spec.parent else []
    transforms += [parse_static_tf(t, spec.frame_id) for t in static_tf]
    if len(transforms) > 1:  # tf2: a frame has one parent
        given = "--parent-frame (or the profile's [frame] parent)" if spec.parent else "--static-tf"
        raise ConfigError(
            f"--static-tf: {spec.frame_id!r} would have {len(transforms)} parents (with {given}); "
            "a frame has one parent in tf2: give one transform"
        )
    return Ros2Settings(spec.frame_id, tuple(transforms), limits or default_limits())


def frame_transform(spec: FrameSpec) -> StaticTransform:
    """The static transform parent -> frame_id of a validated spec with a parent."""
    translation = tuple(float(v) for v in spec.translation_m)
    return StaticTransform(spec.parent, spec.frame_id, translation, frame_rotation(spec))  # type: ignore[arg-type]


def parse_numbers(text: str | None, count: int, option: str) -> tuple[float, ...] | None:
    """``"X,Y,Z"`` -> floats (None passes through); ConfigError naming the option."""
    if text is None:
        return None
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        values = ()
    if len(values) != count or not all(map(math.isfinite, values)):
        raise ConfigError(f"{option} {text[:80]!r}: expected {count} numbers separated by commas")
    return values
