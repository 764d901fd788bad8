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


def test_marker_widens_a_pair_by_its_two_pulses_uncertainties():
    """Two boards inside their slots, one 0.3 ms late and the next 0.25 ms early: 0.55 ms of
    the 2 x 0.5 ms between them used, so neither hears the other. Unknown times (each ± half
    the margin) leave that undecided and mark it; times TIME_SYNC measured to ± 20 us do not,
    and a pair that really closes the gap is marked either way."""
    s = Schedule.from_robot(load_robot("virtual-4"), window_s=0.003)
    back, right = s.fire_time("back", 0.0, 3) + 0.3e-3, s.fire_time("right", 0.0, 3) - 0.25e-3
    assert not s.hears(right, back, margin_s=0.0)  # the truth: not reached
    unknown = CrosstalkMarker(s, ["back", "right"])
    unknown.observe("back", back)
    assert unknown.observe("right", right) == ["back"]
    measured = CrosstalkMarker(s, ["back", "right"])
    measured.observe("back", back, uncertainty_s=20e-6)
    assert measured.observe("right", right, uncertainty_s=20e-6) == []
    # right 1.05 ms early instead: back's pulse is inside its guard time, heard
    measured.observe("back", back + s.period_s, uncertainty_s=20e-6)
    late = right + s.period_s - 0.8e-3
    assert s.hears(late, back + s.period_s, margin_s=0.0)
    assert measured.observe("right", late, uncertainty_s=20e-6) == ["back"]
    # a measured uncertainty wider than half the margin (a clock not yet converged) widens more
    wide = CrosstalkMarker(s, ["back", "right"])
    wide.observe("back", back, uncertainty_s=0.4e-3)
    assert wide.observe("right", right + 0.3e-3, uncertainty_s=0.4e-3) == ["back"]
    unknown.observe("back", back + 2 * s.period_s)
    assert unknown.observe("right", right + 2 * s.period_s + 0.3e-3) == []


def _phase(synced: bool, t0: float = 10.0):
    from spiel_edge.robot.slot_keeper import SlotPhase

    s = Schedule.from_robot(load_robot("virtual-4"), window_s=0.003)
    p = SlotPhase(s, "left", t0)
    p.started(synced)
    return s, p


def _pulses(s, t0, first_cycle, n, offset_s):
    return [s.fire_time("left", t0, first_cycle + k) + offset_s for k in range(n)]


def test_slot_phase_protocol_1_takes_the_landing_as_the_links_latency():
    """A protocol-1 pulse carries the link's unseen latency: a stream that lands 0.8 ms off is
    taken as on time (reported at the slot's times), and only a change of phase beyond the
    margin from there restarts it."""
    s, p = _phase(synced=False)
    results = [p.observe(t) for t in _pulses(s, 10.0, 0, 24, 0.8e-3)]
    assert not any(restart for _, restart in results)
    slots = _pulses(s, 10.0, 0, 24, 0.0)
    np.testing.assert_allclose([t for t, _ in results[8:]], slots[8:], atol=1e-12)
    drifted = [p.observe(t) for t in _pulses(s, 10.0, 24, 16, 0.8e-3 + 0.6e-3)]
    assert any(restart for _, restart in drifted)
    assert drifted[-1][0] == pytest.approx(slots[-1] + 40 * s.period_s - 24 * s.period_s + 0.6e-3)


def test_slot_phase_protocol_2_counts_the_measured_phase():
    """A TIME_SYNC pulse is where the board fired: a start that landed 0.8 ms off (outside the
    0.5 ms margin) is redone after the settling pulses, and pulses are reported as measured."""
    s, p = _phase(synced=True)
    pulses = _pulses(s, 10.0, 0, 8, 0.8e-3)
    results = [p.observe(t) for t in pulses]
    assert [r for _, r in results] == [False] * 7 + [True]
    np.testing.assert_allclose([t for t, _ in results], pulses, atol=1e-12)
    # landed within the margin: kept, until the phase itself passes the margin
    p.started(True)
    kept = [p.observe(t) for t in _pulses(s, 10.0, 8, 16, 0.3e-3)]
    assert not any(r for _, r in kept)
    gone = [p.observe(t) for t in _pulses(s, 10.0, 24, 8, 0.6e-3)]
    assert gone[-1][1]


def test_slot_phase_learns_how_late_a_host_timed_start_lands():
    """A protocol-2 board started by the host (no START_AT) lands late by the request's
    latency: the start is redone, sent that much earlier, and then lands in the slot."""
    s, p = _phase(synced=True)
    p.started(True, host_timed=True)
    latency = 0.8e-3
    results = [p.observe(t) for t in _pulses(s, 10.0, 0, 8, latency)]
    assert results[-1][1] and p.lead_s == pytest.approx(latency)
    p.started(True, host_timed=True)  # sent lead_s early: lands on the slot
    again = [p.observe(t) for t in _pulses(s, 10.0, 8, 16, latency - p.lead_s)]
    assert not any(r for _, r in again) and p.lead_s == pytest.approx(latency)
    # a start named in the board's clock teaches nothing about the request's latency
    p.started(True, host_timed=False)
    [p.observe(t) for t in _pulses(s, 10.0, 24, 8, 0.2e-3)]
    assert p.lead_s == pytest.approx(latency)


def test_synced_pulse_does_not_take_the_acquisitions_late_wall_clock_read():
    """An acquisition's ``host_time`` is read when it is assembled, after its bytes arrived
    (``received_ns``): 4 ms later on a loaded computer. Converting its TIME_SYNC time with that
    pair moved the pulse 4 ms (run --robot marked it as another board's cross-talk)."""
    import time
    from types import SimpleNamespace

    from spiel_edge.robot.clock import synced_pulse

    now_perf, now_unix = time.perf_counter(), time.time()
    acq = SimpleNamespace(
        stamp_host=now_unix - 0.010,  # fired 10 ms ago
        received_ns=int(now_perf * 1e9),
        host_time=now_unix + 0.004,
    )
    assert synced_pulse(acq) == pytest.approx(now_perf - 0.010, abs=5e-4)
    assert synced_pulse(SimpleNamespace(stamp_host=None)) is None


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
