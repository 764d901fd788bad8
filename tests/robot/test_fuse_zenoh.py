"""`fuse` over Zenoh on loopback: records of several boards' processes fused in base_link; a
board whose computer's clock is seconds off is dropped with a warning, the rest go on."""

from __future__ import annotations

import json
import socket
import threading
import time

import numpy as np
import pytest

from spiel_edge.robot.description import load_robot
from tests.load import HostTiming

zenoh = pytest.importorskip("zenoh", reason="the 'zenoh' extra is not installed")

from spiel_edge.robot.zenoh_fuse import ZenohFuse, zenoh_config  # noqa: E402


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _publishers(session, keys: list[str]) -> dict:
    """A publisher per board key (by the key's last part, the board's name), its route warm
    (the first put on a new publisher may wait for the peers)."""
    out = {key.rsplit("/", 1)[-1]: session.declare_publisher(key) for key in keys}
    time.sleep(0.5)
    return out


def _sleep_until(t: float) -> None:
    time.sleep(max(0.0, t - time.time()))


class Collect:
    def __init__(self):
        self.records = []

    def write(self, record):
        self.records.append(json.loads(json.dumps(record)))

    def close(self):
        pass


def _record(k: int, board_s: float, host: float, target_board_mm) -> bytes:
    return json.dumps(
        {
            "seq": k,
            "acquisition": k,
            "device_time_us": int(board_s * 1e6),
            "host_time": host,
            "targets": [
                {
                    "position_mm": list(target_board_mm),
                    "covariance_mm2": (np.eye(3) * 16).tolist(),
                    "score": 1.0,
                }
            ],
        }
    ).encode()


@pytest.mark.parametrize("clock_off_s", [0.0, 5.0])
def test_fuse_over_zenoh(clock_off_s):
    robot = load_robot("virtual-4")
    endpoint = f"tcp/127.0.0.1:{_free_port()}"
    off = '"scouting": {"multicast": {"enabled": false}}'
    sub_cfg = zenoh.Config.from_json5(f'{{"mode": "peer", {off}}}')
    sink = Collect()
    fuse = ZenohFuse(robot, sink, config=zenoh_config(listen=[endpoint], config=sub_cfg))
    stop = threading.Event()
    worker = threading.Thread(target=fuse.run, args=(stop,), kwargs={"idle_s": 1.0})
    worker.start()
    pub = zenoh.open(
        zenoh_config(
            connect=[endpoint], config=zenoh.Config.from_json5(f'{{"mode": "peer", {off}}}')
        )
    )
    host_timing = HostTiming()  # how late this machine wakes while the boards publish
    try:
        time.sleep(1.0)  # the peers connect
        publishers = _publishers(pub, [b.key for b in robot.boards])
        p_base = np.array([300.0, 0.0, 0.0])  # in front: the front board sees it 200 mm ahead
        t0 = time.time()
        with host_timing:
            for k in range(60):  # boards firing every 25 ms, 5 ms apart (published when due)
                _sleep_until(t0 + k * 0.025)
                for j, b in enumerate(robot.boards):
                    host = time.time() + (clock_off_s if b.name == "back" else 0.0)
                    target = b.mount.to_board(p_base) if b.name == "front" else [0.0, 0.0, 150.0]
                    publishers[b.name].put(_record(k, 10.0 + k * 0.025 + j * 0.005, host, target))
    finally:
        worker.join(timeout=20)
        stop.set()
        fuse.close()
        pub.close()
    records = sink.records
    assert len(records) >= 50
    late = records[20:]
    assert all(r["frame_id"] == "base_link" for r in late)
    # a board's record that this process publishes a cycle (25 ms) late may miss its cycle: as
    # many incomplete cycles as the machine's late wake-ups explain (load 12-15: one of 40)
    slack = host_timing.allowance(0.025, len(late))
    if clock_off_s:
        assert "back" in fuse.dropped and "clock" in fuse.dropped["back"]
        assert all("back" not in r["boards"] for r in late)
        want = {"front", "left", "right"}
    else:
        assert not fuse.dropped
        want = {"front", "left", "back", "right"}
    incomplete = sum(set(r["boards"]) != want for r in late[:-1])
    assert incomplete <= slack, (incomplete, host_timing.why(0.025))
    # the front board's target, in base_link, tracked
    front_targets = [t for r in late for t in r["targets"] if t["boards"] == ["front"]]
    np.testing.assert_allclose(front_targets[-1]["position_mm"], p_base, atol=1e-6)
    assert any(r["tracks"] for r in late)
    # fused as the last board of a cycle comes in (the final cycle waits for the idle end)
    assert np.median([r["latency_ms"] for r in late[:-1]]) < 500
    # the fuser's share: from the last board record's arrival here to the write (one clock)
    for r in late[:-1]:
        assert all("received" in b for b in r["boards"].values())
        if not clock_off_s:
            assert 0.0 <= r["fuser_ms"] <= r["latency_ms"] + 1e-3


