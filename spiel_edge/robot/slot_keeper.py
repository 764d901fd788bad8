"""One board's trigger slot kept on a clock that several computers share (``run --slot``).

Boards of one robot served by different processes or computers (``fuse`` over Zenoh) can
still take turns: every process reads the same robot file, so each board's slot is known,
and the computers' clocks are one clock when they are synchronised (chrony or PTP keep them
within tens of microseconds on a LAN; the robot file's ``sync_margin_ms`` must cover that).
Cycles are counted from the Unix epoch: board B fires at ``n P + offset_B`` for integers
``n``. With protocol version 2 each acquisition's ``stamp_host`` is its pulse on the host's
Unix clock (TIME_SYNC), so a process can see where its board fires against its slot.

:class:`SlotKeeper` is the pure logic (no clock, no I/O: times go in, decisions come out):

- when to send STREAM_START so the first pulse lands on a slot start: ``start_time(now)``,
  ``lead_s`` earlier than the slot, where ``lead_s`` is learned from how late the previous
  starts landed (the median phase of the first ``SETTLE`` pulses after each start);
- whether to restart: after a start that landed outside the sync margin, or when the median
  phase of the last ``CHECK_EVERY`` pulses strays past ``KEEP_WITHIN`` of it (the board's clock
  drifts against the host's: restarted before its pulses leave the slot); before such a restart the requested period is corrected by the drift fitted
  over the last pulses, so restarts become rare.

:class:`SlotPhase` is the same kind of logic for ``run --robot`` (one host, its process
clock), used by its board threads and by the offline virtual robot alike.
"""

from __future__ import annotations

import math
from collections import deque

import numpy as np

SETTLE = 8  # pulses after a start that tell how late it landed
CHECK_EVERY = 8  # pulses between checks of the phase
DRIFT_WINDOW = 128  # pulses the drift is fitted over
START_AHEAD_S = 0.03  # a start is planned at least this far ahead (the request's way out)
LATENCIES_KEPT = 5  # run --robot: host-timed starts whose latency sets the next one's lead
KEEP_WITHIN = 0.75  # a drifting stream is restarted once its phase is this share of the margin


class SlotKeeper:
    """See the module docstring. Times are seconds on the shared clock (Unix)."""

    def __init__(self, period_s: float, offset_s: float, margin_s: float):
        if not (period_s > 0 and 0 <= offset_s < period_s and margin_s > 0):
            raise ValueError(f"slot {offset_s} s in a {period_s} s period, margin {margin_s} s")
        self.period_s = period_s
        self.offset_s = offset_s
        self.margin_s = margin_s
        self.lead_s = 0.0  # a start goes out this long before its slot (learned)
        self.requested_period_s = period_s  # asked of the board (drift corrected)
        self.restarts = 0
        self._settle: list[float] = []
        self._recent: deque[float] = deque(maxlen=CHECK_EVERY)
        self._history: deque[tuple[float, float]] = deque(maxlen=DRIFT_WINDOW)
        self._seen = 0

    @classmethod
    def from_robot(cls, robot, board: str) -> SlotKeeper:
        """The slot of ``board`` in ``robot`` (robot/schedule.py's, checked there)."""
        from spiel_edge.robot.schedule import Schedule

        schedule = Schedule.from_robot(robot)
        return cls(schedule.period_s, schedule.slots[board].offset_s, schedule.margin_s)

    @property
    def rate_hz(self) -> float:
        return 1.0 / self.requested_period_s

    def phase_error(self, t: float) -> float:
        """Signed seconds from the nearest slot start to ``t``."""
        x = math.fmod(t - self.offset_s, self.period_s)
        x = x + self.period_s if x < 0 else x
        return x - self.period_s if x > self.period_s / 2 else x

    def start_time(self, now: float) -> float:
        """When to send STREAM_START: ``lead_s`` before the first slot start that leaves at
        least ``START_AHEAD_S`` from ``now``."""
        first = now + START_AHEAD_S + self.lead_s - self.offset_s
        n = math.ceil(first / self.period_s)
        return n * self.period_s + self.offset_s - self.lead_s

    def started(self) -> None:
        """A stream was just started (at ``start_time``): the pulses from now on are its (the
        drift is fitted over them alone: across a restart the phase jumps)."""
        self._settle = []
        self._recent.clear()
        self._history.clear()
        self._seen = 0

    def observe(self, t_pulse: float) -> bool:
        """One pulse of the current stream (its time on the shared clock); True: restart
        the stream (at ``start_time``, at ``rate_hz``)."""
        e = self.phase_error(t_pulse)
        self._history.append((t_pulse, e))
        self._seen += 1
        if len(self._settle) < SETTLE:
            self._settle.append(e)
            if len(self._settle) < SETTLE:
                return False
            landed = float(np.median(self._settle))
            self.lead_s += landed  # the next start goes out this much earlier (or later)
            return self._restart() if abs(landed) > self.margin_s else False
        self._recent.append(e)
        if self._seen % CHECK_EVERY:
            return False
        if abs(float(np.median(self._recent))) <= KEEP_WITHIN * self.margin_s:
            return False
        self._correct_period()
        return self._restart()

    def _correct_period(self) -> None:
        """The board's pulses drift by ``slope`` seconds per second against the shared
        clock: ask for a period that much shorter (or longer)."""
        h = np.array(self._history)
        if len(h) < 2 * CHECK_EVERY or np.ptp(h[:, 0]) <= 0:
            return
        errors = np.unwrap(h[:, 1] * (2 * np.pi / self.period_s)) * (self.period_s / (2 * np.pi))
        slope = float(np.polyfit(h[:, 0] - h[0, 0], errors, 1)[0])
        if abs(slope) < 0.01:  # a drift of 1 % is no clock's: a jump (a restart) in the window
            self.requested_period_s /= 1.0 + slope
        self._history.clear()

    def _restart(self) -> bool:
        self.restarts += 1
        return True


