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


# --- merging, alignment, cycles and the record at their edges (mutation-testing round) -------

C16 = np.eye(3) * 16.0  # 4 mm each axis: two boards' difference has covariance 32 I


def _two(d_mm: float, ca=C16, cb=C16, scores=(0.0, 0.0)) -> list:
    a = BaseTarget(np.zeros(3), ca, ["front"], scores[0])
    b = BaseTarget(np.array([d_mm, 0.0, 0.0]), cb, ["left"], scores[1])
    return merge_targets([a, b])


def test_merge_gate_is_the_99_percent_chi2_of_three_dof():
    # squared Mahalanobis distance |d|^2 / 32 against chi2(3 dof, 99 %) = 11.34
    assert len(_two(math.sqrt(32 * 10.0))) == 1
    assert len(_two(math.sqrt(32 * 12.0))) == 2


def test_merge_is_information_weighted_and_keeps_the_best_score():
    (m,) = _two(8.0, ca=np.eye(3) * 4.0, cb=np.eye(3) * 12.0, scores=(1.0, 3.0))
    # (0 / 4 + 8 / 12) / (1 / 4 + 1 / 12) = 2 mm; covariance (1 / 4 + 1 / 12)^-1 = 3
    np.testing.assert_allclose(m.position_mm, [2.0, 0, 0], atol=1e-9)
    np.testing.assert_allclose(m.covariance_mm2, np.eye(3) * 3.0, atol=1e-9)
    assert m.score == 3.0 and sorted(m.boards) == ["front", "left"]


def test_merge_takes_the_nearest_pair_first():
    """front at 0, left at 5 mm, front again at 12 mm: every pair of two boards is within the
    gate, but the nearest pair is merged first, and front's second target then stays apart."""
    a = BaseTarget(np.zeros(3), C16, ["front"])
    b = BaseTarget(np.array([5.0, 0, 0]), C16, ["left"])
    c = BaseTarget(np.array([12.0, 0, 0]), C16, ["front"])
    out = sorted(merge_targets([a, b, c]), key=lambda t: t.position_mm[0])
    assert [sorted(t.boards) for t in out] == [["front", "left"], ["front"]]
    np.testing.assert_allclose(out[0].position_mm, [2.5, 0, 0], atol=1e-9)


def test_to_base_gives_a_symmetric_covariance():
    from spiel_edge.robot.description import Mount, rotation_from_rpy_deg
    from spiel_edge.robot.fusion import to_base

    mount = Mount(rotation_from_rpy_deg([10.0, 20.0, 30.0]), np.array([1.0, 2.0, 3.0]))
    c = np.array([[4.0, 1.3, 0.7], [1.3, 9.0, -2.1], [0.7, -2.1, 16.0]])
    p, cb = to_base(mount, [10.0, 20.0, 300.0], c)
    np.testing.assert_allclose(p, mount.to_base([10.0, 20.0, 300.0]))
    np.testing.assert_allclose(cb, mount.covariance_to_base(c), atol=1e-12)
    assert np.array_equal(cb, cb.T)


def _pair(robot) -> Fuser:
    mounts = {n: robot.board(n).mount for n in ("front", "left")}
    return Fuser(mounts, period_s=PERIOD, track=False)


def _ahead(robot, p_base) -> list:
    return [(robot.board("front").mount.to_board(np.asarray(p_base, float)), C16, 1.0)]


def test_a_cycle_is_fused_at_its_reports_mean_time(robot):
    fuser = _pair(robot)
    assert fuser.add(BoardReport("front", 1.0, [])) == []
    (rec,) = fuser.add(BoardReport("left", 1.01, []))
    assert rec["host_time"] == pytest.approx(1.005)
    # a repeated report of a cycle already out is late: counted, not fused again
    assert fuser.add(BoardReport("left", 1.011, [])) == []
    assert fuser.stats["left"]["late"] == 1


