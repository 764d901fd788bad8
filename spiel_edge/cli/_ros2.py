"""The ROS 2 options of `spiel-edge run` (one decorator; values go to open_outputs)."""

from __future__ import annotations

import click

from spiel_edge.outputs.ros2 import (
    DEFAULT_FRAME_ID,
    RECORD_PROFILES,
    ZENOH_ENCODINGS,
    settings,
)


def ros2_options(command):
    for option in reversed(
        [
            click.option(
                "--record-profile",
                type=click.Choice(RECORD_PROFILES),
                default="json",
                show_default=True,
                help="MCAP message encoding of --record: json (Foxglove, schemas in JSON) or "
                "ros2 (CDR: PointStamped, PointCloud2, /tf_static; read by rosbags, ros2 bag).",
            ),
            click.option(
                "--frame-id",
                default=DEFAULT_FRAME_ID,
                show_default=True,
                help="header.frame_id of the ROS 2 messages (the sensor frame).",
            ),
            click.option(
                "--static-tf",
                multiple=True,
                metavar="PARENT:X,Y,Z[,R,P,Y]",
                help="Pose of the sensor frame in a robot frame (metres, radians), published on "
                "/tf_static by the ros2 recording and Zenoh cdr (repeatable).",
            ),
            click.option(
                "--zenoh-encoding",
                type=click.Choice(ZENOH_ENCODINGS),
                default="json",
                show_default=True,
                help="json: each record on KEY; cdr: ROS 2 messages on KEY/point, KEY/targets "
                "and tf_static (the keys zenoh-bridge-ros2dds maps to /KEY/point, ...).",
            ),
        ]
    ):
        command = option(command)
    return command


def ros2_output_options(values: dict) -> dict:
    """open_outputs keyword arguments from the options' values (ConfigError when bad)."""
    return {
        "record_profile": values["record_profile"],
        "zenoh_encoding": values["zenoh_encoding"],
        "ros2": settings(values["frame_id"], tuple(values["static_tf"])),
    }
