"""ROS 2 Humble: its rmw_zenoh (0.1.x) writes TypeHashNotSupported where later distributions
write RIHS01 type hashes, in data keys and liveliness tokens; ``--ros-distro humble``."""

from __future__ import annotations

import time

import pytest

from spiel_edge.errors import ConfigError
from spiel_edge.outputs.rmw_zenoh import wire
from spiel_edge.outputs.ros2 import frame_settings
from spiel_edge.profile.frame_section import FrameSpec
from tests.headless.test_rmw_zenoh import RECORD, _config, _settings, _wait, router  # noqa: F401


def test_distro_type_hash():
    rihs = "RIHS01_" + "ab" * 32
    assert wire.distro_type_hash("jazzy", rihs) == rihs
    assert wire.distro_type_hash("rolling", rihs) == rihs
    assert wire.distro_type_hash("humble", rihs) == "TypeHashNotSupported"
    with pytest.raises(ConfigError, match="iron"):
        wire.distro_type_hash("iron", rihs)
    key = wire.topic_key(
        0, "/spiel/point", "geometry_msgs::msg::dds_::PointStamped_", "TypeHashNotSupported"
    )
    assert wire.parse_topic_key(key)[3] == "TypeHashNotSupported"


def test_the_distro_comes_from_the_option_then_ros_distro(monkeypatch):
    from spiel_edge.cli._ros2 import zenoh_settings

    monkeypatch.setenv("ROS_DISTRO", "humble")
    assert zenoh_settings({"zenoh_encoding": "rmw_zenoh"}).ros_distro == "humble"
    assert zenoh_settings({"ros_distro": "kilted"}).ros_distro == "kilted"
    monkeypatch.setenv("ROS_DISTRO", "iron")  # no rmw_zenoh there: the default format
    assert zenoh_settings({}).ros_distro == "jazzy"
    monkeypatch.delenv("ROS_DISTRO")
    assert zenoh_settings({}).ros_distro == "jazzy"


@pytest.mark.parametrize("distro", ["humble", "jazzy"])
def test_a_humble_subscriber_receives_only_the_humble_format(router, distro):  # noqa: F811
    from dataclasses import replace

    from spiel_edge.outputs.rmw_zenoh.sink import RmwZenohSink
    from tests.headless._rmw_zenoh_listener import Listener

    zenoh, port, _router = router
    settings = replace(_settings(port), ros_distro=distro)
    sink = RmwZenohSink("spiel", frame_settings(FrameSpec()), settings)
    client = zenoh.open(_config(zenoh, "client", connect=port))
    try:
        listener = Listener(client, domain=7, humble=True).start()
        assert _wait(lambda: "/spiel/point" in listener.publishers())
        point = listener.publishers()["/spiel/point"]
        humble_key = "7/spiel/point/geometry_msgs::msg::dds_::PointStamped_/TypeHashNotSupported"
        got = []
        exact = client.declare_subscriber(humble_key, lambda s: got.append(s))  # as Humble does
        time.sleep(0.3)
        for i in range(10):
            sink.write({**RECORD, "host_time": RECORD["host_time"] + 0.02 * i})
        if distro == "humble":
            assert point.type_hash == "TypeHashNotSupported"
            assert _wait(lambda: len(got) == 10)
            assert _wait(lambda: len(listener.received("/spiel/point")) == 10)
            assert not listener.problems, listener.problems[:3]
        else:  # the Jazzy format: a Humble node lists the topic and receives nothing
            assert point.type_hash.startswith("RIHS01_")
            time.sleep(1.0)
            assert got == []
        exact.undeclare()
    finally:
        client.close()
        sink.close()
