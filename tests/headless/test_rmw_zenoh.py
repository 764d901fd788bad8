"""ROS 2 without ROS: type hashes, the rmw_zenoh wire format, and a loopback Zenoh graph seen
by a test-only subscriber that receives as rmw_zenoh does (_rmw_zenoh_listener.py)."""

from __future__ import annotations

import json
import logging
import math
import re
import socket
import time
from pathlib import Path

import numpy as np
import pytest

rosbags = pytest.importorskip("rosbags", reason="rosbags is in the 'test' extra")
from rosbags.typesys import Stores, get_typestore  # noqa: E402
from rosbags.typesys.msg import get_types_from_msg  # noqa: E402

from spiel_edge.cli import main  # noqa: E402
from spiel_edge.errors import ConfigError  # noqa: E402
from spiel_edge.messages import ros2_messages as rm  # noqa: E402
from spiel_edge.messages import ros2_types  # noqa: E402
from spiel_edge.outputs.rmw_zenoh import wire  # noqa: E402
from spiel_edge.outputs.ros2 import Ros2Settings, ZenohSettings, frame_settings  # noqa: E402
from spiel_edge.profile.frame_section import FrameSpec  # noqa: E402

REPO = Path(__file__).resolve().parents[2]
STAMP = 1_796_097_713.156419
TARGETS = [
    {
        "position_mm": [10.0, -20.0, 150.0],
        "covariance_mm2": [[4.0, 0.1, 0.3], [0.1, 9.0, -0.2], [0.3, -0.2, 16.0]],
        "score": 0.9,
        "track_id": 7,
    },
    {"position_mm": [-5.0, 5.0, 90.0], "covariance_mm2": np.eye(3).tolist(), "score": -2.0},
]
GARBAGE = [
    {"position_mm": [3.0, 4.0, 0.5], "covariance_mm2": np.eye(3).tolist(), "score": 1.0},  # z~0
    {"position_mm": [0.0, 0.0, 200.0], "covariance_mm2": np.eye(3).tolist(), "score": -500.0},
    {"position_mm": [0.0, 0.0, 200.0], "covariance_mm2": (np.eye(3) * 4e8).tolist(), "score": 1},
    {"position_mm": [0.0, 0.0, -200.0], "covariance_mm2": np.eye(3).tolist(), "score": 1.0},
    {"position_mm": [0.0, 0.0, 900.0], "covariance_mm2": np.eye(3).tolist(), "score": 1.0},
    {"position_mm": [0.0, 0.0, math.nan], "covariance_mm2": np.eye(3).tolist(), "score": 1.0},
]
TRACKS = [
    {
        "track_id": 3,
        "position_mm": [1.0, 2.0, 100.0],
        "velocity_mm_s": [10.0, 0.0, -5.0],
        "covariance_mm2": [[4.0, 0.1, 0.0], [0.1, 9.0, 0.2], [0.0, 0.2, 16.0]],
        "velocity_covariance_mm2_s2": [[40.0, 1.0, 0.0], [1.0, 90.0, 2.0], [0.0, 2.0, 160.0]],
    },
    {"track_id": 4, "position_mm": [1.0, 2.0, 100.0], "velocity_mm_s": [0.0, 0.0, 0.0]},
]
RECORD = {"host_time": STAMP, "position_mm": [10.0, -20.0, 150.0], "targets": TARGETS + GARBAGE}


def _store(store=Stores.ROS2_JAZZY):
    from tests.headless._rmw_zenoh_listener import typestore

    return typestore(store)


# --- type hashes and definitions -----------------------------------------------------------


@pytest.mark.parametrize("store", [Stores.ROS2_JAZZY, Stores.ROS2_KILTED, Stores.ROS2_LYRICAL])
def test_type_hashes_match_rosbags_for_each_distribution(store):
    ts = get_typestore(store)
    standard = [t for t in ros2_types.MSG if t in ts.fielddefs]
    assert "sensor_msgs/msg/Range" in standard and "diagnostic_msgs/msg/DiagnosticArray" in standard
    for name in standard:
        assert ros2_types.type_hash(name) == ts.hash_rihs01(name), name
    # rmw_zenoh's design document's example key for /chatter
    assert ros2_types.type_hash("std_msgs/msg/String") == (
        "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"
    )


