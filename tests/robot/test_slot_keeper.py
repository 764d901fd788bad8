"""`run --slot`'s logic (robot/slot_keeper.py): a board's pulses brought onto its slot of a
clock shared between computers, whatever the start's latency and the board's drift."""

from __future__ import annotations

import math

import numpy as np
import pytest

from spiel_edge.robot.description import load_robot
from spiel_edge.robot.slot_keeper import SlotKeeper


class Board:
    """A board that starts ``latency_s`` after STREAM_START (± jitter) and fires at the
    requested period on its own clock, ``drift`` fast against the shared one."""

    def __init__(self, latency_s: float, drift: float, jitter_s: float = 0.0, seed: int = 0):
        self.latency_s, self.drift, self.jitter_s = latency_s, drift, jitter_s
        self.rng = np.random.default_rng(seed)

    def pulses(self, start: float, period: float, n: int) -> np.ndarray:
        first = start + self.latency_s + self.rng.uniform(-self.jitter_s, self.jitter_s)
        return first + np.arange(n) * period / (1.0 + self.drift)


def run(keeper: SlotKeeper, board: Board, pulses: int, now: float = 1796220000.123):
    """Pulses as the board fires them, restarted when the keeper says so: (phase errors of
    every pulse, restarts)."""
    errors = []
    while len(errors) < pulses:
        start = keeper.start_time(now)
        assert start >= now
        keeper.started()
        for t in board.pulses(start, keeper.requested_period_s, pulses - len(errors)):
            errors.append(keeper.phase_error(t))
            now = t
            if keeper.observe(t):
                break
    return np.array(errors), keeper.restarts


def test_the_phase_is_the_distance_to_the_nearest_slot_start():
    k = SlotKeeper(0.025, 0.005, 0.0005)
    assert k.phase_error(1000.005) == pytest.approx(0.0, abs=1e-9)
    assert k.phase_error(1000.0062) == pytest.approx(0.0012, abs=1e-9)
    assert k.phase_error(1000.0041) == pytest.approx(-0.0009, abs=1e-9)
    assert k.phase_error(1000.017) == pytest.approx(-0.013, abs=1e-9) or k.phase_error(
        1000.017
    ) == pytest.approx(0.012, abs=1e-9)
    with pytest.raises(ValueError):
        SlotKeeper(0.025, 0.03, 0.0005)


@pytest.mark.parametrize("latency_ms", [0.0, 3.0, 11.0, 20.0])
def test_a_late_start_is_learned_and_the_next_lands_in_the_slot(latency_ms):
    keeper = SlotKeeper(0.025, 0.00566, 0.0005)
    errors, restarts = run(keeper, Board(latency_ms / 1000, 0.0), 400)
    assert restarts <= 1 and (restarts == 1) == (latency_ms > 0.5)
    assert np.all(np.abs(errors[16:]) <= 0.0005)  # from the second start on
    assert keeper.lead_s == pytest.approx(math.remainder(latency_ms / 1000, 0.025), abs=1e-6)


@pytest.mark.parametrize("drift_ppm", [-200.0, 80.0, 200.0])
def test_a_drifting_board_is_corrected_and_restarts_rarely(drift_ppm):
    """±200 ppm moves the phase 5 us per 25 ms pulse: out of a 0.5 ms margin within 100
    pulses uncorrected (10-23 restarts in 2000 pulses); with the drift fitted 2-3 in 2000."""
    keeper = SlotKeeper(0.025, 0.0, 0.0005)
    errors, restarts = run(keeper, Board(0.002, drift_ppm * 1e-6, jitter_s=5e-5), 2000)
    assert restarts <= 4
    assert np.all(np.abs(errors[100:]) <= 0.0005)  # restarted before leaving the slot
    # the board fires at its requested period / (1 + drift): asked for the drift-corrected one
    assert keeper.requested_period_s / (1 + drift_ppm * 1e-6) == pytest.approx(0.025, rel=2e-5)
    assert keeper.rate_hz == pytest.approx(1.0 / keeper.requested_period_s)  # the rate asked


def test_the_slot_comes_from_the_robot_file():
    robot = load_robot("virtual-4")
    left = SlotKeeper.from_robot(robot, "left")
    assert (left.period_s, left.margin_s) == (0.025, 0.0005)
    assert left.offset_s == pytest.approx(0.00566, abs=1e-5)  # slot 1 of 5.66 ms slots