def test_marked_acquisitions_and_targets_out_of_view_are_left_out(robot):
    p = [400.0, 0.0, 0.0]  # 300 mm straight ahead of front
    fuser = _pair(robot)
    fuser.add(BoardReport("front", 1.0, _ahead(robot, p), crosstalk=["left"]))
    (rec,) = fuser.add(BoardReport("left", 1.006, []))
    assert rec["targets"] == [] and fuser.stats["front"]["marked"] == 1
    keep = Fuser(fuser.mounts, period_s=PERIOD, track=False, drop_marked=False)
    keep.add(BoardReport("front", 1.0, _ahead(robot, p), crosstalk=["left"]))
    (rec,) = keep.add(BoardReport("left", 1.006, []))
    (t,) = rec["targets"]
    np.testing.assert_allclose(t["position_mm"], p, atol=0.01)
    # field_of_view_deg: 30 degrees for front; a target 45 degrees off is not fused
    narrow = Fuser(fuser.mounts, period_s=PERIOD, track=False, field_of_view_deg={"front": 30.0})
    off = [400.0, 300.0, 0.0]  # 45 degrees off front's facing
    narrow.add(BoardReport("front", 1.0, _ahead(robot, off) + _ahead(robot, [400.0, 50, 0])))
    (rec,) = narrow.add(BoardReport("left", 1.006, []))
    (t,) = rec["targets"]  # the one 9.5 degrees off
    np.testing.assert_allclose(t["position_mm"], [400.0, 50, 0], atol=0.01)


def test_a_target_that_is_not_finite_is_left_out(robot):
    fuser = _pair(robot)
    nan = [(np.array([np.nan, 0.0, 300.0]), C16, 1.0)]
    fuser.add(BoardReport("front", 1.0, nan + _ahead(robot, [400.0, 0, 0])))
    (rec,) = fuser.add(BoardReport("left", 1.006, []))
    assert len(rec["targets"]) == 1 and np.all(np.isfinite(rec["targets"][0]["position_mm"]))


def test_in_odom_the_covariance_is_rotated_too(robot):
    rot, trans = planar_pose(1000.0, 0.0, math.pi / 2)
    mounts = {"front": robot.board("front").mount}
    fuser = Fuser(mounts, period_s=PERIOD, track=False, odometry=lambda t: (rot, trans))
    c = np.diag([1.0, 4.0, 9.0])  # board frame
    (rec,) = fuser.add(BoardReport("front", 1.0, [(np.array([0.0, 0.0, 300.0]), c, 1.0)]))
    (t,) = rec["targets"]
    m = mounts["front"]
    np.testing.assert_allclose(t["position_mm"], rot @ m.to_base([0, 0, 300.0]) + trans, atol=0.01)
    np.testing.assert_allclose(
        t["covariance_mm2"], rot @ m.covariance_to_base(c) @ rot.T, atol=1e-3
    )


def test_a_quiet_board_is_not_waited_for_until_it_reports_again(robot):
    fuser = _pair(robot)
    fuser.add(BoardReport("front", 1.0, []))
    assert len(fuser.add(BoardReport("left", 1.006, []))) == 1  # cycle 0: both
    out = []
    for k in range(1, 6):  # left is silent from cycle 1 on
        out.append(len(fuser.add(BoardReport("front", 1.0 + k * PERIOD, []))))
    # cycles 1 and 2 go out 3 cycles late, each missing left
    assert out == [0, 0, 0, 1, 1]
    # cycle 3 is left's third missed in a row: from then on nobody waits for it, so cycles 3-6
    # go out together, and each later cycle as soon as front reports
    recs = fuser.add(BoardReport("front", 1.0 + 6 * PERIOD, []))
    assert len(recs) == 4 and all(r["missing"] == ["left"] for r in recs)
    assert len(fuser.add(BoardReport("front", 1.0 + 7 * PERIOD, []))) == 1
    # left reports again: the next cycle waits for it
    assert len(fuser.add(BoardReport("left", 1.006 + 8 * PERIOD, []))) == 0
    assert len(fuser.add(BoardReport("front", 1.0 + 8 * PERIOD, []))) == 1
    assert fuser.add(BoardReport("front", 1.0 + 9 * PERIOD, [])) == []


