"""The board's field of view and range limits as ROS 2 messages state them (sensor_msgs/Range,
the target filter of messages/ros2_messages.py), from a profile."""

from __future__ import annotations

import math
from dataclasses import dataclass

FIELD_OF_VIEW_RAD = math.pi  # the CH101's 180 degrees (the paper, section IV)


@dataclass(frozen=True)
class SensorLimits:
    """The board's field of view and range limits (sensor_msgs/Range, the target filter)."""

    field_of_view_rad: float = FIELD_OF_VIEW_RAD
    min_range_m: float = 0.0702  # spiel-icra23: 9 blind samples at 22 kHz, 343 m/s
    max_range_m: float = 0.4989  # 64 samples
    boresight: tuple[float, float, float] = (0.0, 0.0, 1.0)  # in the geometry's frame

    @classmethod
    def of_profile(cls, profile) -> SensorLimits:
        a, g = profile.acquisition, profile.geometry
        metres_per_sample = g.speed_of_sound_m_s / a.sample_rate_hz / 2.0  # round trip
        facing = [float(v) for v in g.facing]
        norm = math.sqrt(sum(v * v for v in facing)) or 1.0
        return cls(
            FIELD_OF_VIEW_RAD,
            round(profile.preprocess.blind_zone_samples * metres_per_sample, 4),
            round(a.n_samples * metres_per_sample, 4),
            tuple(v / norm for v in facing),  # type: ignore[arg-type]
        )