def test_own_and_radar_types_hash_as_rosbags_hashes_their_definitions():
    ts = get_typestore(Stores.ROS2_JAZZY)
    types = {}
    for name in ("radar_msgs/msg/RadarTrack", "radar_msgs/msg/RadarTracks", *ros2_types.SPIEL_MSGS):
        types.update(get_types_from_msg(ros2_types.MSG[name], name))
    ts.register(types)
    for name in ("radar_msgs/msg/RadarTracks", *ros2_types.SPIEL_MSGS):
        assert ros2_types.type_hash(name) == ts.hash_rihs01(name), name
    # the listener's upstream radar_msgs definition (its own copy) gives the same hash
    assert ros2_types.type_hash("radar_msgs/msg/RadarTracks") == _store().hash_rihs01(
        "radar_msgs/msg/RadarTracks"
    )


def test_spiel_msgs_package_is_what_the_recordings_carry():
    package = REPO / "packaging" / "ros2" / "spiel_msgs"
    for name in ros2_types.SPIEL_MSGS:
        text = (package / "msg" / f"{name.split('/')[-1]}.msg").read_text()
        lines = [line.split("#")[0].strip() for line in text.splitlines()]
        fields = [" ".join(line.split()) for line in lines if line]
        assert fields == ros2_types.MSG[name].splitlines()
        assert ros2_types.type_hash(name) in text
        assert ros2_types.type_hash(name) in (package / "README.md").read_text()
    cmake = (package / "CMakeLists.txt").read_text()
    assert "rosidl_generate_interfaces" in cmake and '"msg/Acquisition.msg"' in cmake
    assert (
        "<member_of_group>rosidl_interface_packages</member_of_group>"
        in (package / "package.xml").read_text()
    )


def test_rosbag2_definitions_parse_in_rosbags_and_mcap_ros2():
    from mcap_ros2._dynamic import generate_dynamic

    for name in set(rm.TOPICS.values()) | set(ros2_types.SPIEL_MSGS):
        text = ros2_types.rosbag2_definition(name)
        assert generate_dynamic(name, text)  # mcap-ros2-support's parser
        assert text.startswith(ros2_types.MSG[name])


# --- the messages -------------------------------------------------------------------------


@pytest.mark.parametrize("frame_id", ["spiel", "a", "ab", "abc", "base_sonar_optical"])
def test_every_message_reencodes_byte_for_byte_with_rosbags(frame_id):
    ts = _store()
    messages = rm.Ros2Messages(Ros2Settings(frame_id))
    out = messages.of_record({**RECORD, "tracks": TRACKS})
    assert [name for name, _ in out] == ["point", "targets", "tracks", "range", "/diagnostics"]
    for name, data in [*out, ("/tf_static", messages.tf_message(STAMP))]:
        type_name = rm.TOPICS[name]
        message = ts.deserialize_cdr(data, type_name)
        assert ts.serialize_cdr(message, type_name) == data, name
        header = getattr(message, "header", None)
        if header is not None:
            assert header.frame_id == rm.optical_frame(frame_id)
            assert (header.stamp.sec, header.stamp.nanosec) == (1796097713, 156419000)