class SlotPhase:
    """One board's pulses against its slot in ``run --robot``: when to restart its stream, and
    the time each pulse is reported at (to the cross-talk marker and the fusion). Pure.

    The first ``SETTLE`` pulses after a start say how it landed. A pulse mapped by TIME_SYNC
    (``synced``: protocol 2) is the pulse's time within its stated uncertainty, so its phase is
    measured: a start that landed outside the sync margin is redone, later pulses count against
    the slot itself, and each is reported as measured, so the marker sees where the board
    really fires. A pulse from the one-way estimate (protocol 1) carries the link's smallest
    latency, which one-way stamps cannot show: the landing is taken as that bias, only a change
    of phase beyond the margin counts, and a pulse whose recent phase (less the bias) is within
    the margin is reported at the slot's time. A start the host times itself (no START_AT) goes
    out ``lead_s`` early: the request's latency, the median of the last few such starts' (each
    measured by how late it landed, a delay taken modulo the period)."""

    def __init__(self, schedule, board: str, t0: float):
        self.schedule = schedule
        self.board = board
        self.t0 = t0
        self.synced = False
        self.lead_s = 0.0
        self._latencies: deque[float] = deque(maxlen=LATENCIES_KEPT)
        self._learn_lead = False
        self._settle: list[float] = []
        self._bias_s = 0.0
        self._recent: deque[float] = deque(maxlen=CHECK_EVERY)
        self._seen = 0

    def started(self, synced: bool, host_timed: bool = False) -> None:
        """A stream was (re)started, or the pulses' time axis changed (``synced``: TIME_SYNC's
        mapping from now on; ``host_timed``: the host sent the start at the slot's moment, less
        ``lead_s``)."""
        self.synced = synced
        self._learn_lead = synced and host_timed
        self._settle = []
        self._bias_s = 0.0
        self._recent.clear()
        self._seen = 0

    def observe(self, pulse: float) -> tuple[float, bool]:
        """One pulse of the current stream (host time): (the time to report it at, whether
        to restart the stream in its slot)."""
        margin = self.schedule.margin_s
        err = self.schedule.phase_error(self.board, self.t0, pulse)
        self._seen += 1
        if len(self._settle) < SETTLE:
            self._settle.append(err)
            landed = float(np.median(self._settle))
            if not self.synced:
                self._bias_s = landed
            settled = self.synced and len(self._settle) == SETTLE
            if settled and self._learn_lead:
                # the whole latency, lead_s + landed, is a delay: in [0, P) (a latency beyond
                # a period lands on a later grid point, which is the slot's all the same); the
                # median of the last few, as one start's latency may be a scheduling hiccup
                period = self.schedule.period_s
                self._latencies.append((self.lead_s + landed) % period)
                ref = self._latencies[-1]  # a median on the circle: 0.1 and 24.9 ms are close
                near = [(x - ref + period / 2) % period - period / 2 for x in self._latencies]
                self.lead_s = float(ref + np.median(near)) % period
            return self._reported(pulse), settled and abs(landed) > margin
        self._recent.append(err)
        restart = (
            self._seen % CHECK_EVERY == 0
            and abs(float(np.median(self._recent)) - self._bias_s) > margin
        )
        return self._reported(pulse), restart

    def _reported(self, pulse: float) -> float:
        if self.synced:
            return pulse
        t = pulse - self._bias_s
        off = self.schedule.phase_error(self.board, self.t0, t)  # from the nearest slot start
        err = float(np.median(self._recent)) - self._bias_s if self._recent else off
        return t - off if abs(err) <= self.schedule.margin_s else t


class StartAtTrust:
    """Whether a board keeps the start time it is named (START_AT): ``STRIKES`` starts in a row
    whose first pulse lands more than ``margin_s`` from the named time (a firmware that offers
    the capability and ignores the field, or a clock mapping gone wrong) end it; the host then
    starts the board by itself, at the slot's moment. Pure: times in, a decision out."""

    STRIKES = 2

    def __init__(self, margin_s: float):
        self.margin_s = margin_s
        self.usable = True
        self._strikes = 0

    def landed(self, named_s: float, first_pulse_s: float) -> bool:
        """The first pulse of a stream started at ``named_s`` (both on one clock): whether it
        landed within the margin (a miss counts towards ending the trust: ``usable``)."""
        if abs(first_pulse_s - named_s) <= self.margin_s:
            self._strikes = 0
            return True
        self._strikes += 1
        if self._strikes >= self.STRIKES:
            self.usable = False
        return False
