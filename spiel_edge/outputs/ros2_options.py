"""The outputs' ROS 2 and Zenoh settings from option values (`run`'s and `replay`'s options,
cli/_ros2.py, or a library run's, runtime/live.py): a key left out is the option's default.

The sensor frame and its static transform come from the profile's ``[frame]`` section; each
value given here overrides its key (profile/frame_section.py, docs/ros2.md).
"""

from __future__ import annotations

import os

from spiel_edge.outputs.rmw_zenoh.wire import DEFAULT_DISTRO, ROS_DISTROS
from spiel_edge.outputs.ros2 import Ros2Settings, ZenohSettings, frame_settings, parse_numbers


def ros2_settings(values: dict, profile) -> Ros2Settings:
    """The frame id and static transforms: the profile's [frame] with the options over it
    (ConfigError naming the option or key that is wrong)."""
    from spiel_edge.messages.ros2_limits import SensorLimits

    return frame_settings(
        profile.frame,
        tuple(values.get("static_tf") or ()),
        origin=profile.name,
        limits=SensorLimits.of_profile(profile),
        frame_id=values.get("frame_id"),
        parent=values.get("parent_frame"),
        translation_m=parse_numbers(values.get("translation_m"), 3, "--translation-m"),
        rotation_rpy_deg=parse_numbers(values.get("rotation_rpy_deg"), 3, "--rotation-rpy-deg"),
        rotation_xyzw=parse_numbers(values.get("rotation_xyzw"), 4, "--rotation-xyzw"),
    )


def ros2_output_options(values: dict, profile) -> dict:
    """open_outputs keyword arguments from the options' values (ConfigError when bad)."""
    return {
        "record_profile": values.get("record_profile", "json"),
        "zenoh_encoding": values.get("zenoh_encoding", "json"),
        "ros2": ros2_settings(values, profile),
        "zenoh_settings": zenoh_settings(values),
    }


def zenoh_settings(values: dict) -> ZenohSettings:
    """Mode, endpoints and ROS domain; ConfigError on a bad endpoint or domain id."""
    from spiel_edge.outputs.rmw_zenoh.wire import check_domain_id
    from spiel_edge.outputs.zenoh import check_endpoint

    given = values.get("ros_domain_id")
    if given is not None:
        domain = check_domain_id(given)
    elif values.get("zenoh_encoding") == "rmw_zenoh":  # $ROS_DOMAIN_ID matters only there
        domain = check_domain_id(os.environ.get("ROS_DOMAIN_ID") or 0, "ROS_DOMAIN_ID")
    else:
        domain = 0
    connect = tuple(check_endpoint(e) for e in values.get("zenoh_connect") or ())
    auth_key = None
    if values.get("zenoh_auth_key"):
        from spiel_edge.errors import ConfigError
        from spiel_edge.outputs.record_auth import load_key

        if values.get("zenoh_encoding", "json") != "json":
            raise ConfigError(
                "--zenoh-auth-key tags JSON records (what `fuse` reads): "
                "not with --zenoh-encoding " + str(values.get("zenoh_encoding"))
            )
        auth_key = load_key(values["zenoh_auth_key"], "--zenoh-auth-key")
    distro = values.get("ros_distro") or os.environ.get("ROS_DISTRO", "").strip().lower()
    if distro not in ROS_DISTROS:  # unset, or a distribution without rmw_zenoh (iron, ...)
        distro = DEFAULT_DISTRO
    return ZenohSettings(
        values.get("zenoh_mode") or "", connect, domain, auth_key=auth_key, ros_distro=distro
    )