def test_targets_cloud_has_the_full_covariance_and_drops_what_is_not_a_target():
    ts = _store()
    messages = rm.Ros2Messages(Ros2Settings())
    out = dict(messages.of_record(RECORD))
    cloud = ts.deserialize_cdr(out["targets"], rm.POINT_CLOUD2)
    names = [f.name for f in cloud.fields]
    assert names == [
        "x", "y", "z", "score", "track_id", "cov_xx", "cov_xy", "cov_xz", "cov_yy", "cov_yz",
        "cov_zz",
    ]  # fmt: skip
    assert cloud.point_step == 44 and cloud.width == 2 and cloud.is_dense
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
    cov = TARGETS[0]["covariance_mm2"]
    upper = [cov[0][0], cov[0][1], cov[0][2], cov[1][1], cov[1][2], cov[2][2]]
    got = [points[n][0] for n in names[5:]]
    np.testing.assert_allclose(got, np.array(upper) / 1e6, rtol=1e-6)
    assert messages.counts["dropped_targets"] == len(GARBAGE)
    # nothing publishable: no point, an empty cloud, range +inf
    bad = dict(messages.of_record({"host_time": STAMP, "targets": GARBAGE}))
    assert "point" not in bad
    assert ts.deserialize_cdr(bad["targets"], rm.POINT_CLOUD2).width == 0
    assert math.isinf(ts.deserialize_cdr(bad["range"], rm.RANGE).range)


def test_range_tracks_and_diagnostics_content():
    ts = _store()
    status = {"name": "spiel-edge: b", "hardware_id": "SN1", "level": 1, "values": {"lost": 3}}
    messages = rm.Ros2Messages(Ros2Settings(), status_provider=lambda: status)
    out = dict(messages.of_record({**RECORD, "tracks": TRACKS}))
    rng = ts.deserialize_cdr(out["range"], rm.RANGE)
    assert rng.radiation_type == 0  # ULTRASOUND
    assert rng.range == pytest.approx(math.sqrt(5**2 + 5**2 + 90**2) / 1e3, rel=1e-6)
    assert rng.field_of_view == pytest.approx(math.pi)
    assert (rng.min_range, rng.max_range) == pytest.approx((0.0702, 0.4989), rel=1e-6)
    assert rng.variance == pytest.approx(1e-6, rel=1e-5)  # unit covariance, mm^2 -> m^2
    tracks = ts.deserialize_cdr(out["tracks"], rm.RADAR_TRACKS).tracks
    assert len(tracks) == 2 and bytes(tracks[0].uuid.uuid) == rm.track_uuid(3)
    assert bytes(tracks[0].uuid.uuid) != bytes(tracks[1].uuid.uuid)
    assert (tracks[0].velocity.x, tracks[0].velocity.z) == (0.01, -0.005)
    np.testing.assert_allclose(
        tracks[0].velocity_covariance, np.array([40, 1, 0, 90, 2, 160]) / 1e6, rtol=1e-6
    )
    assert np.isnan(tracks[1].position_covariance).all()
    (diag,) = ts.deserialize_cdr(out["/diagnostics"], rm.DIAGNOSTIC_ARRAY).status
    assert (diag.level, diag.name, diag.hardware_id) == (1, "spiel-edge: b", "SN1")
    values = {kv.key: kv.value for kv in diag.values}
    assert values["lost"] == "3" and values["dropped_targets"] == str(len(GARBAGE))
    # 1 Hz of record time: not again within the second, again after it
    later = messages.of_record({**RECORD, "host_time": STAMP + 0.5})
    assert "/diagnostics" not in dict(later)
    assert "/diagnostics" in dict(messages.of_record({**RECORD, "host_time": STAMP + 1.01}))


def test_optical_frame_follows_rep_103():
    settings = frame_settings(FrameSpec(parent="base_link", translation_m=(0.1, 0.0, 0.25)))
    messages = rm.Ros2Messages(settings)
    mount, optical = messages.transforms
    assert (mount.parent, mount.child) == ("base_link", "spiel")
    assert (optical.parent, optical.child) == ("spiel", "spiel_optical")
    x, y, z, w = optical.rotation_xyzw
    rot = np.array(  # rotation matrix of the quaternion: columns = optical axes in spiel
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )
    # the boresight (optical z) is spiel's x (REP 103 forward); optical x right, y down
    np.testing.assert_allclose(rot @ [0, 0, 1], [1, 0, 0], atol=1e-12)
    np.testing.assert_allclose(rot @ [1, 0, 0], [0, -1, 0], atol=1e-12)
    np.testing.assert_allclose(rot @ [0, 1, 0], [0, 0, -1], atol=1e-12)


# --- the wire format ----------------------------------------------------------------------


