"""Field-of-view-aware track maintenance (robot/coast.py): a fused track is charged a miss
only where some board could have seen it; outside every field of view it coasts, within
bounds, and keeps its id across the gap between two fields of view."""

from __future__ import annotations

import math

import numpy as np
import pytest

from spiel_edge.profile.track_section import TrackSpec
from spiel_edge.robot.coast import CoastPolicy
from spiel_edge.robot.description import load_robot
from spiel_edge.robot.fusion import BaseTarget, BoardReport, Fuser, planar_pose
from spiel_edge.track import Tracker

PERIOD = 0.025
CV = {"imm_switch_probability": 0.0, "imm_static_share": 0.0}


@pytest.fixture(scope="module")
def robot():
    return load_robot("virtual-4")


def test_in_odom_the_cones_are_checked_in_base_link(robot):
    """With odometry the tracks are in odom; the robot's pose at the cycle's time moves their
    predicted positions back into base_link, where the cones are (no pose: none is held)."""
    pose = {"now": planar_pose(100.0, 0.0, math.pi / 2)}
    fuser = Fuser(
        {b.name: b.mount for b in robot.boards},
        period_s=PERIOD,
        odometry=lambda t: pose["now"],
        coast=CoastPolicy.from_robot(robot),
    )
    np.testing.assert_allclose(
        fuser._to_base_at(0.0)(np.array([[100.0, 300, 0]])), [[300, 0, 0]], atol=1e-9
    )
    pose["now"] = None
    assert fuser._to_base_at(0.0)(np.zeros((1, 3))) is None
    tracker = _tracker_with_a_track()
    assert len(fuser.coast.hold(tracker, 5 * PERIOD, fuser._to_base_at(0.0))) == 0


def _tracker_with_a_track(velocity=(0.0, 0.0, 0.0)) -> Tracker:
    tracker = Tracker(TrackSpec(max_misses=3, **CV))
    for k in range(4):  # confirmed (3 hits) and moving along x
        p = np.array(velocity) * k * PERIOD
        tracker.update([BaseTarget(p, np.eye(3) * 4.0, ["a"])], k * PERIOD)
    assert len(tracker.tracks()) == 1
    return tracker


def _misses_after_empty_update(policy, tracker, t) -> tuple[int, list]:
    held = policy.hold(tracker, t)
    (track,) = tracker.update([], t) or [None]
    return (track.misses if track else None), held.tolist()


def test_a_track_is_charged_a_miss_only_inside_some_field_of_view():
    # one board at the origin facing +x, 45 degrees, 800 mm
    policy = CoastPolicy([(np.zeros(3), np.array([1.0, 0, 0]), 45.0)], range_mm=800.0)
    np.testing.assert_array_equal(
        policy.visible(np.array([[500.0, 0, 0], [500, 600, 0], [-100, 0, 0], [900, 0, 0]])),
        [True, False, False, False],
    )
    inside = _tracker_with_a_track()
    inside.update([], 4 * PERIOD)  # ... then the object goes unseen: a miss
    policy_far = CoastPolicy([(np.array([10.0, 0, 0]), np.array([1.0, 0, 0]), 45.0)], range_mm=800)
    # the track sits at the origin, behind the board at x = 10 mm: outside, its misses hold
    assert _misses_after_empty_update(policy_far, inside, 5 * PERIOD)[0] == 1
    # in front of a board: charged
    policy_near = CoastPolicy(
        [(np.array([-10.0, 0, 0]), np.array([1.0, 0, 0]), 45.0)], range_mm=800.0
    )
    misses, held = _misses_after_empty_update(policy_near, inside, 6 * PERIOD)
    assert misses == 2 and held == []
    # a hit still resets the count while the track is held
    policy_far.hold(inside, 7 * PERIOD)
    (track,) = inside.update([BaseTarget(np.zeros(3), np.eye(3) * 4.0, ["a"])], 7 * PERIOD)
    assert track.misses == 0


def test_the_coast_is_bounded_in_time_and_in_covariance():
    behind = [(np.array([10.0, 0, 0]), np.array([1.0, 0, 0]), 45.0)]
    timed = CoastPolicy(behind, range_mm=800.0, max_coast_s=0.1, max_sigma_mm=1e4)
    tracker = _tracker_with_a_track()
    held = []
    for t in PERIOD * np.arange(4, 12):
        held.append(len(timed.hold(tracker, t)))
        tracker.update([], t)
    assert held[:4] == [1, 1, 1, 1] and sum(held[4:]) == 0  # 0.1 s after the last hit
    assert not tracker.tracks()  # then charged: deleted after max_misses
    tight = CoastPolicy(behind, range_mm=800.0, max_coast_s=10.0, max_sigma_mm=20.0)
    tracker = _tracker_with_a_track()
    held = []
    for t in PERIOD * np.arange(4, 40):
        held.append(len(tight.hold(tracker, t)))
        if not tracker.update([], t):
            break
    assert held[0] == 1 and held[-1] == 0  # held until its position std passed 20 mm
    assert not tracker.tracks()


