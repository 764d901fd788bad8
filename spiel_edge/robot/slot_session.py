"""``run --slot ROBOT:BOARD``: the board's stream started on its trigger slot of the clock the
robot's computers share, and kept there (the logic: robot/slot_keeper.py; this module is
its I/O: the session and the clock)."""

from __future__ import annotations

import logging
import threading
import time
from collections import deque

import numpy as np

from spiel_edge.robot.slot_keeper import SlotKeeper, StartAtTrust

log = logging.getLogger(__name__)


class SlottedStream:
    """Starts ``session``'s stream at its slot (``start``) and restarts it there when the
    keeper says so (``on_acquisition``, for every acquisition of the stream)."""

    def __init__(self, session, keeper: SlotKeeper, stop: threading.Event, **start_options):
        self.session = session
        self.keeper = keeper
        self.stop = stop
        self.start_options = start_options  # n_samples, sample_format
        self._stream = None  # the stream this started (the session may restart it itself)
        self.on_clock_of_board = False  # the last start named the slot in the board's clock
        self.trust = StartAtTrust(keeper.margin_s)  # does the board keep the named time?
        self._named: float | None = None  # the time the current stream was named to start
        self.phases_s: deque[float] = deque(maxlen=2000)  # the last pulses' phases (summary)

    def start(self):
        """Start the stream on the slot's start of the shared (Unix) clock: named in the
        board's clock where it offers that (START_AT, through TIME_SYNC), else by sending
        STREAM_START at that moment."""
        at = self.keeper.start_time(time.time())

        def by_host() -> bool:  # sent at the slot's moment instead
            _sleep_until_unix(self.keeper.start_time(time.time()), self.stop)
            return not self.stop.is_set()  # stopping: no new stream

        answer, named = start_in_time(
            self.session, self.trust, at, self.keeper.rate_hz, by_host, **self.start_options
        )
        self.on_clock_of_board = named
        self._named = at if named else None
        if answer is None:
            return None
        self.keeper.started()
        self._stream = answer
        return answer

    def on_acquisition(self, acq) -> None:
        if self._stream is None or self.stop.is_set():
            return
        if self.session.stream is not self._stream:  # the board came back: the session
            log.info("the stream was restarted (the board came back); back into its slot")
            self.start()  # restarted it at once, in no slot
            return
        if acq.stamp_host is None:
            return  # the clocks are not synced yet: nothing to place the pulse with
        if (acq.index - self._stream.first_acquisition) & 0xFFFFFFFF >= 1 << 31:
            return  # left over from before the last start
        if self._named is not None:  # the first pulse of a stream named to start at a time
            k = (acq.index - self._stream.first_acquisition) & 0xFFFFFFFF
            named = self._named + k * self.keeper.requested_period_s
            self._named = None
            if not self.trust.landed(named, acq.stamp_host) and not self.trust.usable:
                log.warning(
                    "the board does not start at the time of its clock it is given (%.2f ms "
                    "off); starting it by the host from now on",
                    (acq.stamp_host - named) * 1e3,
                )
        self.phases_s.append(self.keeper.phase_error(acq.stamp_host))
        if self.keeper.observe(acq.stamp_host) and not self.stop.is_set():
            log.info("the board left its slot; restarting it in the slot")
            self.start()

    def summary(self) -> str:
        p = np.abs(np.array(self.phases_s)) * 1e3
        phase = (
            f", |phase| median {np.median(p):.3f} ms, p95 {np.percentile(p, 95):.3f} ms"
            if p.size
            else ""
        )
        # a board found to ignore start times began when the host's request arrived
        on_clock = self.on_clock_of_board and self.trust.usable
        how = "started on the board's clock" if on_clock else "started by the host"
        return (
            f"slot: {self.keeper.restarts} restarts{phase} (margin {self.keeper.margin_s * 1e3:g} "
            f"ms; {how})"
        )


def start_in_time(session, trust: StartAtTrust, unix_at: float, rate_hz: float, by_host, **options):
    """The one slot starter of `run --slot` and `run --robot` (robot/board_worker.py): the
    stream named to start at ``unix_at`` in the board's clock (START_AT, TIME_SYNC synced) while
    ``trust`` says the board keeps such times, else sent by the host once ``by_host()`` has
    waited for the moment (False: stopping, no start). (the stream's answer or None, whether
    it was named in the board's clock)."""
    if trust.usable:
        answer = session.start_stream_at(unix_at, rate_hz=rate_hz, **options)
        if answer is not None:
            return answer, True
    if not by_host():
        return None, False
    return session.start_stream(rate_hz=rate_hz, **options), False


def _sleep_until_unix(at: float, stop: threading.Event) -> None:
    """Sleep until the Unix clock reads ``at`` (spinning the last 2 ms)."""
    while not stop.is_set():
        wait = at - time.time()
        if wait <= 0:
            return
        time.sleep(wait - 0.002 if wait > 0.003 else 0)


def slot_keeper_of(slot: str) -> SlotKeeper:
    """``--slot ROBOT:BOARD`` (a robot file or a built-in name, and one of its boards): its
    keeper; ConfigError naming what is wrong."""
    from spiel_edge.errors import ConfigError
    from spiel_edge.robot.description import load_robot

    robot_file, sep, board = slot.rpartition(":")
    if not sep or not robot_file or not board:
        raise ConfigError(f"--slot {slot!r}: ROBOT:BOARD, e.g. rover.toml:front")
    robot = load_robot(robot_file)
    names = [b.name for b in robot.boards]
    if board not in names:
        raise ConfigError(f"--slot {slot!r}: the robot has no board {board!r} ({', '.join(names)})")
    return SlotKeeper.from_robot(robot, board)


def start_in_slot(
    session, keeper: SlotKeeper, stop: threading.Event, stream: dict
) -> SlottedStream:
    """The stream started in the keeper's slot; protocol version 2 needed (its pulses on the
    host's clock), else DeviceError before any start."""
    from spiel_edge.errors import DeviceError

    if session.protocol_version < 2:
        raise DeviceError(
            f"{session.url}: --slot needs protocol version 2 (TIME_SYNC puts the board's pulses "
            f"on the shared clock); the board speaks {session.protocol_version}"
        )
    slotted = SlottedStream(session, keeper, stop, **stream)
    slotted.start()
    return slotted


def slot_starter(slot: str):
    """``--slot ROBOT:BOARD``'s starter for runtime/live.py's LiveRun (its ``in_slot``): the
    robot file read now (ConfigError naming what is wrong), the stream started in the slot
    when the board is open."""
    keeper = slot_keeper_of(slot)

    def in_slot(session, stop: threading.Event, stream: dict) -> SlottedStream:
        return start_in_slot(session, keeper, stop, stream)

    in_slot.keeper = keeper  # type: ignore[attr-defined]
    return in_slot