def test_wire_format_as_the_design_document_shows_it():
    # the design document's talker: depth 7, everything else default
    assert wire.qos_to_keyexpr(wire.Qos(depth=7)) == "::,7:,:,:,,"
    assert wire.qos_to_keyexpr(wire.LATCHED_QOS) == ":1:,1:,:,:,,"
    assert wire.keyexpr_to_qos(":1:,1:,:,:,,") == wire.LATCHED_QOS
    zid = "8b20917502ee955ac4476e0266340d5c"
    hash_ = ros2_types.type_hash("std_msgs/msg/String")
    token = wire.publisher_token(
        2, zid, 0, 10, "/", "talker", "/chatter", "std_msgs::msg::dds_::String_", hash_,
        wire.Qos(depth=7),
    )  # fmt: skip
    assert token == (
        f"@ros2_lv/2/{zid}/0/10/MP/%/%/talker/%chatter/std_msgs::msg::dds_::String_/{hash_}"
        "/::,7:,:,:,,"
    )
    assert wire.node_token(2, zid, 0, "/", "listener") == f"@ros2_lv/2/{zid}/0/0/NN/%/%/listener"
    assert wire.topic_key(0, "/robot1/chatter", "std_msgs::msg::dds_::String_", hash_) == (
        f"0/robot1/chatter/std_msgs::msg::dds_::String_/{hash_}"
    )
    parsed = wire.parse_token(token)
    assert (parsed.topic, parsed.node, parsed.qos.depth) == ("/chatter", "talker", 7)
    gid = wire.gid_of(token)
    data = wire.attachment(5, 1_700_000_000_123_456_789, gid)
    assert len(data) == 33 and data[16] == 16
    assert wire.parse_attachment(data) == (5, 1_700_000_000_123_456_789, gid)
    with pytest.raises(ValueError):
        wire.parse_attachment(data[:-1])


@pytest.mark.parametrize(
    "topic",
    ["spiel/x", "/spiel/", "/spiel//x", "/1spiel/x", "/spiel/x-y", "/spiel/ x", "/" + "a" * 250],
)
def test_topic_names_ros_rejects(topic):
    assert wire.topic_name_problem(topic)
    with pytest.raises(ConfigError, match="ROS 2 topic"):
        wire.check_topic(topic, "--zenoh")


@pytest.mark.parametrize("bad", ["-1", "233", "x", "1.5", ""])
def test_domain_ids_out_of_range(bad):
    with pytest.raises(ConfigError, match="0-232"):
        wire.check_domain_id(bad)
    assert wire.check_domain_id("232") == 232


@pytest.mark.parametrize(
    "args, message",
    [
        (["--zenoh", "robot 1", "--zenoh-encoding", "rmw_zenoh"], "ROS 2 topic"),
        (["--zenoh", "spiel", "--zenoh-encoding", "rmw_zenoh", "--ros-domain-id", "300"], "0-232"),
        (["--zenoh", "spiel", "--zenoh-connect", "localhost:7447"], "--zenoh-connect"),
        (["--frame-id", "/sonar"], "--frame-id"),
        (["--zenoh", "spiel", "--zenoh-connect", "tcp/127.0.0.1:99999"], "--zenoh-connect"),
        (["--zenoh", "spiel", "--zenoh-connect", "tcp/[::1"], "--zenoh-connect"),
        (["--zenoh", "robot/*"], "holds a wildcard"),
        (["--static-tf", "/base:1,2,3"], "the parent frame must be"),
        (["--static-tf", "base:1e308,0,0"], "X, Y, Z must be in"),
        (["--static-tf", "spiel_optical:0,0,0"], "the sensor's own"),
        (["--parent-frame", "spiel_optical"], "the sensor's own optical frame"),
        (["--static-tf", "base:0,0,0", "--static-tf", "base:1,0,0"], "a frame has one parent"),
    ],
)
def test_bad_ros_options_fail_at_start_in_one_line(args, message, tmp_path, capsys, monkeypatch):
    pytest.importorskip("zenoh", reason="extra 'zenoh' not installed")
    monkeypatch.delenv("ROS_DOMAIN_ID", raising=False)
    out = tmp_path / "o.ndjson"
    code = main(["run", "--port", "sim://", "--frames", "3", "-o", str(out), *args])
    err = capsys.readouterr().err.strip()
    assert code != 0 and message in err and len(err.splitlines()) == 1, err
    assert not out.exists() or out.read_text() == ""


