"""What the ROS 2 messages carry from the settings: the sensor frame id, the static transforms
of its mount, its limits and whether its records are in optical axes (outputs/ros2.py builds
them from the profile and the command line)."""

from __future__ import annotations

from dataclasses import dataclass, field

from spiel_edge.messages.cdr import StaticTransform
from spiel_edge.messages.ros2_limits import SensorLimits
from spiel_edge.profile.frame_section import DEFAULT_FRAME_ID


def default_limits():
    return SensorLimits()


@dataclass(frozen=True)
class Ros2Settings:
    frame_id: str = DEFAULT_FRAME_ID  # the sensor's REP 103 frame; messages: <frame_id>_optical
    transforms: tuple[StaticTransform, ...] = ()  # the mount: parent -> frame_id
    limits: object = field(default_factory=default_limits)  # ros2_messages.SensorLimits
    # False: the records are already in frame_id's own REP 103 axes (a robot's fused scene in
    # base_link or odom): messages stamped frame_id itself, no optical frame, no Range
    optical: bool = True