def test_a_dropped_board_is_not_missing(robot):
    fuser = Fuser({b.name: b.mount for b in robot.boards}, period_s=PERIOD, track=False)
    fuser.drop("right")
    for k, name in enumerate(("front", "left")):
        fuser.add(BoardReport(name, 1.0 + 0.006 * k, []))
    (rec,) = fuser.add(BoardReport("back", 1.012, []))
    assert rec["missing"] == []


def test_a_drifting_boards_cycle_is_followed(robot):
    """left's clock runs 200 ppm slow against front's: over 75 s its pulse moves 15 ms, past a
    half period within the cycle; its reports keep landing in the cycle of front's."""
    fuser = _pair(robot)
    missing = 0
    for k in range(3000):
        out = fuser.add(BoardReport("front", k * PERIOD, []))
        out += fuser.add(BoardReport("left", 0.002 + k * PERIOD * (1 + 2e-4), []))
        missing += sum(bool(rec["missing"]) for rec in out)
    assert fuser.seq == 3000 and missing == 0


def test_the_schedule_places_the_first_reports_in_their_cycle(robot):
    """With the slots given, the first report (left's pulse of cycle 1) does not set the cycle
    grid: front's pulse of that cycle, 0.7 ms earlier, is in the same cycle."""
    fuser = _pair(robot)
    fuser.set_schedule(1.0, {"front": 0.0, "left": 0.0057})
    assert fuser.add(BoardReport("left", 1.0 + PERIOD + 0.0057, [])) == []
    (rec,) = fuser.add(BoardReport("front", 1.0 + PERIOD - 0.0001, []))
    assert sorted(rec["boards"]) == ["front", "left"] and rec["missing"] == []


def test_targets_move_to_the_cycles_time_with_their_track(robot):
    """A target moving 400 mm/s along y, seen by front 10 ms before the cycle's mean time (left
    reports 20 ms after front): once its track has the speed, front's target goes into the
    cycle 4 mm further along; a new target far from every track is not moved."""
    from spiel_edge.profile.track_section import TrackSpec

    mounts = {n: robot.board(n).mount for n in ("front", "left")}
    spec = TrackSpec(imm_switch_probability=0.0, imm_static_share=0.0)  # constant velocity
    fuser = Fuser(mounts, period_s=PERIOD, spec=spec)
    v = 400.0  # mm/s

    def at(t):
        return np.array([400.0, -300.0 + v * t, 0.0])

    far = np.array([700.0, -300.0, 0.0])  # appears at the last cycle, 400 mm from the mover
    rec = None
    for k in range(60):
        t = k * PERIOD
        seen = _ahead(robot, at(t)) + (_ahead(robot, far) if k == 59 else [])
        fuser.add(BoardReport("front", t, seen))
        (rec,) = fuser.add(BoardReport("left", t + 0.02, []))
    (track,) = [tr for tr in rec["tracks"] if tr["position_mm"][0] < 500]
    assert track["velocity_mm_s"][1] == pytest.approx(v, rel=0.01)
    mover, new = sorted(rec["targets"], key=lambda x: x["position_mm"][0])
    np.testing.assert_allclose(mover["position_mm"], at(59 * PERIOD + 0.01), atol=0.2)
    np.testing.assert_allclose(new["position_mm"], far, atol=0.01)


def test_latency_counts_from_the_last_boards_acquisition_and_arrival():
    from spiel_edge.robot.fusion import stamp_latency

    record = {
        "boards": {
            "front": {"acquired": 100.000, "received": 100.010},
            "left": {"acquired": 100.020, "received": 100.030},
            "back": {},  # a board that says neither
        }
    }
    latencies: list[float] = []
    stamp_latency(record, 100.050, latencies)
    assert record["latency_ms"] == pytest.approx(30.0)  # after left's, the last acquisition
    assert record["fuser_ms"] == pytest.approx(20.0)  # after left's record reached the fuser
    assert latencies == [pytest.approx(30.0)]
    bare = {"boards": {"front": {}}}
    stamp_latency(bare, 1.0, latencies)
    assert "latency_ms" not in bare and "fuser_ms" not in bare and len(latencies) == 1