@pytest.mark.parametrize("encoding", ["json", "cdr", "rmw_zenoh"])
def test_a_bad_zenoh_key_is_refused_before_the_board(encoding, tmp_path, capsys):
    """The key is checked with the other options: the missing board is never reached."""
    args = ["run", "--port", str(tmp_path / "no-tty"), "--frames", "3", "-o", str(tmp_path / "o")]
    assert main([*args, "--zenoh", "a//b", "--zenoh-encoding", encoding]) == 2
    err = capsys.readouterr().err
    assert "--zenoh 'a//b'" in err and "no-tty" not in err, err


# --- over Zenoh, on loopback --------------------------------------------------------------


def _port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _config(zenoh, mode: str, *, listen: int | None = None, connect: int | None = None):
    c = {"mode": mode, "scouting": {"multicast": {"enabled": False}}}
    if listen is not None:
        c["listen"] = {"endpoints": [f"tcp/127.0.0.1:{listen}"]}
    if connect is not None:
        c["connect"] = {"endpoints": [f"tcp/127.0.0.1:{connect}"]}
    return zenoh.Config.from_json5(json.dumps(c))


def _wait(predicate, timeout: float = 10.0) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.02)
    return predicate()


@pytest.fixture
def router():
    zenoh = pytest.importorskip("zenoh", reason="extra 'zenoh' not installed")
    port = _port()
    session = zenoh.open(_config(zenoh, "router", listen=port))
    yield zenoh, port, session
    session.close()


def _settings(port: int, mode: str = "peer", domain: int = 7) -> ZenohSettings:
    return ZenohSettings(mode, (f"tcp/127.0.0.1:{port}",), domain)


def test_rmw_zenoh_graph_topics_types_qos_and_every_sample(router):
    from spiel_edge.outputs.rmw_zenoh.sink import RmwZenohSink
    from tests.headless._rmw_zenoh_listener import Listener, dds_name

    zenoh, port, _router = router
    mount = FrameSpec(parent="base_link", translation_m=(0.1, 0.0, 0.25))
    sink = RmwZenohSink("robot1/spiel", frame_settings(mount), _settings(port))
    client = zenoh.open(_config(zenoh, "client", connect=port))
    try:
        listener = Listener(client, domain=7).start()
        want = {
            "/robot1/spiel/point": rm.POINT_STAMPED,
            "/robot1/spiel/targets": rm.POINT_CLOUD2,
            "/robot1/spiel/tracks": rm.RADAR_TRACKS,
            "/robot1/spiel/range": rm.RANGE,
            "/diagnostics": rm.DIAGNOSTIC_ARRAY,
            "/tf_static": rm.TF_MESSAGE,
        }
        assert _wait(lambda: set(listener.publishers()) == set(want))
        (node,) = listener.nodes()
        assert (node.node, node.namespace) == ("spiel_edge", "/")
        for topic, endpoint in listener.publishers().items():
            assert endpoint.type_name == dds_name(want[topic])
            assert endpoint.type_hash == listener.store.hash_rihs01(want[topic])
            assert endpoint.reliability == 1 and endpoint.history == 1  # reliable, keep last
            latched = topic == "/tf_static"
            assert (endpoint.durability, endpoint.depth) == ((1, 1) if latched else (2, 10))
        n = 40
        time.sleep(0.3)  # the subscriber's declaration reaches the peer through the router
        for i in range(n):
            sink.write({**RECORD, "host_time": STAMP + i * 0.02, "tracks": TRACKS})
        assert _wait(lambda: len(listener.received("/robot1/spiel/range")) == n)
        assert not listener.problems, listener.problems[:3]
        publishers = listener.publishers()
        for topic in ("/robot1/spiel/point", "/robot1/spiel/targets", "/robot1/spiel/range"):
            got = listener.received(topic)
            assert [s.seq for s in got] == list(range(1, n + 1))  # from 1, none lost
            assert {s.gid for s in got} == {publishers[topic].gid}  # the announcing token's
            assert all(abs(s.stamp_ns / 1e9 - time.time()) < 60 for s in got)
        assert listener.received("/robot1/spiel/targets")[0].message.width == 2
        assert len(listener.received("/diagnostics")) == 1  # 40 records of 20 ms: < 1 s
        # a late joiner gets /tf_static from the advanced publisher's cache
        late = zenoh.open(_config(zenoh, "client", connect=port))
        try:
            tf_listener = Listener(late, domain=7)
            started = time.monotonic()
            tf_sub = tf_listener.subscribe_latched(sink.keys["/tf_static"])
            assert _wait(lambda: tf_listener.received("/tf_static"), timeout=5.0)
            (tf,) = tf_listener.received("/tf_static")
            assert tf.seq == 1 and tf.at - started < 5.0
            frames = [(t.header.frame_id, t.child_frame_id) for t in tf.message.transforms]
            assert frames == [("base_link", "spiel"), ("spiel", "spiel_optical")]
            tf_sub.undeclare()
        finally:
            late.close()
    finally:
        client.close()
        sink.close()