def test_a_stream_the_session_restarted_goes_back_into_its_slot():
    """The board came back and its session restarted the stream on its own (in no slot): the
    next acquisition starts it again in the slot; acquisitions left over from before a start
    are not taken as the new stream's."""
    import threading
    import types

    from spiel_edge.robot.slot_session import SlottedStream

    class Session:
        def __init__(self):
            self.stream, self.starts = None, []

        def start_stream_at(self, unix_s, **stream):
            return None  # a board that cannot be told: started by the host, at the slot's time

        def start_stream(self, rate_hz, **options):
            self.starts.append(rate_hz)
            self.stream = types.SimpleNamespace(first_acquisition=100 * len(self.starts))
            return self.stream

    session = Session()
    keeper = SlotKeeper(0.025, 0.005, 0.0005)
    slotted = SlottedStream(session, keeper, threading.Event())
    slotted.start()
    assert session.starts == [40.0]

    def acq(index, t):
        return types.SimpleNamespace(index=index, stamp_host=t)

    slotted.on_acquisition(acq(5, 1000.0))  # before this stream's first: left over
    assert not slotted.phases_s
    slotted.on_acquisition(acq(100, 1000.0052))
    assert list(slotted.phases_s) == [pytest.approx(0.0002, abs=1e-9)]
    session.stream = types.SimpleNamespace(first_acquisition=0)  # the session's own restart
    slotted.on_acquisition(acq(0, 1000.5))
    assert len(session.starts) == 2 and slotted.phases_s.maxlen == 2000
    assert "slot: 0 restarts" in slotted.summary()


def test_a_board_with_start_at_is_given_its_slot_in_its_own_clock():
    """A board that offers START_AT gets STREAM_START at once, naming the slot's start in its
    clock (the session's TIME_SYNC mapping), not sent at the slot's moment."""
    import threading
    import time
    import types

    from spiel_edge.robot.slot_session import SlottedStream

    class Session:
        stream = None

        def start_stream_at(self, unix_s, **stream):
            self.sent_at, self.start_at_unix = time.time(), unix_s
            self.stream = types.SimpleNamespace(first_acquisition=0)
            return self.stream

    session, keeper = Session(), SlotKeeper(0.5, 0.2, 0.0005)
    slotted = SlottedStream(session, keeper, threading.Event())
    slotted.start()
    assert keeper.phase_error(session.start_at_unix) == pytest.approx(0.0, abs=1e-9)
    assert session.start_at_unix - session.sent_at >= 0.02  # asked ahead, not at the moment
    assert "started on the board's clock" in slotted.summary()
    for _ in range(2):  # two first pulses far from their named time: the board ignores them
        slotted.trust.landed(0.0, 1.0)
    assert "started by the host" in slotted.summary()  # also before any restart came


def test_a_start_on_the_boards_clock_that_is_refused_is_made_by_the_host(caplog):
    """A board that offers START_AT but refuses the time it is given (here: a clock mapping
    a minute off): one warning, and the stream is started by the host at the slot's moment."""
    import threading
    import time

    from spiel_edge.device import DeviceSession
    from spiel_edge.robot.slot_session import SlottedStream
    from spiel_edge.sim import protocol_sim

    keeper = SlotKeeper(0.05, 0.01, 0.0005)
    url = "sim://slot-start-refused"
    with DeviceSession(url, reconnect=False) as session:
        session.sync_clock()
        mapped = session.board_time_at
        session.board_time_at = lambda unix_s: mapped(unix_s) + 61_000_000  # a minute off
        slotted = SlottedStream(session, keeper, threading.Event(), n_samples=64)
        with caplog.at_level("WARNING"):
            answer = slotted.start()
        sent = time.time()
        session.stop_stream()
    protocol_sim.forget(url)
    assert answer is not None and not slotted.on_clock_of_board
    assert "refused a start on its clock" in caplog.text and "60 s" in caplog.text
    assert abs(keeper.phase_error(sent)) < 0.01  # sent at the slot's moment


def test_start_at_trust_ends_after_two_starts_in_a_row_that_miss():
    from spiel_edge.robot.slot_keeper import StartAtTrust

    trust = StartAtTrust(0.0005)
    assert trust.landed(10.0, 10.0003) and trust.usable  # within the margin
    assert not trust.landed(20.0, 20.004) and trust.usable  # one miss
    assert trust.landed(30.0, 30.0001) and trust.usable  # a hit clears it
    assert not trust.landed(40.0, 39.99) and trust.usable
    assert not trust.landed(50.0, 50.01) and not trust.usable  # two in a row: no more


def test_the_start_at_ignored_lie_never_lands_on_the_named_grid_by_chance():
    """The virtual board's `lie=start-at-ignored` starts at once, but half a period later when
    "at once" falls within 1 ms of the named grid: the lie shows on every start."""
    from spiel_edge.sim.lies import ignoring_start_times

    first_due = ignoring_start_times(lambda start_at_us, period_s, now: 10.0)
    assert first_due(1, 0.025, 3.0123) == 3.0123  # off the grid: at once
    assert first_due(1, 0.025, 3.0) == pytest.approx(3.0125)  # on it: half a period later
    assert first_due(1, 0.025, 3.0249) == pytest.approx(3.0374)


