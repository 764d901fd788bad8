"""MCAP recordings with the ROS 2 profile (``--record-profile ros2``): CDR messages that
``rosbags``, ``mcap-ros2-support`` and ``ros2 bag`` read, and ``spiel-edge replay`` replays.

Topics (frame ids from ``--frame-id``, metres):

* ``/spiel/point``: geometry_msgs/msg/PointStamped, the best target of each acquisition
  (none when the acquisition has no fix), stamped with the acquisition's host time;
* ``/spiel/targets``: sensor_msgs/msg/PointCloud2, every target (cdr.TARGET_FIELDS: x, y, z,
  score, track_id (-1: none), var_x/y/z the covariance diagonal in m^2);
* ``/spiel/position``: std_msgs/msg/String, the whole JSON record (reason, echoes, ...);
* ``/spiel/acquisition`` and ``/spiel/background``: spiel_msgs/msg/Acquisition, the raw frames
  (the message definition is stored in the file, so ROS tools decode it without a package);
* ``/tf_static``: tf2_msgs/msg/TFMessage, the static transforms given (``--static-tf``).
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

import numpy as np

from spiel_edge.io import cdr
from spiel_edge.io.mcap import ACQUISITION_TOPIC, BACKGROUND_TOPIC, POSITION_TOPIC
from spiel_edge.outputs.mcap import McapSink, _default, _stamp

POINT_TOPIC = "/spiel/point"
TARGETS_TOPIC = "/spiel/targets"
TF_STATIC_TOPIC = "/tf_static"

TOPIC_TYPES = {
    ACQUISITION_TOPIC: cdr.ACQUISITION,
    BACKGROUND_TOPIC: cdr.ACQUISITION,
    POINT_TOPIC: cdr.POINT_STAMPED,
    TARGETS_TOPIC: cdr.POINT_CLOUD2,
    POSITION_TOPIC: cdr.STRING,
    TF_STATIC_TOPIC: cdr.TF_MESSAGE,
}
# rosbag2's QoS metadata: /tf_static is transient-local, so `ros2 bag play` latches it
_LATCHED_QOS = (
    "- history: 3\n  depth: 0\n  reliability: 1\n  durability: 1\n"
    "  deadline:\n    sec: 2147483647\n    nsec: 4294967295\n"
    "  lifespan:\n    sec: 2147483647\n    nsec: 4294967295\n"
    "  liveliness: 1\n  liveliness_lease_duration:\n    sec: 2147483647\n    nsec: 4294967295\n"
    "  avoid_ros_namespace_conventions: false"
)


class Ros2McapSink(McapSink):
    """An McapSink whose channels are ROS 2 messages in CDR (profile ``ros2``)."""

    profile = "ros2"

    def __init__(
        self,
        path: str | Path,
        *,
        frame_id: str = "spiel",
        transforms: list[cdr.StaticTransform] | tuple = (),
        metadata: dict[str, Any] | None = None,
        **options: Any,
    ):
        self.encoder = cdr.Ros2Encoder(frame_id)
        super().__init__(path, metadata={**(metadata or {}), "frame_id": frame_id}, **options)
        if transforms:
            self.write_transforms(transforms, time.time())

    def write_transforms(self, transforms, stamp_s: float) -> None:
        """The static transforms, once, on /tf_static (latched by its QoS metadata)."""
        message = self.encoder.tf_message(list(transforms), stamp_s)
        self._add(TF_STATIC_TOPIC, message, int(stamp_s * 1e9))

    def _register_channels(self) -> dict[str, int]:
        schemas = {
            name: self._writer.register_schema(name, "ros2msg", cdr.DEFINITIONS[name].encode())
            for name in sorted(set(TOPIC_TYPES.values()))
        }
        return {
            topic: self._writer.register_channel(
                topic,
                "cdr",
                schemas[name],
                {"offered_qos_profiles": _LATCHED_QOS} if topic == TF_STATIC_TOPIC else {},
            )
            for topic, name in TOPIC_TYPES.items()
        }

    def write_acquisition(self, acquisition: dict, frames: np.ndarray) -> None:
        meta = {k: v for k, v in acquisition.items() if k not in ("frames", "background")}
        stamp = _stamp(meta)
        synced = meta.get("stamp_host_ns")  # the board's time on the host clock (protocol 2)
        if isinstance(synced, int) and synced > 0:
            stamp = synced
        seconds = stamp / 1e9 if stamp else None
        background = acquisition.get("background")
        if background is not None and (
            self._background is None or not np.array_equal(background, self._background)
        ):
            self._background = np.array(background, copy=True)
            message = cdr.acquisition_message(
                self._background, seq=-1, device_time_us=0, stamp_s=seconds
            )
            self._add(BACKGROUND_TOPIC, message, stamp)
        message = cdr.acquisition_message(
            np.asarray(frames),
            seq=int(meta.get("seq", self.counts["acquisitions"])),
            device_time_us=int(meta.get("device_time_us") or 0),
            stamp_s=seconds,
        )
        self._add(ACQUISITION_TOPIC, message, stamp)
        self.counts["acquisitions"] += 1

    def write(self, record: dict) -> None:
        seconds = record.get("stamp_host") or record.get("host_time")  # synced board time first
        stamp = int(seconds * 1e9) if isinstance(seconds, (int, float)) and seconds > 0 else 0
        best = record.get("position_mm")
        if best is not None:
            self._add(POINT_TOPIC, self.encoder.point_stamped(best, seconds), stamp)
        targets = record.get("targets") or []
        self._add(TARGETS_TOPIC, self.encoder.targets_cloud(targets, seconds), stamp)
        text = json.dumps(record, separators=(",", ":"), allow_nan=False, default=_default)
        self._add(POSITION_TOPIC, cdr.string_message(text), stamp)
        self.counts["records"] += 1