def test_no_router_warns_once_and_the_run_goes_on_then_connects(caplog):
    zenoh = pytest.importorskip("zenoh", reason="extra 'zenoh' not installed")
    from spiel_edge.outputs.rmw_zenoh import sink as sink_module
    from tests.headless._rmw_zenoh_listener import Listener

    port = _port()
    caplog.set_level(logging.WARNING, logger=sink_module.__name__)
    sink = sink_module.RmwZenohSink("spiel", Ros2Settings(), _settings(port, "client"))
    router = None
    try:
        for i in range(20):  # no router: writes return at once, the messages are dropped
            sink.write({**RECORD, "host_time": STAMP + i * 0.02})
        assert sink.dropped > 0
        warnings = [r for r in caplog.records if r.levelno == logging.WARNING]
        assert len(warnings) == 1 and "run goes on" in warnings[0].getMessage()
        router = zenoh.open(_config(zenoh, "router", listen=port))
        client = zenoh.open(_config(zenoh, "client", connect=port))
        try:
            listener = Listener(client, domain=7).start()
            assert _wait(lambda: "/spiel/range" in listener.publishers(), timeout=15.0)
            time.sleep(0.3)
            for i in range(5):
                sink.write({**RECORD, "host_time": STAMP + 1 + i * 0.02})
            assert _wait(lambda: len(listener.received("/spiel/range")) == 5)
            # the router goes away and comes back: the session reconnects by itself
            router.close()
            router = None
            for i in range(10):
                sink.write({**RECORD, "host_time": STAMP + 2 + i * 0.02})
        finally:
            client.close()
        router = zenoh.open(_config(zenoh, "router", listen=port))
        client = zenoh.open(_config(zenoh, "client", connect=port))
        try:
            listener = Listener(client, domain=7).start()
            assert _wait(lambda: "/spiel/point" in listener.publishers(), timeout=15.0)
            time.sleep(0.3)

            def flows() -> bool:
                sink.write({**RECORD, "host_time": time.time()})
                return bool(listener.received("/spiel/point"))

            assert _wait(flows, timeout=15.0)
        finally:
            client.close()
    finally:
        sink.close()
        if router is not None:
            router.close()


