"""Fusion in base_link: duplicates merged, ids kept across fields of view, cycles, odom."""

from __future__ import annotations

import math

import numpy as np
import pytest

from spiel_edge.robot.description import load_robot
from spiel_edge.robot.fusion import (
    BaseTarget,
    BoardReport,
    Fuser,
    fuse_sequence,
    merge_targets,
    planar_pose,
    record_targets,
)

PERIOD = 0.025


@pytest.fixture(scope="module")
def robot():
    return load_robot("virtual-4")


def _seen(robot, name, p_base, rng, sigma=4.0, half_angle=50.0):
    """What board ``name`` reports of a point in base_link: the point in its frame (noisy)
    when within its field of view, with covariance sigma^2 I."""
    m = robot.board(name).mount
    v = p_base - m.translation_mm
    if v @ m.facing < math.cos(math.radians(half_angle)) * np.linalg.norm(v):
        return []
    p = m.to_board(p_base) + rng.normal(0, sigma, 3)
    return [(p, np.eye(3) * sigma**2, 1.0)]


def test_two_boards_seeing_one_target_give_one_fused_target(robot):
    rng = np.random.default_rng(0)
    p = np.array([200.0, 200.0, 0.0])  # 45 degrees: front and left both see it
    fuser = Fuser({b.name: b.mount for b in robot.boards}, period_s=PERIOD, track=False)
    reports = [
        BoardReport(n, 1.0 + 0.005 * k, _seen(robot, n, p, rng, half_angle=65.0))
        for k, n in enumerate(("front", "left", "back", "right"))
    ]
    assert reports[0].targets and reports[1].targets and not reports[2].targets
    (record,) = fuse_sequence(fuser, reports)
    (target,) = record["targets"]
    assert sorted(target["boards"]) == ["front", "left"]
    # the information-weighted mean of the two, in base_link
    a = robot.board("front").mount.to_base(reports[0].targets[0][0])
    b = robot.board("left").mount.to_base(reports[1].targets[0][0])
    np.testing.assert_allclose(target["position_mm"], (a + b) / 2, atol=0.01)
    np.testing.assert_allclose(np.array(target["covariance_mm2"]), np.eye(3) * 8.0, atol=0.01)


def test_far_apart_or_same_board_targets_are_not_merged():
    c = np.eye(3) * 16.0
    a = BaseTarget(np.zeros(3), c, ["front"])
    b = BaseTarget(np.array([50.0, 0, 0]), c, ["left"])
    assert len(merge_targets([a, b])) == 2
    same = BaseTarget(np.array([1.0, 0, 0]), c, ["front"])
    assert len(merge_targets([a, same])) == 2
    near = BaseTarget(np.array([1.0, 0, 0]), c, ["left"])
    (m,) = merge_targets([a, near])
    np.testing.assert_allclose(m.position_mm, [0.5, 0, 0])


def test_a_target_circling_the_robot_keeps_its_track_id(robot):
    rng = np.random.default_rng(1)
    fuser = Fuser({b.name: b.mount for b in robot.boards}, period_s=PERIOD)
    offsets = {"front": 0.0, "left": 0.0057, "back": 0.0113, "right": 0.017}
    records, seen_by = [], set()
    for cycle in range(600):  # 15 s at 0.5 rad/s: more than a full turn, through every board
        for name, off in offsets.items():
            t = cycle * PERIOD + off
            p = np.array([280 * math.cos(0.5 * t), 280 * math.sin(0.5 * t), 0.0])
            targets = _seen(robot, name, p, rng, half_angle=65.0)  # fields of view overlap
            seen_by |= {name} if targets else set()
            records += fuser.add(BoardReport(name, t, targets))
    assert seen_by == set(offsets)
    ids = {tr["track_id"] for r in records[20:] for tr in r["tracks"]}
    assert len(ids) == 1, ids
    err = [
        np.linalg.norm(
            np.array(r["tracks"][0]["position_mm"])
            - [280 * math.cos(0.5 * r["host_time"]), 280 * math.sin(0.5 * r["host_time"]), 0]
        )
        for r in records[20:]
    ]
    assert np.median(err) < 6.0


