"""Odometry as ROS 2 publishes and records it (nav_msgs/msg/Odometry in CDR) or as JSON, live
or from a recording, and `fuse --replay`: the boards' recorded records fused offline, in odom
with a recording's poses."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from mcap.writer import Writer

from spiel_edge.cli import main
from spiel_edge.errors import InputError
from spiel_edge.messages.cdr import decode_odometry
from spiel_edge.robot.description import load_robot
from spiel_edge.robot.odometry import parse_odometry
from spiel_edge.robot.odometry_sources import read_odometry_file

pytest.importorskip("rosbags.typesys", reason="rosbags (test extra) writes the reference")

from ._odometry import odometry_cdr  # noqa: E402


@pytest.mark.parametrize("little", [True, False])
@pytest.mark.parametrize("frame", ["", "o", "odom", "odom_frame_7"])  # every alignment
def test_odometry_cdr_decodes_as_rosbags_wrote_it(little, frame):
    for yaw in (0.0, 0.7, -2.9, math.pi - 1e-6):
        data = odometry_cdr(1796220097.25, 1.5, -0.75, yaw, frame=frame, little=little)
        stamp, x, y, got = decode_odometry(data)
        assert stamp == pytest.approx(1796220097.25, abs=1e-6)
        assert (x, y) == (1.5, -0.75)
        assert math.remainder(got - yaw, 2 * math.pi) == pytest.approx(0.0, abs=1e-9)


def test_odometry_messages_json_or_cdr_and_what_is_neither():
    assert parse_odometry(b'{"stamp": 5.0, "x": 1, "y": 2, "yaw": 0.5}') == (5.0, 1.0, 2.0, 0.5)
    assert parse_odometry(b'{"x": 1, "y": 2, "yaw": 0}')[0] is None  # no stamp: the arrival's
    assert parse_odometry(odometry_cdr(3.5, 0.1, 0.2, 0.0))[:3] == (3.5, 0.1, 0.2)
    for bad in (b"", b"nope", b'{"x": 1}', b'{"x": "NaN", "y": 0, "yaw": 0}', b"\x00\x01\x00\x00"):
        with pytest.raises(InputError):
            parse_odometry(bad)


def _mcap(path, topics: dict[str, list[bytes]], chunk_size: int = 1024 * 1024) -> None:
    with open(path, "wb") as f:  # as rosbag2 writes it: ros2msg schema, cdr, zstd chunks
        w = Writer(f, chunk_size=chunk_size)
        w.start("ros2", "rosbag2")
        schema = w.register_schema("nav_msgs/msg/Odometry", "ros2msg", b"")
        for topic, messages in topics.items():
            channel = w.register_channel(topic, "cdr", schema)
            for k, data in enumerate(messages):
                w.add_message(channel, log_time=k, data=data, publish_time=k)
        w.finish()


def test_odometry_from_a_recording(tmp_path):
    poses = [odometry_cdr(100.0 + 0.02 * k, 0.001 * k, 0.0, 0.01 * k) for k in range(50)]
    _mcap(tmp_path / "bag.mcap", {"/odom": poses[::-1], "/other": poses[:3]})  # any order
    odom = read_odometry_file(tmp_path / "bag.mcap")
    assert len(odom) == 50
    rot, trans = odom(100.5)  # between poses 25 and 25: x 25 mm, yaw 0.25
    np.testing.assert_allclose(trans, [25.0, 0.0, 0.0], atol=1e-6)
    assert math.atan2(rot[1, 0], rot[0, 0]) == pytest.approx(0.25)
    assert odom(99.0) is None  # before the recording
    lines = [json.dumps({"stamp": 10.0 + k, "x": k, "y": 0, "yaw": 0}) for k in range(3)]
    (tmp_path / "odom.ndjson").write_text("\n".join(lines) + "\n")
    assert len(read_odometry_file(tmp_path / "odom.ndjson")) == 3
    with pytest.raises(InputError, match=r"no messages on /odom \(topics: /other"):
        _mcap(tmp_path / "none.mcap", {"/other": poses[:2]})
        read_odometry_file(tmp_path / "none.mcap")
    (tmp_path / "nostamp.ndjson").write_text('{"x": 0, "y": 0, "yaw": 0}\n')
    with pytest.raises(InputError, match="message 1 has no stamp"):
        read_odometry_file(tmp_path / "nostamp.ndjson")
    with pytest.raises(InputError, match="cannot read the odometry"):
        read_odometry_file(tmp_path / "missing.mcap")


def _board_files(tmp_path, robot, speed_mm_s: float, n: int = 80) -> dict[str, str]:
    """Each board's records as its `run -o` writes them: the robot drives along x at
    ``speed_mm_s`` past a post 600 mm ahead in odom, which the front board sees."""
    files = {}
    post_odom = np.array([600.0, 0.0, 0.0])
    for j, b in enumerate(robot.boards):
        lines = []
        for k in range(n):
            t = 1000.0 + k * 0.025 + j * 0.005
            p_base = post_odom - [speed_mm_s * (t - 1000.0), 0.0, 0.0]
            targets = []
            if b.name == "front":
                cov = (np.eye(3) * 16).tolist()
                targets = [{"position_mm": list(b.mount.to_board(p_base)), "covariance_mm2": cov}]
            record = {"acquisition": k, "device_time_us": int((5.0 + t - 1000) * 1e6)}
            lines.append(json.dumps({**record, "host_time": t, "targets": targets}))
        lines.insert(n // 2, "not json")  # a damaged line: counted, not fatal
        files[b.name] = tmp_path / f"{b.name}.ndjson"
        files[b.name].write_text("\n".join(lines) + "\n")
    return {k: str(v) for k, v in files.items()}


def test_fuse_replay_in_base_link_and_in_odom(tmp_path, capsys):
    robot = load_robot("virtual-4")
    files = _board_files(tmp_path, robot, speed_mm_s=200.0)
    replay = [a for name, path in files.items() for a in ("--replay", f"{name}={path}")]
    out = tmp_path / "fused.ndjson"
    assert main(["fuse", "--robot", "virtual-4", *replay, "-o", out]) == 0
    records = [json.loads(line) for line in out.read_text().splitlines()]
    assert len(records) == 80 and all(r["frame_id"] == "base_link" for r in records)
    assert all(set(r["boards"]) == set(files) and "latency_ms" not in r for r in records)
    late = [t for r in records[20:] for t in r["tracks"]]
    assert late and np.median([t["velocity_mm_s"][0] for t in late]) == pytest.approx(-200, abs=20)
    # with the robot's odometry from a recording (rosbag2's CDR): the post stands still in odom
    poses = [odometry_cdr(999.9 + 0.01 * k, 0.2 * 0.01 * (k - 10), 0.0, 0.0) for k in range(300)]
    _mcap(tmp_path / "odom.mcap", {"/odom": poses})
    out2 = tmp_path / "fused_odom.ndjson"
    args = ["fuse", "--robot", "virtual-4", *replay, "--odom-file", tmp_path / "odom.mcap"]
    assert main([*args, "-o", out2]) == 0
    records = [json.loads(line) for line in out2.read_text().splitlines()]
    assert all(r["frame_id"] == "odom" for r in records)
    posts = [t["position_mm"] for r in records[20:] for t in r["targets"]]
    np.testing.assert_allclose(np.median(posts, axis=0), [600.0, 0.0, 0.0], atol=5.0)
    tracks = [t for r in records[20:] for t in r["tracks"]]
    assert abs(np.median([t["velocity_mm_s"][0] for t in tracks])) < 20.0


def test_fuse_replay_bad_input_is_one_line_before_any_output(tmp_path, capsys):
    robot = load_robot("virtual-4")
    files = _board_files(tmp_path, robot, speed_mm_s=0.0, n=10)
    out = tmp_path / "fused.ndjson"
    base = ["fuse", "--robot", "virtual-4", "-o", out]
    cases = [
        (["--replay", f"nose={files['front']}"], "the robot has no board 'nose'"),
        (["--replay", "front"], "BOARD=FILE"),
        (["--replay", f"front={tmp_path / 'missing.ndjson'}"], "cannot read board front's records"),
        (["--replay", f"front={files['front']}", "--connect", "tcp/h:7447"], "--connect is for the live"),
        (["--odom-file", files["front"]], "--odom-file goes with --replay"),
        (["--replay", f"front={files['front']}", "--odom-file", files["front"]], "odometry message 1"),
    ]  # fmt: skip
    for extra, message in cases:
        capsys.readouterr()
        assert main([*base, *extra]) == 2
        err = capsys.readouterr().err
        assert message in err and "Traceback" not in err, err
        assert not out.exists()
    # one board only: the others are left out, its cycles are not held back
    assert main([*base, "--replay", f"left={files['left']}"]) == 0
    records = [json.loads(line) for line in out.read_text().splitlines()]
    assert len(records) == 10 and all(list(r["boards"]) == ["left"] for r in records)


def test_fuse_counts_records_of_the_wrong_shape_and_goes_on(tmp_path, capsys):
    """A record whose fields have the wrong types (a hostile or broken publisher) is counted
    as a bad record like a line that is not JSON: the fusion goes on with the good ones."""
    robot = load_robot("virtual-4")
    files = _board_files(tmp_path, robot, speed_mm_s=0.0, n=40)
    good = {"acquisition": 1, "device_time_us": 5_000_000, "host_time": 1000.5}
    bad = [
        {**good, "acquisition": None},
        {**good, "acquisition": "x"},
        {**good, "targets": 5},
        {**good, "crosstalk": 7},
        {**good, "crosstalk": [3]},
        {**good, "device_time_us": "5"},
        {**good, "host_time": None},
        5,
        [],
    ]
    path = tmp_path / "front.ndjson"
    lines = path.read_text().splitlines()
    path.write_text("\n".join(lines[:20] + [json.dumps(b) for b in bad] + lines[20:]) + "\n")
    out = tmp_path / "fused.ndjson"
    replay = [a for name, f in files.items() for a in ("--replay", f"{name}={f}")]
    capsys.readouterr()
    assert main(["fuse", "--robot", "virtual-4", *replay, "-o", out]) == 0
    assert "Traceback" not in capsys.readouterr().err
    records = [json.loads(line) for line in out.read_text().splitlines()]
    assert len(records) == 40 and all("front" in r["boards"] for r in records)


@pytest.mark.parametrize("profile", ["json", "ros2"])
def test_fuse_replay_takes_a_boards_mcap_recording_as_its_ndjson(tmp_path, capsys, profile):
    """`run --record` (either profile) carries the same records as `run -o`: fused alike."""
    port = "sim://front?scene=robot&robot=virtual-4&board=front&movers=5"
    mcap, ndjson = tmp_path / "front.mcap", tmp_path / "front.ndjson"
    args = ["run", "--port", port, "--frames", "30", "--rate", "40", "--max-targets", "4"]
    assert main([*args, "--record", mcap, "--record-profile", profile, "-o", ndjson]) == 0
    fused = {}
    for source in (mcap, ndjson):
        out = tmp_path / f"fused-{source.suffix[1:]}.ndjson"
        fuse = ["fuse", "--robot", "virtual-4", "--replay", f"front={source}", "-o", out]
        assert main(fuse) == 0
        fused[source.suffix] = out.read_text()
    assert fused[".mcap"] == fused[".ndjson"] and len(fused[".mcap"].splitlines()) >= 25
    assert "left: not replayed" in capsys.readouterr().err


def test_a_string_message_decodes_or_says_why():
    from spiel_edge.messages.cdr import decode_string, string_message

    assert decode_string(string_message('{"x": "é"}')) == '{"x": "é"}'
    good = string_message("abc")
    for bad, why in (
        (b"\x00\x00\x00\x00" + good[4:], "not little-endian"),
        (good[:6], "truncated"),
        (good[:-1], "announced"),
        (good[:-1] + b"x", "announced"),  # no terminating NUL
        (good[:8] + b"\xff\xfe\xfd\x00", "not UTF-8"),
    ):
        with pytest.raises(InputError, match=why):
            decode_string(bad)


def _ros2_messages(path, topics):
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        return [(c.topic, m) for _, c, _, m in reader.iter_decoded_messages(topics=topics)]


@pytest.mark.parametrize("odom", [False, True])
def test_the_fused_scene_in_ros2_is_in_the_robots_frame(tmp_path, odom):
    """Fused records are in base_link (or odom) axes already: their ROS 2 messages are stamped
    that frame (not a sensor's optical frame), every target kept whatever its direction, no
    Range; /tf_static carries the boards' mounts."""
    import struct

    robot = load_robot("virtual-4")
    files = _board_files(tmp_path, robot, speed_mm_s=0.0, n=40)
    for name, path in files.items():  # targets all around, some below base_link's plane
        lines = Path(path).read_text().splitlines()
        k = list(files).index(name)
        p_base = np.array([np.cos(k * 1.6), np.sin(k * 1.6), -0.1 * (k % 2)]) * 250.0
        target = {"position_mm": list(robot.boards[k].mount.to_board(p_base)), "score": 1.0}
        target["covariance_mm2"] = (np.eye(3) * 16).tolist()
        lines = [
            json.dumps({**json.loads(line), "targets": [target]}) if line.startswith("{") else line
            for line in lines
        ]
        Path(path).write_text("\n".join(lines) + "\n")
    replay = [a for name, path in files.items() for a in ("--replay", f"{name}={path}")]
    extra = []
    if odom:
        poses = [
            json.dumps({"stamp": 999.0 + 0.01 * k, "x": 0, "y": 0, "yaw": 0}) for k in range(400)
        ]
        (tmp_path / "odom.ndjson").write_text("\n".join(poses) + "\n")
        extra = ["--odom-file", tmp_path / "odom.ndjson"]
    out, bag = tmp_path / "fused.ndjson", tmp_path / "fused.mcap"
    args = ["fuse", "--robot", "virtual-4", *replay, *extra, "--record", bag]
    assert main([*args, "--record-profile", "ros2", "-o", out]) == 0
    records = [json.loads(line) for line in out.read_text().splitlines()]
    messages = _ros2_messages(bag, ["/spiel/targets", "/tf_static", "/spiel/range"])
    frame = "odom" if odom else "base_link"
    clouds = [m for topic, m in messages if topic == "/spiel/targets"]
    assert len(clouds) == len(records) and {c.header.frame_id for c in clouds} == {frame}
    for cloud, record in zip(clouds, records, strict=True):
        points = [
            struct.unpack_from("<3f", bytes(cloud.data), i * cloud.point_step)
            for i in range(cloud.width)
        ]
        want = [np.array(t["position_mm"]) / 1000.0 for t in record["targets"]]
        assert len(points) == len(want)  # none left out for its direction
        np.testing.assert_allclose(points, np.array(want).reshape(-1, 3), atol=1e-6)
    assert sum(c.width for c in clouds) > 100
    assert not [m for topic, m in messages if topic == "/spiel/range"]
    tf = [
        (t.header.frame_id, t.child_frame_id)
        for topic, m in messages
        if topic == "/tf_static"
        for t in m.transforms
    ]
    assert set(tf) == {("base_link", b.name) for b in robot.boards}


def test_an_odometry_message_joins_the_buffer_on_its_stamp_or_its_arrival():
    from spiel_edge.robot.odometry import OdometryBuffer

    odom = OdometryBuffer()
    assert odom.add_message(b'{"stamp": 100.0, "x": 1, "y": 0, "yaw": 0}', arrived=100.3)
    assert odom.add_message(b'{"stamp": 5.0, "x": 2, "y": 0, "yaw": 0}', arrived=101.0)  # skewed
    assert odom.add_message(odometry_cdr(101.5, 3.0, 0.0, 0.0), arrived=101.6, shift_s=0.0)
    assert not odom.add_message(b"garbage", arrived=102.0)
    assert not odom.add_message(b'{"stamp": 50.0, "x": 9, "y": 0, "yaw": 0}', arrived=50.2)
    assert odom.rejected == 2 and len(odom) == 3  # the malformed and the out-of-order one
    np.testing.assert_allclose(odom(101.0)[1], [2000.0, 0.0, 0.0])  # at its arrival
    shifted = OdometryBuffer()
    assert shifted.add_message(b'{"x": 1, "y": 0, "yaw": 0}', arrived=10.0, shift_s=-9.0)
    np.testing.assert_allclose(shifted(1.0)[1], [1000.0, 0.0, 0.0])  # on the caller's clock


def test_fuse_replay_of_damaged_files_goes_as_far_as_they_go(tmp_path, capsys):
    """Garbage instead of records drops that board (one warning, status 1); a recording cut
    short (a robot's power lost) gives what it holds; a cut odometry bag its poses so far."""
    rng = np.random.default_rng(7)
    junk = tmp_path / "junk.ndjson"
    junk.write_bytes(rng.integers(0, 256, 20000, dtype=np.uint8).tobytes())
    port = "sim://front?scene=robot&robot=virtual-4&board=front&movers=5"
    mcap = tmp_path / "front.mcap"
    args = ["run", "--port", port, "--frames", "60", "--rate", "40", "--max-targets", "4"]
    assert main([*args, "--record", mcap, "-o", tmp_path / "front.ndjson"]) == 0
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(mcap.read_bytes()[: mcap.stat().st_size * 2 // 3])
    out = tmp_path / "fused.ndjson"
    replay = ["--replay", f"front={cut}", "--replay", f"left={junk}"]
    capsys.readouterr()
    status = main(["fuse", "--robot", "virtual-4", *replay, "-o", out])
    err = capsys.readouterr().err
    assert status == 1 and "Traceback" not in err, err
    assert "board left dropped" in err and "not spiel-edge records" in err
    records = [json.loads(line) for line in out.read_text().splitlines()]
    assert 10 <= len(records) < 60  # what the cut recording holds
    poses = [odometry_cdr(100.0 + 0.01 * k, 0.001 * k, 0.0, 0.0) for k in range(400)]
    _mcap(tmp_path / "odom.mcap", {"/odom": poses}, chunk_size=4096)  # many chunks
    data = (tmp_path / "odom.mcap").read_bytes()
    (tmp_path / "odom_cut.mcap").write_bytes(data[: len(data) // 2])
    odom = read_odometry_file(tmp_path / "odom_cut.mcap")
    assert 0 < len(odom) < 400
