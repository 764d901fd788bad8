"""ROS 2 without rclpy: CDR messages read back by rosbags, ros2-profile MCAP recordings."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

rosbags = pytest.importorskip("rosbags", reason="rosbags is in the 'test' extra")
from rosbags.highlevel import AnyReader  # noqa: E402
from rosbags.typesys import Stores, get_typestore  # noqa: E402

from spiel_edge.cli import main  # noqa: E402
from spiel_edge.data import load_subset  # noqa: E402
from spiel_edge.errors import ConfigError  # noqa: E402
from spiel_edge.messages import cdr, ros2_types  # noqa: E402
from spiel_edge.outputs.ros2 import parse_static_tf, settings  # noqa: E402
from spiel_edge.recordings.mcap_reader import iter_mcap_recordings  # noqa: E402
from spiel_edge.recordings.ros2_mcap import Ros2McapSink  # noqa: E402

STAMP = 1_796_097_713.156419
TARGETS = [
    {
        "position_mm": [10.0, -20.0, 150.0],
        "covariance_mm2": [[4.0, 0.1, 0], [0.1, 9.0, 0], [0, 0, 16.0]],
        "score": 0.9,
        "track_id": 7,
    },
    {
        "position_mm": [-5.0, 5.0, 90.0],
        "covariance_mm2": [[1, 0, 0], [0, 1, 0], [0, 0, 1]],
        "score": 0.2,
    },
]


@pytest.fixture(scope="module")
def typestore():
    return get_typestore(Stores.ROS2_HUMBLE)


@pytest.mark.parametrize("frame_id", ["spiel", "a", "base_link_sensor"])
def test_messages_decode_and_reencode_identically(typestore, frame_id):
    encoder = cdr.Ros2Encoder(frame_id)
    point = encoder.point_stamped([12.5, -3.0, 140.25], STAMP)
    message = typestore.deserialize_cdr(point, cdr.POINT_STAMPED)
    assert message.header.frame_id == frame_id
    assert (message.header.stamp.sec, message.header.stamp.nanosec) == (1796097713, 156419000)
    assert (message.point.x, message.point.y, message.point.z) == (0.0125, -0.003, 0.14025)
    assert typestore.serialize_cdr(message, cdr.POINT_STAMPED) == point  # byte-identical
    for targets in (TARGETS, []):
        cloud = encoder.targets_cloud(targets, STAMP)
        decoded = typestore.deserialize_cdr(cloud, cdr.POINT_CLOUD2)
        assert typestore.serialize_cdr(decoded, cdr.POINT_CLOUD2) == cloud
        assert decoded.width == len(targets) and decoded.header.frame_id == frame_id


def test_point_stamped_is_52_bytes_for_spiel():
    assert len(cdr.Ros2Encoder().point_stamped([1, 2, 3], 0.0)) == 52


def test_targets_cloud_fields(typestore):
    cloud = typestore.deserialize_cdr(
        cdr.Ros2Encoder().targets_cloud(TARGETS, STAMP), cdr.POINT_CLOUD2
    )
    names = [f.name for f in cloud.fields]
    assert names[:5] == ["x", "y", "z", "score", "track_id"]
    assert names[5:] == ["cov_xx", "cov_xy", "cov_xz", "cov_yy", "cov_yz", "cov_zz"]
    dtype = np.dtype(
        {
            "names": names,
            "formats": ["<f4"] * 4 + ["<i4"] + ["<f4"] * 6,
            "offsets": [f.offset for f in cloud.fields],
            "itemsize": cloud.point_step,
        }
    )
    points = np.frombuffer(cloud.data.tobytes(), dtype)
    np.testing.assert_allclose(points["z"], [0.150, 0.090], rtol=1e-6)
    assert points["track_id"].tolist() == [7, -1]
    np.testing.assert_allclose(points["cov_yy"], [9e-6, 1e-6], rtol=1e-6)
    np.testing.assert_allclose(points["cov_xy"], [1e-7, 0.0], rtol=1e-6)


def test_static_transform_flag(typestore):
    tf = parse_static_tf("base_link:0.1,0,0.25,0,0,1.5707963267948966")
    assert (tf.parent, tf.child, tf.translation_m) == ("base_link", "spiel", (0.1, 0.0, 0.25))
    np.testing.assert_allclose(tf.rotation_xyzw, [0, 0, math.sqrt(0.5), math.sqrt(0.5)])
    message = typestore.deserialize_cdr(cdr.Ros2Encoder().tf_message([tf], STAMP), cdr.TF_MESSAGE)
    assert message.transforms[0].child_frame_id == "spiel"
    assert message.transforms[0].header.frame_id == "base_link"
    for bad in ["base_link", "base_link:1,2", ":1,2,3", "spiel:1,2,3", "b:1,2,x"]:
        with pytest.raises(ConfigError):
            parse_static_tf(bad)
    with pytest.raises(ConfigError):
        settings("/spiel")


def test_recording_read_by_rosbags_and_replayed(tmp_path):
    subset = load_subset()
    path = tmp_path / "r.mcap"
    tf = parse_static_tf("base_link:0.1,0,0.2", "sonar")
    n = 50
    with Ros2McapSink(path, frame_id="sonar", transforms=[tf]) as sink:
        for i in range(n):
            acq = {
                "seq": i,
                "timestamp_ns": 1_000_000_000 * (i + 1),
                "background": subset.backgrounds[i],
            }
            sink.write_acquisition(acq, subset.frames[i])
            best = None if i % 10 == 3 else [float(i), 0.0, 100.0]
            first = [{"position_mm": best, "covariance_mm2": np.eye(3).tolist(), "score": 1.0}]
            targets = first + TARGETS[: i % 3] if best else []
            sink.write({"seq": i, "host_time": i + 1.0, "position_mm": best, "targets": targets})
    with AnyReader([path]) as reader:
        assert reader.connections  # profile ros2, CDR: rosbags accepts it
        points = [c for c in reader.connections if c.topic == "/spiel/point"]
        got = [
            reader.deserialize(raw, c.msgtype) for c, _t, raw in reader.messages(connections=points)
        ]
        assert len(got) == n - 5
        assert all(m.header.frame_id == "sonar_optical" for m in got)
        assert [m.point.x for m in got] == [i / 1e3 for i in range(n) if i % 10 != 3]
        assert got[0].header.stamp.sec == 1
        clouds = [c for c in reader.connections if c.topic == "/spiel/targets"]
        widths = [
            reader.deserialize(raw, c.msgtype).width
            for c, _t, raw in reader.messages(connections=clouds)
        ]
        assert widths == [0 if i % 10 == 3 else 1 + i % 3 for i in range(n)]
        statics = [c for c in reader.connections if c.topic == "/tf_static"]
        (tf_message,) = [
            reader.deserialize(raw, c.msgtype)
            for c, _t, raw in reader.messages(connections=statics)
        ]
        assert tf_message.transforms[0].transform.translation.x == 0.1
        assert [t.child_frame_id for t in tf_message.transforms] == ["sonar", "sonar_optical"]
        for connection in reader.connections:  # as rosbag2 writes them
            assert connection.ext.offered_qos_profiles
        records = [c for c in reader.connections if c.topic == "/spiel/position"]
        first = next(reader.messages(connections=records))
        assert json.loads(reader.deserialize(first[2], first[0].msgtype).data)["seq"] == 0
    with open(path, "rb") as f:
        from mcap.reader import make_reader

        summary = make_reader(f).get_summary()
    for channel in summary.channels.values():
        schema = summary.schemas[channel.schema_id]
        assert channel.metadata["topic_type_hash"] == ros2_types.type_hash(schema.name)
        latched = "durability: 1" in channel.metadata["offered_qos_profiles"]
        assert latched == (channel.topic == "/tf_static")
    recordings = list(iter_mcap_recordings(path))
    assert len(recordings) == n and all(r.error is None for r in recordings)
    for i, recording in enumerate(recordings):
        np.testing.assert_array_equal(recording.frames, subset.frames[i])
        np.testing.assert_array_equal(recording.background, subset.backgrounds[i])
    out = tmp_path / "out.ndjson"
    assert main(["replay", str(path), "--association", "geometric", "-o", str(out)]) == 0
    assert len(out.read_text().splitlines()) == n


def test_run_records_ros2_profile(tmp_path):
    path = tmp_path / "run.mcap"
    args = [
        "run",
        "--port",
        "sim://ros2",
        "--frames",
        "20",
        "--rate",
        "0",
        "-o",
        str(tmp_path / "o.ndjson"),
    ]
    args += ["--record", str(path), "--record-profile", "ros2", "--frame-id", "sonar"]
    mount = ["--parent-frame", "base_link", "--translation-m", "0,0,0.3"]
    assert main([*args, *mount]) == 0
    fixes = sum(
        json.loads(line)["position_mm"] is not None
        for line in (tmp_path / "o.ndjson").read_text().splitlines()
    )
    with AnyReader([path]) as reader:
        points = [c for c in reader.connections if c.topic == "/spiel/point"]
        assert sum(c.msgcount for c in points) == fixes > 0
        statics = [c for c in reader.connections if c.topic == "/tf_static"]
        (tf,) = [reader.deserialize(r, c.msgtype) for c, _t, r in reader.messages(statics)]
        assert [(t.header.frame_id, t.child_frame_id) for t in tf.transforms] == [
            ("base_link", "sonar"),
            ("sonar", "sonar_optical"),
        ]
        diagnostics = [c for c in reader.connections if c.topic == "/diagnostics"]
        first = next(reader.messages(diagnostics))
        (status,) = reader.deserialize(first[2], first[0].msgtype).status
        values = {kv.key: kv.value for kv in status.values}
        assert status.level == 0 and status.message == "streaming" and status.hardware_id
        assert {"records", "lost", "crc_errors", "reconnects", "firmware"} <= set(values)
        ranges = [c for c in reader.connections if c.topic == "/spiel/range"]
        assert sum(c.msgcount for c in ranges) == 20
    assert main(["replay", str(path), "-o", str(tmp_path / "replayed.ndjson")]) == 0
