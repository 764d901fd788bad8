"""The virtual robot offline, in virtual time: every board's pulses, clocks and links.

:func:`simulate` drives a :class:`spiel_edge.sim.robot.RobotWorld` without the protocol or a
host clock, fast and reproducibly (tools/bench/robot_eval.py, tests/robot/): free-running boards, or
boards kept in their trigger slots by the host logic of robot/schedule.py and robot/clock.py.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from spiel_edge.sim.robot import BoardFrame, RobotWorld


@dataclass
class BoardClockTruth:
    """A board's clock: ``board_s = (t - boot_s) * (1 + drift)``."""

    boot_s: float
    drift: float

    def board_time(self, t: float) -> float:
        return (t - self.boot_s) * (1.0 + self.drift)

    def true_time(self, board_s: float) -> float:
        return self.boot_s + board_s / (1.0 + self.drift)


@dataclass
class Acquisition:
    board: str
    index: int
    t_fire: float  # true time of the pulse
    board_us: int  # the board's stamp
    arrival: float  # host time its last byte arrived
    frame: BoardFrame
    host_pulse: float = 0.0  # the pulse as the host reports it (run --robot's protocol-1 path)


def simulate(
    world: RobotWorld,
    *,
    cycles: int,
    scheduled: bool,
    seed: int = 0,
    drift_ppm: float = 200.0,
    latency_s: tuple[float, float] = (0.3e-3, 0.5e-3),
    want_clean: bool = False,
    crosstalk: bool = True,
):
    """Every board's acquisitions over ``cycles`` periods, in arrival order.

    Unscheduled, each board streams at the period on its own clock from a random phase
    (boards free-running side by side). Scheduled, the host starts each board in its slot
    (robot/schedule.py) and keeps it there as ``run --robot`` keeps a protocol-1 board: it
    maps the board's stamps to host time (robot/clock.py, from the arrivals), corrects the
    board's rate by the estimated drift and restarts it in its slot when its pulses stray more
    than the sync margin (robot/slot_keeper.py's ``SlotPhase``, which also gives each
    acquisition's ``host_pulse``).
    Returns (acquisitions, restarts per board)."""
    from spiel_edge.robot.clock import StampClock
    from spiel_edge.robot.schedule import Schedule
    from spiel_edge.robot.slot_keeper import SlotPhase

    rng = np.random.default_rng([seed, 0xC10C])
    sched = Schedule.from_robot(world.robot, window_s=world.n_samples / world.sample_rate_hz)
    period = sched.period_s
    window = sched.window_s
    names = world.names
    clocks = {
        n: BoardClockTruth(rng.uniform(-5.0, 5.0), rng.uniform(-drift_ppm, drift_ppm) * 1e-6)
        for n in names
    }
    host_clock = {n: StampClock() for n in names}
    t0 = 1.0
    # per board: the stream: start true time, board-time period
    stream = {}
    for n in names:
        if scheduled:
            stream[n] = (t0 + sched.slots[n].offset_s, period)
        else:
            stream[n] = (t0 + rng.uniform(0, period), period)
    # board clock -> true time of the k-th pulse of the current stream
    count = {n: 0 for n in names}
    restarts = {n: 0 for n in names}
    end = t0 + cycles * period
    pending: list[tuple[float, str]] = []

    def next_pulse(n: str) -> float:
        start, p_board = stream[n]
        c = clocks[n]
        b0 = c.board_time(start)
        return c.true_time(b0 + count[n] * p_board)

    out: list[Acquisition] = []
    phase = {n: SlotPhase(sched, n, t0) for n in names}
    fired: dict[str, list[float]] = {n: [] for n in names}
    # generate pulses in true-time order
    nxt = {n: next_pulse(n) for n in names}
    index = {n: 0 for n in names}
    while True:
        n = min(nxt, key=nxt.get)
        t = nxt[n]
        if t >= end:
            break
        fired[n].append(t)
        count[n] += 1
        nxt[n] = next_pulse(n)
        pending.append((t, n))
        # a pulse's frame is made once every pulse that could reach its window is known
        horizon = min(nxt.values())
        while pending and pending[0][0] + window < horizon:
            tp, bp = pending.pop(0)
            pulses = [
                (o, tt)
                for o in names
                if o != bp
                for tt in _near(fired[o], tp - 2 * window - sched.guard_s, tp + window)
            ]
            frame = world.frame(bp, tp, pulses, crosstalk=crosstalk, want_clean=want_clean)
            stamp = clocks[bp].board_time(tp)
            arrival = tp + window + latency_s[0] + rng.exponential(latency_s[1])
            acq = Acquisition(bp, index[bp], tp, int(stamp * 1e6), arrival, frame)
            index[bp] += 1
            out.append(acq)
            hc = host_clock[bp]
            hc.observe(stamp, arrival)
            acq.host_pulse = hc.to_host(stamp) - window  # as run --robot maps a protocol-1 board
            if scheduled:
                acq.host_pulse, off_slot = phase[bp].observe(acq.host_pulse)
                if off_slot:
                    # restart in the slot: the next slot start after now, rate corrected
                    restart_at = sched.next_fire(bp, t0, arrival + 2e-3)
                    stream[bp] = (restart_at + rng.uniform(0, 0.1e-3), period / (1 + hc.drift))
                    count[bp] = 0
                    restarts[bp] += 1
                    phase[bp].started(False)
                    nxt[bp] = next_pulse(bp)
                elif abs(stream[bp][1] - period / (1 + hc.drift)) > 1e-9 and index[bp] % 64 == 0:
                    # rate correction alone: continue from the next pulse at the new rate
                    b_next = clocks[bp].board_time(nxt[bp])
                    start_true = clocks[bp].true_time(b_next)
                    stream[bp] = (start_true, period / (1 + hc.drift))
                    count[bp] = 0
                    nxt[bp] = next_pulse(bp)
        if len(out) > cycles * len(names) + 10:
            break
    out.sort(key=lambda a: a.arrival)
    return out, restarts, clocks


def _near(times: list[float], lo: float, hi: float) -> list[float]:
    res = []
    for t in reversed(times):
        if t < lo:
            break
        if t <= hi:
            res.append(t)
    return res
