"""Where the robot's odometry comes from: a recording (:func:`read_odometry_file`: a rosbag2
MCAP or NDJSON) or a Zenoh key (:class:`OdometrySubscription`); the messages and the buffer
are robot/odometry.py's."""

from __future__ import annotations

import contextlib
import os
import time
from collections.abc import Callable
from pathlib import Path

from spiel_edge.errors import ConfigError, InputError
from spiel_edge.robot.odometry import OdometryBuffer, parse_odometry

ODOM_TOPIC = "/odom"  # ROS's name for the robot's odometry


def read_odometry_file(path: str | Path, topic: str = ODOM_TOPIC) -> OdometryBuffer:
    """Every pose of a recording, in time order: an MCAP (the messages on ``topic``:
    rosbag2's nav_msgs/msg/Odometry in CDR, or the JSON message; a damaged file is read as far
    as it goes) or NDJSON lines of the JSON message. Each pose needs its stamp. InputError
    naming the file and what is wrong."""
    path = Path(path)
    try:
        with open(path, "rb") as f:
            if f.read(8).startswith(b"\x89MCAP"):
                messages = _mcap_messages(f, topic, path)
            else:
                f.seek(0)
                messages = [line for line in f.read().splitlines() if line.strip()]
    except OSError as exc:
        raise InputError(f"{path}: cannot read the odometry: {exc.strerror or exc}") from exc
    poses = []
    for n, payload in enumerate(messages, 1):
        try:
            stamp, x, y, yaw = parse_odometry(payload)
        except InputError as exc:
            raise InputError(f"{path}: odometry message {n}: {exc}") from exc
        if stamp is None:
            raise InputError(f"{path}: odometry message {n} has no stamp")
        poses.append((stamp, 1000.0 * x, 1000.0 * y, yaw))
    buffer = OdometryBuffer(max_poses=None)
    for pose in sorted(poses):
        buffer.add(*pose)  # a repeated stamp is kept once
    if not len(buffer):
        raise InputError(f"{path}: no odometry in it")
    return buffer


def _mcap_messages(f, topic: str, path: Path) -> list[bytes]:
    from spiel_edge.recordings.mcap_scan import McapScanner

    scanner = McapScanner(f, os.fstat(f.fileno()).st_size)
    messages, topics = [], set()
    for msg in scanner.messages():
        topics.add(msg.topic or "?")
        if msg.topic == topic:
            messages.append(msg.data)
    if not messages:
        seen = ", ".join(sorted(topics)) or "none"
        raise InputError(f"{path}: no messages on {topic} (topics: {seen}; --odom-topic)")
    return messages


class OdometrySubscription:
    """A Zenoh subscriber on ``key`` handing each message and its arrival (Unix s) to
    ``deliver`` (from Zenoh's thread: hand over, nothing more); its own session, from
    ``$ZENOH_CONFIG`` or Zenoh's defaults. ConfigError when it cannot subscribe."""

    def __init__(self, key: str, deliver: Callable[[bytes, float], None]):
        from spiel_edge.outputs.zenoh import import_zenoh
        from spiel_edge.robot.zenoh_fuse import zenoh_config

        zenoh = import_zenoh()
        self.session = None
        try:
            self.session = zenoh.open(zenoh_config())
            self.session.declare_subscriber(
                key, lambda sample: deliver(sample.payload.to_bytes(), time.time())
            )
        except Exception as exc:  # zenoh.ZError
            self.close()
            raise ConfigError(f"--odom {key}: cannot subscribe on Zenoh: {exc}") from exc

    def close(self) -> None:
        if self.session is not None:
            with contextlib.suppress(Exception):  # zenoh.ZError on a closing session
                self.session.close()
            self.session = None
