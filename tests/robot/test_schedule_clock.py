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
    the 2 x 0.5 ms between them used, so neither hears the other. Two unknown times (widened
    by one margin together) leave that undecided and mark it; times TIME_SYNC measured to
    ± 20 us do not, and a pair that really closes the gap is marked either way."""
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


def test_marker_widening_of_mixed_and_malformed_uncertainties():
    """One unknown time beside a measured one widens by the margin plus the measured
    uncertainty (the unknown pulse may be a margin off its reported time); a NaN or negative
    uncertainty is unknown, never a narrower window."""
    s = Schedule.from_robot(load_robot("virtual-4"), window_s=0.003)
    back = s.fire_time("back", 0.0, 3)
    right = s.fire_time("right", 0.0, 3) - 0.49e-3  # 0.49 ms early: within its margin
    for u_back, u_right, heard in (
        (None, 20e-6, ["back"]),  # 0.5 + 0.02 ms of the 1 ms between them: undecided, marked
        (20e-6, 20e-6, []),
        (float("nan"), 20e-6, ["back"]),
        (-1.0, 20e-6, ["back"]),
        (20e-6, float("inf"), ["back"]),
    ):
        m = CrosstalkMarker(s, ["back", "right"])
        m.observe("back", back, uncertainty_s=u_back)
        assert m.observe("right", right, uncertainty_s=u_right) == heard, (u_back, u_right)
    m = CrosstalkMarker(s, ["back", "right"])  # two unknowns: one margin, 0.49 ms not marked
    m.observe("back", back)
    assert s.margin_s == pytest.approx(0.5e-3) and m.observe("right", right) == []


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


@pytest.mark.parametrize("latency_s", [0.0109, 0.0134, 0.030])
def test_slot_phase_learns_a_start_latency_beyond_half_a_period(latency_s):
    """A start latency past half the 25 ms period shows as an early landing (the phase wraps):
    the latency is a delay, so the lead is taken modulo the period and the next start lands in
    the slot (a latency past a whole period on a later grid point). A lead clamped to +-10 ms
    restarted such a board every 8 pulses for ever."""
    s, p = _phase(synced=True)
    p.started(True, host_timed=True)
    [p.observe(t) for t in _pulses(s, 10.0, 0, 8, latency_s)]
    assert p.lead_s == pytest.approx(latency_s % s.period_s, abs=1e-9)
    for start in range(3):  # sent lead_s early: lands on the slot, kept
        p.started(True, host_timed=True)
        landed = (latency_s - p.lead_s) % s.period_s
        results = [p.observe(t) for t in _pulses(s, 10.0, 8 + 8 * start, 8, landed)]
        assert not any(r for _, r in results)


def test_slot_phase_lead_is_a_median_on_the_circle():
    """Latencies a hair either side of a whole period (0.1 ms, then 24.95 ms: 0.05 ms early)
    are close: the lead stays near 0 (mod P), not halfway round at 12.5 ms."""
    s, p = _phase(synced=True)
    for first, landing in enumerate((0.1e-3, -0.05e-3)):
        p.started(True, host_timed=True)
        [p.observe(t) for t in _pulses(s, 10.0, 8 * first, 8, landing - p.lead_s)]
    gap = min(p.lead_s, s.period_s - p.lead_s)
    assert gap < 0.2e-3, p.lead_s


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
    assert synced_pulse(SimpleNamespace()) is None  # a version-1 acquisition has no stamp_host


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


# --- the schedule's checks, edges and marking (mutation-testing round) ------------------------

# window 3 ms, guard 4 ms, margin 0.5 ms: a slot is max(3, 4) + 2 x 0.5 = 5 ms
_SLOT = dict(window_s=0.003, guard_s=0.004, margin_s=0.0005)


def test_a_slot_starts_inside_the_period():
    from spiel_edge.errors import ConfigError
    from spiel_edge.robot.schedule import Slot

    for offset in (-0.001, 0.025):  # before the period, and the next period's start
        with pytest.raises(ConfigError, match="outside the 25 ms period"):
            Schedule([Slot("a", offset)], period_s=0.025, **_SLOT)
    last = Schedule([Slot("a", 0.020)], period_s=0.025, **_SLOT)  # its slot ends at the period's
    assert last.slot_s == pytest.approx(0.005)


def test_slots_overlap_across_the_wrap_around():
    from spiel_edge.errors import ConfigError
    from spiel_edge.robot.schedule import Slot

    # b's slot (22-27 ms) runs 2 ms into the next period, where a's slot starts
    with pytest.raises(ConfigError, match="'a' .* and 'b' .* overlap"):
        Schedule([Slot("a", 0.0), Slot("b", 0.022)], period_s=0.025, **_SLOT)
    with pytest.raises(ConfigError, match="overlap"):  # the same, listed the other way round
        Schedule([Slot("b", 0.022), Slot("a", 0.0)], period_s=0.025, **_SLOT)
    # 20-25 ms touches a's next start exactly: allowed
    s = Schedule([Slot("a", 0.0), Slot("b", 0.020)], period_s=0.025, **_SLOT)
    assert s.span_s == pytest.approx(0.025)  # first start to the last slot's end
    assert Schedule([Slot("a", 0.005), Slot("b", 0.015)], period_s=0.025, **_SLOT).span_s == (
        pytest.approx(0.015)
    )


def test_a_period_shorter_than_the_slots_is_refused():
    from spiel_edge.errors import ConfigError
    from spiel_edge.robot.schedule import Slot

    # one board whose slot (5 ms) is longer than the period: no pair to overlap, still refused
    with pytest.raises(ConfigError, match="too short for 1 boards"):
        Schedule([Slot("a", 0.0)], period_s=0.0045, **_SLOT)
    slots = [Slot(n, i * 0.005) for i, n in enumerate("abcd")]
    assert len(Schedule(slots, period_s=0.020, **_SLOT).slots) == 4  # exactly full
    with pytest.raises(ConfigError, match="too short for 4 boards"):
        Schedule(slots[:3] + [Slot("d", 0.0149)], period_s=0.0199, **_SLOT)


def test_hears_includes_the_clock_margin_on_both_sides():
    s = Schedule.from_robot(load_robot("virtual-4"), window_s=0.003)
    u = s.margin_s
    assert u == pytest.approx(0.5e-3)
    early = 1.0 - s.guard_s - u / 2  # within the margin before the guard
    late = 1.0 + 0.003 + u / 2  # within the margin after the window
    assert s.hears(1.0, early) and s.hears(1.0, late)
    # the margin is the caller's to set: without it, both are outside
    assert not s.hears(1.0, early, margin_s=0.0) and not s.hears(1.0, late, margin_s=0.0)
    assert s.hears(1.0, 1.0 - s.guard_s, margin_s=0.0) and s.hears(1.0, 1.003, margin_s=0.0)


def test_next_fire_before_the_schedule_starts_is_its_first_pulse():
    s = Schedule.from_robot(load_robot("virtual-4"), window_s=0.003)
    first = s.fire_time("back", 10.0, 0)
    assert s.next_fire("back", 10.0, 9.0) == pytest.approx(first)
    assert s.next_fire("back", 10.0, 10.0 - 3 * s.period_s) == pytest.approx(first)
    assert s.next_fire("back", 10.0, first) == pytest.approx(first)  # at: that pulse


def test_marker_checks_the_earlier_pulses_too():
    """A board's acquisition that reaches the marker after the other board's next pulse
    (a late report) is still checked against the pulse that reached its window."""
    s = Schedule.from_robot(load_robot("virtual-4"), window_s=0.003)
    m = CrosstalkMarker(s, ["front", "left"])
    t = 5.0
    assert m.observe("left", t) == []
    assert m.observe("left", t + s.period_s) == []
    assert m.observe("left", t + 2 * s.period_s) == []
    # front's pulse 1 ms after left's first: left's first pulse reached its window
    assert m.observe("front", t + 0.001) == ["left"]
    assert m.seen == {"front": 1, "left": 3} and m.marked == {"front": 1, "left": 0}


def test_trigger_window_ms_sets_the_window(write_robot):
    path = write_robot(
        [{"name": "a", "slot": "slot = 0"}, {"name": "b", "slot": "slot = 1"}],
        trigger="period_ms = 25.0\nmax_range_m = 0.8\nwindow_ms = 8.0",
    )
    s = Schedule.from_robot(load_robot(path))
    assert s.window_s == pytest.approx(0.008)
    assert s.slot_s == pytest.approx(0.008 + 2 * 0.5e-3)  # the window is longer than the guard
    assert s.slots["b"].offset_s == pytest.approx(s.slot_s)


def test_the_window_from_the_profiles_is_the_longest_boards(tmp_path):
    from importlib import resources

    text = (resources.files("spiel_edge") / "profile" / "builtin" / "spiel-icra23.toml").read_text()
    assert "n_samples = 64 " in text
    long = tmp_path / "long.toml"
    long.write_text(text.replace("n_samples = 64 ", "n_samples = 256 "))
    path = tmp_path / "robot.toml"
    path.write_text(
        '[robot]\nname = "t"\n[trigger]\nperiod_ms = 30.0\nmax_range_m = 0.8\n'
        f'[[board]]\nname = "a"\nport = "sim://a"\nprofile = "{long}"\nslot = 0\n'
        '[[board]]\nname = "b"\nport = "sim://b"\nslot = 1\n'
    )
    s = Schedule.from_robot(load_robot(path))
    assert s.window_s == pytest.approx(256 / 22000.0)  # board a's, not the last board's


# --- StampClock: the lower envelope, the drift's span and bound (mutation-testing round) -------


def test_stamp_clock_refuses_to_map_before_any_acquisition():
    clock = StampClock()
    assert not clock.ready
    with pytest.raises(ValueError, match="no acquisition"):
        clock.to_host(1.0)


def test_stamp_clock_level_is_the_smallest_delay_before_the_first_block():
    clock = StampClock()
    for k, latency in enumerate((0.005, 0.001, 0.003)):  # fewer than one block of 8
        clock.observe(2.0 + k * 0.025, 102.0 + k * 0.025 + latency)
    # transport only delays: the least delayed acquisition sets the mapping
    assert clock.to_host(2.1) == pytest.approx(102.1 + 0.001, abs=1e-9)
    clock.observe(2.075, 102.075)  # a repeated stamp is no reset
    clock.observe(2.075, 102.076)
    assert clock.resets == 0 and clock.to_host(2.1) == pytest.approx(102.1, abs=1e-9)


def test_stamp_clock_is_not_moved_by_a_congested_stretch():
    """Two blocks in which every acquisition is 5 ms late do not lift the level: the lower
    envelope's lowest point sets it (a delayed acquisition does not move it); they show in
    the uncertainty."""
    clock = StampClock()
    assert clock.uncertainty_s == float("inf")  # nothing fitted yet
    for k in range(200):  # 5 s at 40 Hz, no drift, 0.3 ms latency; the last 16 congested
        t = k * 0.025
        clock.observe(t - 7.0, t + 0.0003 + (0.005 if k >= 184 else 0.0))
    assert clock.drift == 0.0
    assert clock.to_host(4.0 - 7.0) == pytest.approx(4.0003, abs=1e-9)
    # the last four minima (the level's points): two on time, two 5 ms late
    assert clock.uncertainty_s == pytest.approx(0.005, abs=1e-9)


def test_stamp_clock_fits_no_drift_before_ten_seconds():
    rng = np.random.default_rng(5)
    clock = StampClock()
    board = 0.0
    for k in range(320):  # 8 s of a board 200 ppm slow, latency 0.3 ms + exp(0.5 ms)
        t = k * 0.025
        board = t * (1 - 200e-6)
        clock.observe(board, t + 0.0003 + rng.exponential(0.0005))
    assert clock.drift == 0.0  # the minima span under 10 s: no drift yet
    # the level comes from the recent minima: within 0.3 ms now (the oldest are 1.6 ms off)
    assert abs(clock.to_host(board) - (t + 0.0003)) < 3e-4
    for k in range(320, 800):  # 20 s in all: now it is fitted
        t = k * 0.025
        clock.observe(t * (1 - 200e-6), t + 0.0003 + rng.exponential(0.0005))
    assert clock.drift == pytest.approx(200e-6, rel=0.1)


def test_stamp_clock_drift_is_bounded():
    clock = StampClock()
    for k in range(800):  # 20 s of a board whose clock runs 1 % slow: not a crystal's drift
        t = k * 0.025
        clock.observe(t * 0.99, t + 0.0003)
    assert clock.drift == pytest.approx(1e-3, abs=1e-12)  # MAX_DRIFT: 0.1 %


def test_stamp_clock_lateness_counts_the_drift_far_from_the_board_epoch():
    """A board up for a day, 200 ppm slow: the lateness of a timely acquisition is its latency,
    not the drift times the board's time (here 17 s, which would read as a clock gone wrong)."""
    clock = StampClock()
    late = None
    for k in range(1200):  # 30 s
        t = 1000.0 + k * 0.025
        late = clock.observe((t + 86400.0) * (1 - 200e-6), t + 0.0003)
    assert clock.drift == pytest.approx(200e-6, rel=1e-3)
    assert abs(late) < 1e-4


