"""The ROS 2 options of `spiel-edge run` and `replay` (decorators; values go to the sinks).

The sensor frame and its static transform come from the profile's ``[frame]`` section; each
option given here overrides its key (profile/frame_section.py, docs/ros2.md).
"""

from __future__ import annotations

import click

from spiel_edge.outputs.rmw_zenoh.wire import ROS_DISTROS
from spiel_edge.outputs.ros2 import RECORD_PROFILES, ZENOH_ENCODINGS, ZENOH_MODES
from spiel_edge.outputs.ros2_options import (  # noqa: F401  (the commands' names for them)
    ros2_output_options,
    ros2_settings,
    zenoh_settings,
)

_RECORD_PROFILE = click.option(
    "--record-profile",
    type=click.Choice(RECORD_PROFILES),
    default="json",
    show_default=True,
    help="MCAP message encoding: json (Foxglove, schemas in JSON) or ros2 (CDR: point, "
    "targets, tracks, range, /diagnostics, /tf_static; read by rosbags, ros2 bag).",
)
_FRAME = [
    click.option(
        "--frame-id",
        default=None,
        help="header.frame_id of the ROS 2 messages, the sensor frame (default: the profile's "
        "[frame] frame_id, 'spiel').",
    ),
    click.option(
        "--parent-frame",
        default=None,
        metavar="FRAME",
        help="Robot frame the sensor is mounted on: publishes FRAME -> frame id on /tf_static "
        "(default: the profile's [frame] parent).",
    ),
    click.option(
        "--translation-m",
        default=None,
        metavar="X,Y,Z",
        help="Sensor origin in the parent frame, metres (default: the profile's).",
    ),
    click.option(
        "--rotation-rpy-deg",
        default=None,
        metavar="R,P,Y",
        help="Sensor axes in the parent frame: roll about X, pitch about Y, yaw about Z "
        "(fixed axes, tf2 setRPY), degrees.",
    ),
    click.option(
        "--rotation-xyzw",
        default=None,
        metavar="X,Y,Z,W",
        help="Sensor axes in the parent frame as a unit quaternion (instead of the angles).",
    ),
    click.option(
        "--static-tf",
        multiple=True,
        metavar="PARENT:X,Y,Z[,R,P,Y]",
        help="The sensor frame's pose in a robot frame (metres, radians), on /tf_static, "
        "instead of --parent-frame (tf2 gives a frame one parent).",
    ),
]
_ZENOH = [
    click.option(
        "--zenoh-encoding",
        type=click.Choice(ZENOH_ENCODINGS),
        default="json",
        show_default=True,
        help="json: each record on KEY; rmw_zenoh: ROS 2 topics /KEY/point, /KEY/targets, "
        "/KEY/tracks, /KEY/range, /diagnostics, /tf_static as ROS 2 nodes with "
        "RMW_IMPLEMENTATION=rmw_zenoh_cpp see them; cdr: the same messages on the plain keys "
        "zenoh-bridge-ros2dds maps (KEY/point, ..., tf_static).",
    ),
    click.option(
        "--zenoh-connect",
        multiple=True,
        metavar="ENDPOINT",
        help="Zenoh router or peer to connect to, e.g. tcp/127.0.0.1:7447 (rmw_zenohd's "
        "default); repeatable. The run goes on while it is unreachable.",
    ),
    click.option(
        "--zenoh-mode",
        type=click.Choice(ZENOH_MODES),
        default=None,
        help="Zenoh session mode: peer (rmw_zenoh's own) or client (through the router only); "
        "default peer, or the ZENOH_CONFIG file's.",
    ),
    click.option(
        "--zenoh-auth-key",
        default=None,
        metavar="FILE",
        help="Tag each JSON record with this board's secret (hex; `openssl rand -hex 32`), "
        "so `fuse` knows it is this board's (its robot file's auth_key_file; "
        "docs/security.md).",
    ),
    click.option(
        "--ros-distro",
        type=click.Choice(ROS_DISTROS),
        default=None,
        help="ROS 2 distribution of the rmw_zenoh nodes that listen (--zenoh-encoding "
        "rmw_zenoh): humble writes TypeHashNotSupported where the others write type hashes "
        "(default $ROS_DISTRO when it is one of these, else jazzy; docs/ros2.md).",
    ),
    click.option(
        "--ros-domain-id",
        default=None,
        metavar="N",
        help="ROS domain of --zenoh-encoding rmw_zenoh, 0-232 (default $ROS_DOMAIN_ID or 0).",
    ),
]


def _apply(command, options: list):
    for option in reversed(options):
        command = option(command)
    return command


def ros2_options(command):
    """`run`: the recording's profile, the frame options and the Zenoh encoding."""
    return _apply(command, [_RECORD_PROFILE, *_FRAME, *_ZENOH])


def ros2_record_options(command):
    """`replay`: the MCAP output's profile and the frame options."""
    return _apply(command, [_RECORD_PROFILE, *_FRAME])