def test_a_slot_outside_its_period_or_no_margin_is_refused():
    for period, offset, margin in [
        (0.025, 0.025, 0.0005),  # the next period's start
        (0.025, -0.001, 0.0005),
        (0.025, 0.005, 0.0),  # no margin to keep the phase within
        (0.0, 0.0, 0.0005),
    ]:
        with pytest.raises(ValueError):
            SlotKeeper(period, offset, margin)
    assert SlotKeeper(0.025, 0.0249, 0.0005).offset_s == 0.0249


def _settle(keeper: SlotKeeper, start: float, late_s: float) -> list[bool]:
    """The first SETTLE (8) pulses of a stream started at ``start``, each ``late_s`` late."""
    from spiel_edge.robot.slot_keeper import SETTLE

    keeper.started()
    return [keeper.observe(start + late_s + i * keeper.period_s) for i in range(SETTLE)]


def test_a_start_just_outside_the_margin_is_redone_and_one_inside_is_kept():
    keeper = SlotKeeper(0.025, 0.005, 0.0005)
    start = keeper.start_time(1000.0)
    # 0.8 ms late (more than the 0.5 ms margin): restarted once the 8th pulse tells it
    assert _settle(keeper, start, 0.0008) == [False] * 7 + [True]
    assert keeper.restarts == 1 and keeper.lead_s == pytest.approx(0.0008, abs=1e-9)
    start = keeper.start_time(start + 1.0)
    assert keeper.phase_error(start) == pytest.approx(-0.0008, abs=1e-9)  # sent that early
    # this time 0.3 ms late (the link got slower): kept, and learned for the next start
    assert _settle(keeper, start, 0.0008 + 0.0003) == [False] * 8
    assert keeper.restarts == 1 and keeper.lead_s == pytest.approx(0.0011, abs=1e-9)


def test_every_start_is_learned_afresh():
    """The settling pulses belong to each start: a start after a restart is learned again."""
    keeper = SlotKeeper(0.025, 0.005, 0.0005)
    start = keeper.start_time(1000.0)
    assert _settle(keeper, start, 0.003)[-1]  # 3 ms late: restart
    start = keeper.start_time(start + 1.0)
    assert _settle(keeper, start, 0.003 + 0.001)[-1]  # the link is 1 ms slower now: again
    assert keeper.restarts == 2 and keeper.lead_s == pytest.approx(0.004, abs=1e-9)
    start = keeper.start_time(start + 1.0)
    assert _settle(keeper, start, 0.004) == [False] * 8  # and now it lands


def test_one_stray_pulse_does_not_restart_the_stream():
    """The phase is judged by the median of 8 pulses, every 8 pulses: one pulse stamped 2 ms
    off (a late stamp) right after the settling pulses restarts nothing."""
    keeper = SlotKeeper(0.025, 0.005, 0.0005)
    start = keeper.start_time(1000.0)
    assert _settle(keeper, start, 0.0) == [False] * 8
    t = start + 8 * keeper.period_s
    assert not keeper.observe(t + 0.002)
    assert not any(keeper.observe(t + i * keeper.period_s) for i in range(1, 40))
    assert keeper.restarts == 0 and keeper.requested_period_s == 0.025


def test_a_jump_in_the_phase_is_no_drift():
    """The pulses jump 10 ms within a stream (say the host's clock was stepped): the stream is
    restarted, but a slope of more than 1 % is no clock's drift, so the period asked stays."""
    keeper = SlotKeeper(0.025, 0.005, 0.0005)
    start = keeper.start_time(1000.0)
    assert _settle(keeper, start, 0.0) == [False] * 8
    t = start + 8 * keeper.period_s
    restarted = [keeper.observe(t + 0.010 + i * keeper.period_s) for i in range(8)]
    assert restarted == [False] * 7 + [True] and keeper.restarts == 1
    assert keeper.requested_period_s == 0.025 and keeper.rate_hz == pytest.approx(40.0)


def test_a_late_first_start_does_not_skew_the_drift_correction():
    """docs/robot.md: ±200 ppm boards keep every pulse after the first 100 within the margin.
    A first start 12 ms late (redone once its 8 pulses show it) must not change that: the
    drift is the new stream's, not the jump from the old stream's phase to the new one's."""
    keeper = SlotKeeper(0.025, 0.0, 0.0005)
    errors, restarts = run(keeper, Board(0.012, 200e-6, jitter_s=5e-5), 2000)
    assert np.all(np.abs(errors[100:]) <= 0.0005)