def test_bridge_mode_announces_its_publishers_and_serves_tf_static(router):
    from spiel_edge.outputs.zenoh_ros2 import ZenohRos2Sink

    zenoh, port, _router = router
    mount = FrameSpec(parent="base_link", translation_m=(0.0, 0.0, 0.3))
    sink = ZenohRos2Sink("robot1/spiel", frame_settings(mount), settings=_settings(port))
    client = zenoh.open(_config(zenoh, "client", connect=port))
    ts = _store()
    try:
        tokens = []
        assert _wait(
            lambda: (
                tokens.extend(
                    str(r.ok.key_expr)
                    for r in client.liveliness().get("@/*/@ros2_lv/**", timeout=2.0)
                    if r.ok is not None
                )
                or len(tokens) >= 6
            )
        )
        pubs = {}
        for key in tokens:
            m = re.fullmatch(r"@/(\w+)/@ros2_lv/MP/([^/]+)/([^/]+)/([^/]+)", key)
            assert m, key
            pubs[m[2].replace("§", "/")] = (m[3].replace("§", "/"), m[4])
        assert pubs["robot1/spiel/tracks"][0] == rm.RADAR_TRACKS
        assert pubs["tf_static"][1].startswith(":1:1:0,1:typehash=RIHS01_")
        assert pubs["robot1/spiel/point"][1] == (
            f":1:0:0,10:typehash={ts.hash_rihs01(rm.POINT_STAMPED)};"
        )
        # old bridges' history query and new bridges' advanced subscriber both get /tf_static
        (reply,) = client.get("@ros2_pub_cache/*/tf_static", timeout=5)
        tf = ts.deserialize_cdr(reply.ok.payload.to_bytes(), rm.TF_MESSAGE)
        assert [t.child_frame_id for t in tf.transforms] == ["spiel", "spiel_optical"]
        got = []
        late = zenoh.ext.declare_advanced_subscriber(
            client,
            "tf_static",
            lambda s: got.append(s.payload.to_bytes()),
            history=zenoh.ext.HistoryConfig(detect_late_publishers=True, max_samples=1),
        )
        assert _wait(lambda: got)
        late.undeclare()
        received = {}
        client.declare_subscriber(
            "robot1/**", lambda s: received.setdefault(str(s.key_expr), s.payload.to_bytes())
        )
        assert _wait(lambda: (sink.write(RECORD), len(received) >= 3)[1])
        point = ts.deserialize_cdr(received["robot1/spiel/point"], rm.POINT_STAMPED)
        assert point.header.frame_id == "spiel_optical" and point.point.z == 0.15
    finally:
        client.close()
        sink.close()


# --- Foxglove live, laid out as a recording ------------------------------------------------


def test_foxglove_live_serves_the_recordings_ros2_channels_and_transforms():
    pytest.importorskip("foxglove", reason="extra 'foxglove' not installed")
    import struct

    from spiel_edge.outputs.foxglove import FoxgloveSink
    from spiel_edge.recordings.ros2_mcap import TOPIC_TYPES
    from tests.headless._ws import MiniWebSocket

    mount = FrameSpec(parent="base_link", translation_m=(0.1, 0.0, 0.25))
    sink = FoxgloveSink("0", receivers_mm=[[0, 0, 0]], ros2=frame_settings(mount, frame_id="sonar"))
    ws = MiniWebSocket("127.0.0.1", sink.port, "foxglove.sdk.v1")
    ts = _store()
    try:
        channels: dict[str, dict] = {}
        deadline = time.monotonic() + 5
        while len(channels) < 9 and time.monotonic() < deadline:
            message = json.loads(ws.recv()[1])
            if message["op"] == "advertise":
                channels.update({c["topic"]: c for c in message["channels"]})
        for topic, type_name in TOPIC_TYPES.items():
            if topic.startswith("/spiel/") and topic.split("/")[-1] in (
                "acquisition",
                "background",
                "position",
            ):
                continue  # raw frames are recorded only; the JSON records are served as JSON
            c = channels[topic]
            assert (c["encoding"], c["schemaEncoding"], c["schemaName"]) == (
                "cdr",
                "ros2msg",
                type_name,
            ), topic
        assert channels["/tf"]["schemaName"] == "foxglove.FrameTransforms"
        assert channels["/spiel/scene"]["schemaName"] == "foxglove.SceneUpdate"
        wanted = {1: "/spiel/point", 2: "/tf_static", 3: "/spiel/scene", 4: "/tf"}
        ws.send_json(
            {
                "op": "subscribe",
                "subscriptions": [
                    {"id": k, "channelId": channels[t]["id"]} for k, t in wanted.items()
                ],
            }
        )
        got: dict[int, bytes] = {}
        while len(got) < len(wanted) and time.monotonic() < deadline + 5:
            sink._next_tf = 0.0  # the transforms again with this record
            sink.write(RECORD)
            frame = ws.recv(wait_s=0.1)
            if frame is not None and frame[0] == 2 and frame[1][0] == 1:
                got[struct.unpack_from("<I", frame[1], 1)[0]] = frame[1][13:]
        point = ts.deserialize_cdr(got[1], rm.POINT_STAMPED)
        assert point.header.frame_id == "sonar_optical" and point.point.z == 0.15
        tf = ts.deserialize_cdr(got[2], rm.TF_MESSAGE)
        assert [(t.header.frame_id, t.child_frame_id) for t in tf.transforms] == [
            ("base_link", "sonar"),
            ("sonar", "sonar_optical"),
        ]
        assert b"sonar_optical" in got[3] and b"base_link" in got[4]
    finally:
        ws.close()
        sink.close()


