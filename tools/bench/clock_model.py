"""Time sync on a simulated clock: minutes of board time in seconds, through the real codec.

A virtual board (``SimDevice``, drifting clock, jittered link) runs on a virtual clock; the
host side sends TIME_SYNC requests as the session does (a burst of 4 after the handshake and
one every ``sync_period_s``), reads the answers the moment the link releases them, and feeds
the same estimator (:mod:`spiel_edge.device.timesync`). Between exchanges, acquisitions at
``rate_hz`` are stamped by the board's clock and mapped back with the estimate as it was at
that moment: the error against the true host time is what ``stamp_host`` would have been off.
``reset_at_s`` reboots the board once (its clock restarts at 0, a new boot id) and the host
handshakes again, as the session does after a reconnect.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from spiel_edge.device.link_services import SYNC_BURST, SYNC_PERIOD_S
from spiel_edge.device.timesync import TimeSyncEstimator
from spiel_edge.protocol import FrameDecoder, Hello, decode_message, encode_message
from spiel_edge.protocol.link_messages import TimeSync, TimeSyncResponse

__all__ = ["ClockSyncResult", "simulate"]

STEP_S = 10e-6  # virtual-time resolution of the host's reads


@dataclass
class ClockSyncResult:
    errors_us: np.ndarray  # stamp_host - truth, per acquisition
    uncertainties_us: np.ndarray  # the stated uncertainty, per acquisition
    times_s: np.ndarray  # host time of each acquisition
    after_reset: np.ndarray  # bool per acquisition: after the board reset
    exchanges: int
    dropped: int
    counters: dict

    def p95_us(self) -> float:
        return float(np.percentile(np.abs(self.errors_us), 95))

    def summary(self) -> dict:
        err = np.abs(self.errors_us)
        out = {
            "acquisitions": int(err.size),
            "p50_us": round(float(np.median(err)), 1),
            "p95_us": round(self.p95_us(), 1),
            "max_us": round(float(err.max()), 1),
            "within_uncertainty": round(float(np.mean(err <= self.uncertainties_us)), 4),
            "exchanges": self.exchanges,
            "dropped": self.dropped,
        }
        if self.after_reset.any():
            ratio = err[self.after_reset] / self.uncertainties_us[self.after_reset]
            first = np.flatnonzero(self.after_reset)[:50]
            out["after_reset_within_uncertainty"] = round(float(np.mean(ratio <= 1.0)), 4)
            out["after_reset_worst_error_over_uncertainty"] = round(float(ratio.max()), 3)
            out["after_reset_first50_max_us"] = round(float(err[first].max()), 1)
        return out


def simulate(
    *,
    duration_s: float = 600.0,
    drift_ppm: float = 200.0,
    jitter_us: float = 1000.0,
    rate_hz: float = 30.0,
    sync_period_s: float = SYNC_PERIOD_S,
    reset_at_s: float | None = None,
    sync_fault: str = "",
    seed: int = 0,
) -> ClockSyncResult:
    from spiel_edge.link.sim_options import SimOptions
    from spiel_edge.sim.device import SimDevice

    clock = [1000.0]  # host seconds (arbitrary epoch)
    options = SimOptions(
        name="clock",
        scene="replay",
        drift_ppm=drift_ppm,
        jitter_us=jitter_us,
        sync_fault=sync_fault,
        seed=seed,
    )
    device = SimDevice(options, clock=lambda: clock[0])
    decoder = FrameDecoder()
    estimator = TimeSyncEstimator()
    seq = [0]

    def exchange(msg) -> tuple[object, float, float]:
        seq[0] = (seq[0] + 1) & 0xFFFF
        sent = clock[0]
        device.write(encode_message(msg, seq=seq[0]))
        deadline = sent + 0.5
        while clock[0] < deadline:
            clock[0] += STEP_S
            for frame in decoder.feed(device.read(1 << 16)):
                if frame.is_response and frame.seq == seq[0]:
                    return decode_message(frame), sent, clock[0]
        return None, sent, clock[0]

    def handshake() -> None:
        exchange(Hello(1, 2, 8256, 0))
        for _ in range(SYNC_BURST):
            sync()

    def sync() -> None:
        answer, sent, received = exchange(TimeSync(int(clock[0] * 1e6)))
        if isinstance(answer, TimeSyncResponse):
            estimator.add(sent * 1e6, received * 1e6, answer.board_time_us, answer.boot_id)
            estimator.take_messages()

    handshake()
    start = clock[0]
    next_sync = clock[0] + sync_period_s
    next_acq = clock[0] + 1.0 / rate_hz
    reset_pending = reset_at_s is not None
    errors, uncert, times, after = [], [], [], []
    reset_done = False
    while clock[0] - start < duration_s:
        if reset_pending and clock[0] - start >= reset_at_s:
            reset_pending = False
            device.board.boot(clock[0])  # the board resets: its clock restarts at 0
            device.discard_output()
            clock[0] += 0.3  # gone from the bus while it reboots
            handshake()
            estimator.reset(device.board.boot_id)
            for _ in range(SYNC_BURST):
                sync()
            reset_done = True
            next_acq = max(next_acq, clock[0])
            next_sync = clock[0] + estimator.interval(sync_period_s)
        if next_acq <= next_sync:
            clock[0] = max(clock[0], next_acq)
            truth = clock[0]
            board_us = device.board.clock_us(truth)
            mapped = estimator.map(board_us)
            if mapped is not None:
                errors.append(mapped[0] - truth * 1e6)
                uncert.append(mapped[1])
                times.append(truth - start)
                after.append(reset_done)
            next_acq += 1.0 / rate_hz
        else:
            clock[0] = max(clock[0], next_sync)
            sync()
            next_sync = max(next_sync + estimator.interval(sync_period_s), clock[0])
    c = estimator.counters
    return ClockSyncResult(
        np.array(errors),
        np.array(uncert),
        np.array(times),
        np.array(after, dtype=bool),
        c.exchanges,
        c.long_rtt + c.backwards + c.outliers,
        c.as_dict(),
    )