def test_cycles_wait_for_every_board_and_not_for_a_dropped_one(robot):
    fuser = Fuser({b.name: b.mount for b in robot.boards}, period_s=PERIOD, track=False)
    assert fuser.add(BoardReport("front", 1.0, [])) == []
    assert fuser.add(BoardReport("left", 1.006, [])) == []
    assert fuser.add(BoardReport("front", 1.025, [])) == []  # cycle 1 opens; 0 still waits
    assert fuser.add(BoardReport("back", 1.011, [])) == []  # late, out of order: still cycle 0
    assert fuser.add(BoardReport("front", 1.05, [])) == []
    (out,) = fuser.add(BoardReport("front", 1.075, []))  # 3 cycles on: 0 goes out incomplete
    assert out["missing"] == ["right"] and sorted(out["boards"]) == ["back", "front", "left"]
    fuser.drop("right")
    assert fuser.add(BoardReport("left", 1.031, [])) == []  # cycle 1 waits for back
    for k in range(2, 6):  # back and right are silent: after a few cycles nobody waits
        out = fuser.add(BoardReport("front", 1.0 + k * PERIOD, []))
        out += fuser.add(BoardReport("left", 1.006 + k * PERIOD, []))
    assert out and out[-1]["boards"].keys() == {"front", "left"}
    assert fuser.add(BoardReport("back", 1.011, [])) == []  # far too late
    assert fuser.stats["back"]["late"] == 1


def test_odometry_puts_targets_in_odom(robot):
    rng = np.random.default_rng(2)
    static_odom = np.array([300.0, 50.0, 0.0])

    def pose(t):
        return planar_pose(0.0, 0.0, 0.3 * t)  # the robot turns in place

    fuser = Fuser({b.name: b.mount for b in robot.boards}, period_s=PERIOD, odometry=pose)
    records = []
    for cycle in range(200):
        for k, name in enumerate(("front", "left", "back", "right")):
            t = cycle * PERIOD + 0.0057 * k
            rot, trans = pose(t)
            p_base = rot.T @ (static_odom - trans)
            records += fuser.add(
                BoardReport(name, t, _seen(robot, name, p_base, rng, sigma=2.0, half_angle=65.0))
            )
    assert records[-1]["frame_id"] == "odom"
    (track,) = records[-1]["tracks"]
    np.testing.assert_allclose(track["position_mm"], static_odom, atol=6.0)
    assert len({tr["track_id"] for r in records[10:] for tr in r["tracks"]}) == 1


def test_record_targets_skips_malformed_entries():
    record = {
        "targets": [
            {"position_mm": [1, 2, 3], "covariance_mm2": np.eye(3).tolist(), "score": 1},
            {"position_mm": [1, 2]},
            {"position_mm": [float("nan"), 0, 0]},
            "junk",
        ]
    }
    (t,) = record_targets(record)
    np.testing.assert_allclose(t[0], [1, 2, 3])


def test_odometry_buffer_interpolates_and_refuses_what_it_cannot_know():
    from spiel_edge.robot.fusion import OdometryBuffer

    odom = OdometryBuffer()
    assert odom(1.0) is None
    assert odom.add(1.0, 0.0, 0.0, math.pi - 0.1)
    assert odom.add(2.0, 100.0, 50.0, -math.pi + 0.1)  # yaw crosses +-pi: the short way
    assert not odom.add(1.5, 0.0, 0.0, 0.0)  # out of order
    assert not odom.add(3.0, float("nan"), 0.0, 0.0)
    rot, trans = odom(1.5)
    np.testing.assert_allclose(trans, [50.0, 25.0, 0.0])
    np.testing.assert_allclose(rot @ [1, 0, 0], [-1, 0, 0], atol=1e-9)  # yaw pi
    assert odom(0.5) is None and odom(2.1) is not None and odom(2.5) is None