@pytest.mark.parametrize("encoding", ["json", "cdr"])
def test_fuse_in_odom_from_an_odometry_key(encoding):
    """The robot drives forward past a post; with its odometry on a Zenoh key (JSON, or a
    nav_msgs/msg/Odometry in CDR as rmw_zenoh carries it) the fused target stays where the
    post is, in odom."""
    if encoding == "cdr":
        pytest.importorskip("rosbags.typesys", reason="rosbags (test extra) writes the CDR")
        from ._odometry import odometry_cdr
    robot = load_robot("virtual-4")
    endpoint = f"tcp/127.0.0.1:{_free_port()}"
    off = '"scouting": {"multicast": {"enabled": false}}'
    sink = Collect()
    fuse = ZenohFuse(
        robot,
        sink,
        config=zenoh_config(
            listen=[endpoint], config=zenoh.Config.from_json5(f'{{"mode": "peer", {off}}}')
        ),
        odom_key="robot/odom",
    )
    stop = threading.Event()
    worker = threading.Thread(target=fuse.run, args=(stop,), kwargs={"idle_s": 1.0})
    worker.start()
    pub = zenoh.open(
        zenoh_config(
            connect=[endpoint], config=zenoh.Config.from_json5(f'{{"mode": "peer", {off}}}')
        )
    )
    post_odom = np.array([600.0, 0.0, 0.0])
    try:
        time.sleep(1.0)
        publishers = _publishers(pub, [b.key for b in robot.boards])
        odom = pub.declare_publisher("robot/odom")
        t0 = time.time()
        for k in range(60):  # the acquisitions and the odometry stamped on one timeline
            _sleep_until(t0 + k * 0.025)
            now = t0 + k * 0.025
            x_mm = 200.0 * (now - t0)  # 0.2 m/s along x
            if encoding == "cdr":
                odom.put(odometry_cdr(now, x_mm / 1000, 0.0, 0.0))
            else:
                odom.put(json.dumps({"stamp": now, "x": x_mm / 1000, "y": 0.0, "yaw": 0.0}))
            for b in robot.boards:
                p_base = post_odom - [x_mm, 0.0, 0.0]
                target = b.mount.to_board(p_base) if b.name == "front" else [0.0, 0.0, 150.0]
                publishers[b.name].put(_record(k, 10.0 + k * 0.025, now, target))
    finally:
        worker.join(timeout=20)
        stop.set()
        fuse.close()
        pub.close()
    late = sink.records[20:-1]
    assert late and all(r["frame_id"] == "odom" for r in late)
    posts = [t["position_mm"] for r in late for t in r["targets"] if t["boards"] == ["front"]]
    assert len(posts) > 10
    # the robot moved about 100 mm meanwhile; the post stays put in odom (to the time the
    # acquisition and the odometry were stamped and mapped: within 10 mm)
    np.testing.assert_allclose(np.median(posts, axis=0), post_odom, atol=10.0)
    assert np.ptp(np.array(posts)[:, 0]) < 25.0


def test_fuse_publishes_with_its_own_zenoh_settings(tmp_path, monkeypatch, zenoh_output_settings):
    """`fuse --connect/--mode/--zenoh-config` reach the session of its --zenoh output too."""
    from spiel_edge.cli import main
    from spiel_edge.robot import zenoh_fuse

    seen = zenoh_output_settings

    class NoBoards:  # no subscriptions: the run ends at once
        def __init__(self, *a, **kw):
            self.dropped = {}

        def run(self, stop, **kw):
            pass

        def close(self):
            pass

        def summary(self):
            return "0 fused records"

    monkeypatch.setattr(zenoh_fuse, "ZenohFuse", NoBoards)
    config = tmp_path / "z.json5"
    config.write_text("{}\n")
    args = ["fuse", "--robot", "virtual-4", "-o", str(tmp_path / "o.ndjson"), "--zenoh", "fused"]
    extra = ["--connect", "tcp/127.0.0.1:7447", "--mode", "client", "--zenoh-config", str(config)]
    assert main([*args, *extra]) in (0, 1)
    (settings,) = seen
    assert settings.connect == ("tcp/127.0.0.1:7447",) and settings.mode == "client"
    assert settings.config_file == str(config)