def test_ros_domain_id_from_the_environment_only_matters_for_rmw_zenoh(monkeypatch):
    from spiel_edge.cli._ros2 import zenoh_settings

    monkeypatch.setenv("ROS_DOMAIN_ID", "999")
    assert zenoh_settings({"zenoh_encoding": "json"}).domain_id == 0
    with pytest.raises(ConfigError, match="ROS_DOMAIN_ID"):
        zenoh_settings({"zenoh_encoding": "rmw_zenoh"})
    monkeypatch.setenv("ROS_DOMAIN_ID", "42")
    assert zenoh_settings({"zenoh_encoding": "rmw_zenoh"}).domain_id == 42
    assert zenoh_settings({"zenoh_encoding": "rmw_zenoh", "ros_domain_id": "7"}).domain_id == 7


def test_peer_without_its_router_warns_once_and_publishes_once_it_is_there(caplog):
    zenoh = pytest.importorskip("zenoh", reason="extra 'zenoh' not installed")
    from spiel_edge.outputs.rmw_zenoh import sink as sink_module
    from tests.headless._rmw_zenoh_listener import Listener

    port = _port()
    caplog.set_level(logging.WARNING, logger=sink_module.__name__)
    sink = sink_module.RmwZenohSink("spiel", Ros2Settings(), _settings(port, "peer"))
    router = client = None
    try:
        started = time.monotonic()
        while time.monotonic() - started < 2.5:  # past two connection checks
            sink.write({**RECORD, "host_time": time.time()})
            time.sleep(0.05)
        warnings = [r for r in caplog.records if r.levelno == logging.WARNING]
        assert len(warnings) == 1 and "run goes on" in warnings[0].getMessage()
        router = zenoh.open(_config(zenoh, "router", listen=port))
        client = zenoh.open(_config(zenoh, "client", connect=port))
        listener = Listener(client, domain=7).start()
        assert _wait(lambda: "/spiel/targets" in listener.publishers(), timeout=15.0)

        def flows() -> bool:
            sink.write({**RECORD, "host_time": time.time()})
            return bool(listener.received("/spiel/targets"))

        assert _wait(flows, timeout=15.0)
        assert not listener.problems
    finally:
        if client is not None:
            client.close()
        sink.close()
        if router is not None:
            router.close()


def test_rmw_zenoh_connects_to_the_local_router_by_default(monkeypatch):
    pytest.importorskip("zenoh", reason="extra 'zenoh' not installed")
    from spiel_edge.outputs.rmw_zenoh.sink import DEFAULT_ROUTER, RmwZenohSink

    monkeypatch.delenv("ZENOH_CONFIG", raising=False)
    sink = RmwZenohSink("spiel")
    try:
        assert sink.settings.connect == (DEFAULT_ROUTER,) == ("tcp/localhost:7447",)
        sink.write(RECORD)  # whether or not a router is there: the run goes on
    finally:
        sink.close()
