"""Trigger slots from the maximum range, cross-talk marking, and the per-board clock."""

from __future__ import annotations

import numpy as np
import pytest

from spiel_edge.robot.clock import StampClock
from spiel_edge.robot.description import load_robot
from spiel_edge.robot.schedule import CrosstalkMarker, Schedule


def test_slot_length_is_window_or_guard_plus_margins():
    robot = load_robot("virtual-4")
    s = Schedule.from_robot(robot, window_s=64 / 22000)
    assert s.guard_s == pytest.approx(2 * 0.8 / 343.0)
    assert s.slot_s == pytest.approx(max(64 / 22000, 2 * 0.8 / 343.0) + 2 * 0.5e-3)
    offsets = sorted(sl.offset_s for sl in s.slots.values())
    np.testing.assert_allclose(np.diff(offsets), s.slot_s)
    # a pulse in another board's slot never reaches a window, nor does a window's pulse
    # reach the other board's window
    for a in s.slots:
        for b in s.slots:
            if a != b:
                ta, tb = s.fire_time(a, 0.0, 3), s.fire_time(b, 0.0, 3)
                for k in (-1, 0, 1):
                    assert not s.hears(ta, tb + k * s.period_s)


def test_hears_follows_the_range_and_the_window():
    s = Schedule.from_robot(load_robot("virtual-4"), window_s=0.003)
    assert s.hears(1.0, 1.0 - s.guard_s + 1e-4)  # its far echoes still arrive
    assert s.hears(1.0, 1.0 + 0.002)  # fired while the window is open
    assert not s.hears(1.0, 1.0 - s.guard_s - s.margin_s - 1e-4)
    assert not s.hears(1.0, 1.0 + 0.003 + s.margin_s + 1e-4)


def test_next_fire_and_phase_error():
    s = Schedule.from_robot(load_robot("virtual-4"), window_s=0.003)
    t = s.next_fire("back", 10.0, 10.3)
    assert t >= 10.3 and t - 10.3 < s.period_s
    assert s.phase_error("back", 10.0, t) == pytest.approx(0.0, abs=1e-12)
    assert s.phase_error("back", 10.0, t + 0.001) == pytest.approx(0.001)
    assert s.phase_error("back", 10.0, t - 0.001) == pytest.approx(-0.001)


def test_marker_marks_what_another_pulse_reached():
    s = Schedule.from_robot(load_robot("virtual-4"), window_s=0.003)
    m = CrosstalkMarker(s, ["front", "left", "back", "right"])
    for cycle in range(5):  # on schedule: nothing marked
        for name in ("front", "left", "back", "right"):
            assert m.observe(name, s.fire_time(name, 0.0, cycle)) == []
    # left fires 1 ms after front: each hears the other
    t = s.fire_time("front", 0.0, 5)
    assert m.observe("front", t) == []  # left's next pulse is predicted in its slot
    assert m.observe("left", t + 0.001) == ["front"]
    assert m.marked["left"] == 1 and m.marked["front"] == 0


@pytest.mark.parametrize("drift_ppm", [-200.0, 0.0, 150.0])
def test_stamp_clock_maps_within_a_fraction_of_a_millisecond(drift_ppm):
    rng = np.random.default_rng(3)
    clock = StampClock()
    errors = []
    for k in range(2000):  # 50 s at 40 Hz, board clock 3.2 s off, latency 0.3 ms + exp(0.5 ms)
        t = 1.0 + k * 0.025
        board = (t - 3.2) * (1 + drift_ppm * 1e-6)
        clock.observe(board, t + 0.0003 + rng.exponential(0.0005))
        if k > 400:
            errors.append(clock.to_host(board) - (t + 0.0003))
    assert np.percentile(np.abs(errors), 95) < 2e-4
    if drift_ppm:
        assert clock.drift == pytest.approx(-drift_ppm * 1e-6, rel=0.1)


def test_stamp_clock_restarts_when_the_board_resets_and_flags_a_jump():
    clock = StampClock()
    for k in range(40):
        clock.observe(5.0 + k * 0.025, 100.0 + k * 0.025)
    assert clock.to_host(5.5) == pytest.approx(100.5, abs=1e-9)
    clock.observe(0.0, 101.1)  # the board rebooted: its clock starts again
    assert clock.resets == 1 and clock.to_host(0.1) == pytest.approx(101.2, abs=1e-9)
    for k in range(1, 20):
        clock.observe(k * 0.025, 101.1 + k * 0.025)
    late = clock.observe(20 * 0.025 + 3.0, 101.1 + 20 * 0.025)  # stamps jump 3 s ahead
    assert late == pytest.approx(-3.0, abs=1e-6)
