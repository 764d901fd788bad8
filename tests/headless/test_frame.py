"""The sensor frame and its static transform: the profile's [frame] section, the options over
it, range checks with one-line errors naming the key or the option."""

from __future__ import annotations

import math

import numpy as np
import pytest

from spiel_edge.cli import main
from spiel_edge.errors import ConfigError
from spiel_edge.outputs.ros2 import frame_settings, parse_numbers
from spiel_edge.profile.frame_section import FrameSpec, quaternion_from_rpy
from spiel_edge.profile.schema import dump_toml, load_profile, profile_from_dict, profile_to_dict

HALF = math.sqrt(0.5)


def _profile(**frame):
    data = profile_to_dict(load_profile())
    data["frame"] = {**data["frame"], **frame}
    return profile_from_dict(data, origin="mounted.toml")


def test_builtin_profile_publishes_no_transform():
    profile = load_profile()
    assert profile.frame == FrameSpec()
    settings = frame_settings(profile.frame)
    assert (settings.frame_id, settings.transforms) == ("spiel", ())


def test_profile_frame_round_trips_and_gives_the_transform():
    profile = _profile(
        frame_id="sonar",
        parent="base_link",
        translation_m=[0.1, 0, 0.25],
        rotation_rpy_deg=[0, 0, 90],
    )
    again = profile_from_dict(profile_to_dict(profile))
    assert again.frame == profile.frame
    assert "[frame]" in dump_toml(profile_to_dict(profile))
    (tf,) = frame_settings(profile.frame).transforms
    assert (tf.parent, tf.child, tf.translation_m) == ("base_link", "sonar", (0.1, 0.0, 0.25))
    np.testing.assert_allclose(tf.rotation_xyzw, [0, 0, HALF, HALF], atol=1e-15)


def test_quaternion_is_normalized_and_matches_rpy():
    q = (0.0, 0.0, 0.70711, 0.70711)  # rounded digits: |q| = 1.000003
    (tf,) = frame_settings(_profile(parent="b", rotation_xyzw=list(q)).frame).transforms
    assert math.isclose(sum(v * v for v in tf.rotation_xyzw), 1.0, rel_tol=1e-12)
    np.testing.assert_allclose(tf.rotation_xyzw, [0, 0, HALF, HALF], atol=1e-12)
    # roll, then pitch, then yaw about fixed axes, as tf2's setRPY
    np.testing.assert_allclose(quaternion_from_rpy(math.pi / 2, 0, 0), [HALF, 0, 0, HALF])


def test_options_override_key_by_key():
    mounted = _profile(parent="base_link", translation_m=[0.1, 0, 0.2], rotation_xyzw=[0, 0, 0, 1])
    s = frame_settings(mounted.frame, frame_id="sonar", rotation_rpy_deg=(0.0, 0.0, 180.0))
    (tf,) = s.transforms
    assert (tf.parent, tf.child, tf.translation_m) == ("base_link", "sonar", (0.1, 0.0, 0.2))
    np.testing.assert_allclose(tf.rotation_xyzw, [0, 0, 1, 0], atol=1e-15)
    assert frame_settings(mounted.frame, parent="").transforms == ()  # "" drops it
    with pytest.raises(ConfigError, match="a frame has one parent in tf2"):
        frame_settings(mounted.frame, static_tf=("odom:0,0,1",))  # two parents of 'spiel'
    (alone,) = frame_settings(FrameSpec(), static_tf=("odom:0,0,1",)).transforms
    assert (alone.parent, alone.child, alone.translation_m) == ("odom", "spiel", (0.0, 0.0, 1.0))


@pytest.mark.parametrize(
    ("frame", "expected"),
    [
        ({"parent": "spiel"}, "mounted.toml: frame.parent is the sensor frame itself"),
        ({"translation_m": [0, 0, 1]}, "mounted.toml: frame.parent is needed"),
        ({"parent": "b", "translation_m": [0, 0, 101]}, "frame.translation_m must be 3 numbers"),
        ({"parent": "b", "translation_m": [0, 0]}, "frame.translation_m must be 3 numbers"),
        ({"parent": "b", "translation_m": [0, 0, float("nan")]}, "frame.translation_m"),
        ({"parent": "b", "rotation_rpy_deg": [0, 400, 0]}, "frame.rotation_rpy_deg must be"),
        ({"parent": "b", "rotation_xyzw": [0, 0, 0, 2]}, "frame.rotation_xyzw must be a unit"),
        ({"parent": "b", "rotation_xyzw": [0, 0, 1]}, "frame.rotation_xyzw must be a unit"),
        (
            {"parent": "b", "rotation_xyzw": [0, 0, 0, 1], "rotation_rpy_deg": [1, 0, 0]},
            "give one rotation",
        ),
        ({"frame_id": "/spiel"}, "frame.frame_id must be letters"),
        ({"frame_id": ""}, "frame.frame_id must be a non-empty"),
        ({"parent": "base link"}, "frame.parent must be letters"),
        ({"parent": 3}, "frame.parent must be str"),
    ],
)
def test_bad_profile_frames_are_one_line_errors(frame, expected):
    with pytest.raises(ConfigError) as info:
        _profile(**frame)
    assert expected in str(info.value) and "\n" not in str(info.value)


@pytest.mark.parametrize(
    ("given", "expected"),
    [
        ({"parent": "b", "translation_m": (0.0, 0.0, 250.0)}, "--translation-m must be"),
        ({"parent": "spiel"}, "--parent-frame is the sensor frame"),
        ({"frame_id": "a b"}, "--frame-id must be"),
        ({"parent": "b", "rotation_xyzw": (0.0, 0.0, 0.0, 0.0)}, "--rotation-xyzw must be"),
    ],
)
def test_bad_options_name_the_option(given, expected):
    with pytest.raises(ConfigError, match=expected):
        frame_settings(FrameSpec(), **given)


def test_option_numbers():
    assert parse_numbers("0.1, 0,2", 3, "--translation-m") == (0.1, 0.0, 2.0)
    assert parse_numbers(None, 3, "--translation-m") is None
    for bad in ("1,2", "1,2,x", "1,2,inf", ""):
        with pytest.raises(ConfigError, match="--translation-m"):
            parse_numbers(bad, 3, "--translation-m")


def test_run_checks_frame_options_before_the_board(capsys):
    args = ["run", "--port", "/dev/nonexistent-spiel", "--frames", "1", "--record-profile", "ros2"]
    assert main([*args, "--parent-frame", "b", "--rotation-rpy-deg", "0,720,0"]) == 2
    err = capsys.readouterr().err
    assert "--rotation-rpy-deg must be 3 numbers in [-360, 360]" in err and "nonexistent" not in err