def _circling(robot, coast, *, rate=0.5, half_angle=50.0, cycles=140):
    """A target circling the robot at 280 mm, each board seeing it within ``half_angle`` of
    its facing: 50 degrees leaves a gap of 22 degrees of arc (0.77 s at 0.5 rad/s, 31 cycles)
    between two boards' fields of view. The ids of the fused confirmed tracks near it per cycle."""
    rng = np.random.default_rng(7)
    spec = TrackSpec(max_misses=20, **CV)
    fuser = Fuser({b.name: b.mount for b in robot.boards}, period_s=PERIOD, spec=spec, coast=coast)
    offsets = {"front": 0.0, "left": 0.0057, "back": 0.0113, "right": 0.017}
    ids = []
    for cycle in range(cycles):
        for name, off in offsets.items():
            t = cycle * PERIOD + off
            p = np.array([280 * math.cos(rate * t + 0.3), 280 * math.sin(rate * t + 0.3), 0.0])
            m = robot.board(name).mount
            v = p - m.translation_mm
            targets = []
            if v @ m.facing >= math.cos(math.radians(half_angle)) * np.linalg.norm(v):
                q = m.to_board(p) + rng.normal(0, 4.0, 3)
                targets = [(q, np.eye(3) * 16.0, 1.0)]
            for rec in fuser.add(BoardReport(name, t, targets)):
                ids.append({tr["track_id"] for tr in rec["tracks"]})
    return ids


def test_a_target_crossing_the_gap_between_two_fields_of_view_keeps_its_id(robot):
    # from front's field of view (0.3 rad) across the gap into left's (past 1.05 rad)
    kept = _circling(robot, CoastPolicy.from_robot(robot))
    assert set().union(*kept[20:]) == {0}  # one id throughout, coasting across the gap
    dropped = _circling(robot, None)  # the old rule: every cycle without a target is a miss
    assert len(set().union(*dropped[20:])) == 2


# --- the cones, the prediction and the bounds at their edges (mutation-testing round) ---------

BEHIND = [(np.array([10.0, 0, 0]), np.array([1.0, 0, 0]), 45.0)]  # the track at 0 is behind


def test_visible_in_any_boards_cone_whatever_the_facings_length():
    policy = CoastPolicy(
        [
            (np.zeros(3), np.array([1.0, 0, 0]), 45.0),
            (np.zeros(3), np.array([0.0, 5.0, 0]), 30.0),  # a facing need not be a unit vector
        ],
        range_mm=800.0,
    )
    pts = np.array([[500.0, 0, 0], [0, 500, 0], [-300, 300, 0], [400, 300, 0], [100, 900, 0]])
    # in the first cone only, in the second only, 45 degrees off the second's facing (and 135
    # off the first's), 37 off the first's, in the second's direction but beyond the range
    np.testing.assert_array_equal(policy.visible(pts), [True, True, False, True, False])


def test_the_robots_cones_reach_its_max_range():
    robot = load_robot("virtual-4")
    policy = CoastPolicy.from_robot(robot)
    assert policy.range_mm == pytest.approx(800.0)  # [trigger] max_range_m = 0.8
    front = robot.board("front").mount
    ahead = front.translation_mm + front.facing * np.array([[700.0], [900.0]])
    np.testing.assert_array_equal(policy.visible(ahead), [True, False])


def test_a_track_is_judged_where_it_will_be_at_the_cycle():
    """The track moves at about 1 m/s along x from behind a board (at x = 150 mm, facing +x)
    into its cone: 0.2 s later it is predicted in front of it, so it is charged, not held."""
    cone = [(np.array([150.0, 0, 0]), np.array([1.0, 0, 0]), 45.0)]
    moving = _tracker_with_a_track(velocity=(1000.0, 0.0, 0.0))  # last seen at x = 75 mm
    t = moving.last_time + 0.2
    assert len(CoastPolicy(cone, range_mm=800.0).hold(moving, t)) == 0
    still = _tracker_with_a_track()  # at x = 0: behind the board then too
    assert len(CoastPolicy(cone, range_mm=800.0).hold(still, still.last_time + 0.2)) == 1


def test_the_sigma_bound_is_on_the_largest_axis():
    """A track known to a few mm across but to about 100 mm in z is past a 50 mm bound."""
    tracker = Tracker(TrackSpec(max_misses=3, **CV))
    for k in range(4):
        cov = np.diag([4.0, 4.0, 40000.0])  # 2 mm, 2 mm and 200 mm
        tracker.update([BaseTarget(np.zeros(3), cov, ["a"])], k * PERIOD)
    t = 4 * PERIOD
    assert len(CoastPolicy(BEHIND, range_mm=800.0, max_sigma_mm=50.0).hold(tracker, t)) == 0
    assert len(CoastPolicy(BEHIND, range_mm=800.0, max_sigma_mm=150.0).hold(tracker, t)) == 1


def test_the_coast_time_counts_from_the_last_hit():
    """0.11 s of coast (4.4 cycles): held for 4 cycles, charged the 5th, seen again, then
    held for 4 cycles more."""
    policy = CoastPolicy(BEHIND, range_mm=800.0, max_coast_s=0.11, max_sigma_mm=1e4)
    tracker = _tracker_with_a_track()
    held = []
    for k in range(4, 14):
        t = k * PERIOD
        held.append(len(policy.hold(tracker, t)))
        hit = [BaseTarget(np.zeros(3), np.eye(3) * 4.0, ["a"])] if k == 8 else []
        tracker.update(hit, t)
    # cycles 4-7 coast (within 0.11 s of the hit at cycle 3), 8 is past it (then the hit),
    # 9-12 coast within 0.11 s of that hit, 13 is past it
    assert held == [1] * 4 + [0] + [1] * 4 + [0]
    assert policy.held == 8


def test_a_cycle_older_than_the_tracker_holds_nothing():
    policy = CoastPolicy(BEHIND, range_mm=800.0)
    tracker = _tracker_with_a_track()  # last updated at 3 periods
    assert len(policy.hold(tracker, 2 * PERIOD)) == 0  # a late cycle: no prediction backwards
    assert len(policy.hold(tracker, 4 * PERIOD)) == 1
