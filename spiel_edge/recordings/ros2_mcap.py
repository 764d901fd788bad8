"""MCAP recordings with the ROS 2 profile (``--record-profile ros2``): CDR messages that
``rosbags``, ``mcap-ros2-support`` and ``ros2 bag`` read, and ``spiel-edge replay`` replays.

Topics: the messages of messages/ros2_messages.py under ``/spiel`` (``/spiel/point``,
``/spiel/targets``, ``/spiel/tracks``, ``/spiel/range``), ``/diagnostics`` and ``/tf_static``
(the mount and the optical frame, once at the start), plus

* ``/spiel/position``: std_msgs/msg/String, the whole JSON record (reason, echoes, ...);
* ``/spiel/acquisition`` and ``/spiel/background``: spiel_msgs/msg/Acquisition, the raw frames
  (the definition is in the file; the package is packaging/ros2/spiel_msgs).

Every channel carries, as rosbag2 (Jazzy and later) writes them, ``offered_qos_profiles`` (the
QoS the live publishers offer: reliable, keep last 10, volatile; /tf_static transient-local,
keep last 1, so `ros2 bag play` latches it) and ``topic_type_hash`` (RIHS01).
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

import numpy as np

from spiel_edge.messages import cdr, ros2_types
from spiel_edge.messages import ros2_messages as rm
from spiel_edge.recordings.mcap_reader import ACQUISITION_TOPIC, BACKGROUND_TOPIC, POSITION_TOPIC
from spiel_edge.recordings.mcap_writer import McapSink, json_default, stamp_ns_of

PREFIX = "/spiel"
POINT_TOPIC = "/spiel/point"
TARGETS_TOPIC = "/spiel/targets"
TF_STATIC_TOPIC = "/tf_static"


def topic_name(topic: str, prefix: str = PREFIX) -> str:
    """A TOPICS name (relative or absolute) -> the absolute topic."""
    return topic if topic.startswith("/") else f"{prefix}/{topic}"


TOPIC_TYPES = {
    ACQUISITION_TOPIC: cdr.ACQUISITION,
    BACKGROUND_TOPIC: cdr.ACQUISITION,
    POSITION_TOPIC: cdr.STRING,
    **{topic_name(t): type_name for t, type_name in rm.TOPICS.items()},
}
_INFINITE = "    sec: 9223372036\n    nsec: 854775807\n"


def qos_yaml(latched: bool) -> str:
    """rosbag2's ``offered_qos_profiles``: one publisher's QoS (rmw enums: history 1 keep
    last, reliability 1 reliable, durability 1 transient local / 2 volatile, liveliness 1
    automatic; infinite durations as rmw's RMW_DURATION_INFINITE)."""
    return (
        f"- history: 1\n  depth: {1 if latched else 10}\n  reliability: 1\n"
        f"  durability: {1 if latched else 2}\n"
        f"  deadline:\n{_INFINITE}  lifespan:\n{_INFINITE}"
        f"  liveliness: 1\n  liveliness_lease_duration:\n{_INFINITE}"
        "  avoid_ros_namespace_conventions: false"
    )


class Ros2McapSink(McapSink):
    """An McapSink whose channels are ROS 2 messages in CDR (profile ``ros2``)."""

    capabilities = frozenset({"acquisitions", "file", "status"})  # /diagnostics too

    profile = "ros2"

    def __init__(
        self,
        path: str | Path,
        *,
        frame_id: str = "spiel",
        transforms: list[cdr.StaticTransform] | tuple = (),
        ros2: Any = None,
        metadata: dict[str, Any] | None = None,
        transforms_now: bool = True,
        **options: Any,
    ):
        from spiel_edge.messages.settings import Ros2Settings

        if ros2 is None:
            ros2 = Ros2Settings(frame_id, tuple(transforms))
        self.messages = rm.Ros2Messages(ros2)
        self.encoder = self.messages.encoder.cdr
        super().__init__(path, metadata={**(metadata or {}), "frame_id": ros2.frame_id}, **options)
        self._transforms_written = False
        if transforms_now:
            self.write_transforms(time.time())

    def set_status_provider(self, provider) -> None:
        self.messages.status_provider = provider

    def write_transforms(self, stamp_s: float, transforms=None) -> None:
        """/tf_static once (latched by its QoS metadata): the mount and the optical frame."""
        if self._transforms_written:
            return
        self._transforms_written = True
        message = self.messages.tf_message(stamp_s)
        self._add(TF_STATIC_TOPIC, message, int(stamp_s * 1e9))

    def _register_channels(self) -> dict[str, int]:
        schemas = {
            name: self._writer.register_schema(
                name, "ros2msg", ros2_types.rosbag2_definition(name).encode()
            )
            for name in sorted(set(TOPIC_TYPES.values()))
        }
        return {
            topic: self._writer.register_channel(
                topic,
                "cdr",
                schemas[name],
                {
                    "offered_qos_profiles": qos_yaml(topic == TF_STATIC_TOPIC),
                    "topic_type_hash": ros2_types.type_hash(name),
                },
            )
            for topic, name in TOPIC_TYPES.items()
        }

    def write_acquisition(self, acquisition: dict, frames: np.ndarray) -> None:
        meta = {k: v for k, v in acquisition.items() if k not in ("frames", "background")}
        stamp = stamp_ns_of(meta)
        synced = meta.get("stamp_host_ns")  # the board's time on the host clock (protocol 2)
        if isinstance(synced, int) and synced > 0:
            stamp = synced
        seconds = stamp / 1e9 if stamp else None
        if not self._transforms_written:  # a replay: stamped with its first acquisition
            self.write_transforms(seconds or time.time())
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
        if not self._transforms_written:  # a replay: stamped with its first record
            self.write_transforms(seconds if stamp else time.time())
        for topic, message in self.messages.of_record(record):
            self._add(topic_name(topic), message, stamp)
        text = json.dumps(record, separators=(",", ":"), allow_nan=False, default=json_default)
        self._add(POSITION_TOPIC, cdr.string_message(text), stamp)
        self.counts["records"] += 1

    def _close(self) -> None:
        if not self.closed and not self._transforms_written:
            self.write_transforms(time.time())  # an empty recording has them too
        super()._close()