def test_wait_until_returns_at_the_time_and_not_when_stopped(monkeypatch):
    import threading

    from spiel_edge.robot import clock as clock_mod

    now = [0.0]

    def sleep(s):
        now[0] += max(s, 0.0) + 1e-4  # each sleep (a spin too) takes a tick more than asked

    monkeypatch.setattr(clock_mod.time, "perf_counter", lambda: now[0])
    monkeypatch.setattr(clock_mod.time, "sleep", sleep)
    stop = threading.Event()
    assert clock_mod.wait_until(1.0, stop)
    assert 1.0 <= now[0] < 1.0 + 2e-4  # at the time, not a spin later
    stop.set()
    assert not clock_mod.wait_until(5.0, stop) and now[0] < 1.0 + 2e-4


def test_stamp_clock_learnt_during_a_backlog_is_learnt_afresh_not_called_off():
    """The first acquisitions queued 1.5 s while the host was busy, then it caught up, 1 ms a
    frame: later arrivals come earlier and earlier against that envelope, gradually. The
    estimate follows (or starts again): no disagreement; a sudden jump of the stamps is still
    flagged (the test above)."""
    clock = StampClock()
    arrival = 101.5
    for k in range(70):
        board = k * 0.025
        arrival = max(100.0 + board + 0.003, arrival + 0.001)  # queued, then drained in order
        late = clock.observe(board, arrival)
        assert late > -1.0, (k, late)
    assert clock.to_host(2.0) == pytest.approx(102.003, abs=1e-3)


def test_a_reader_behind_is_not_a_clock_off_but_a_time_from_the_future_is():
    """Delivery only delays: times 1.7 s in the past for 4 s (a loaded machine's backlog) are
    no disagreement, 5 s of them are; three times from 2 s in the future are at once."""
    from spiel_edge.robot.clock import Disagreement

    behind = Disagreement()
    assert not any(behind.observe(1.7, 100.0 + k * 0.025) for k in range(160))  # 4 s
    assert not behind.observe(0.01, 104.1)  # caught up: the count starts again
    assert not any(behind.observe(1.7, 105.0 + k * 0.025) for k in range(200))  # 4.975 s
    assert behind.observe(1.7, 110.0)  # 5 s behind, all the time
    ahead = Disagreement()
    assert [ahead.observe(-2.0, 100.0 + k) for k in range(3)] == [False, False, True]
