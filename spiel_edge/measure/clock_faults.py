"""Stamps against the truth on deterministic simulated clocks: drift, jitter and bad clocks.

No codec, no board, no wall time: a board clock (a function of the host's true time, drifting
``drift_ppm``, with an optional fault), TIME_SYNC exchanges whose two legs are each delayed
uniformly in [0, ``jitter_us``], and acquisitions at ``rate_hz`` that arrive a span plus a
jittered delay after their first sample. Every event is handed to the estimator
(:mod:`spiel_edge.device.timesync`) and the stamp guard (:mod:`spiel_edge.device.stamp_guard`)
in the order the host would see it, and each stamp is compared with the true time of its
acquisition's first sample.

Faults (``FAULTS``), from half-way through unless said: ``step+5s`` / ``step-2s`` (the board's
clock jumps), ``wrap2s`` (it wraps every 2 s, from the start), ``backwards`` (it runs
backwards), ``stuck`` (it stops), ``garbage`` / ``u64max`` (every 7th answer a random u64 /
u64::MAX), ``ahead1s`` (every answer 1 s ahead of the clock that stamps the acquisitions),
``alternating30ms`` (every other answer 30 ms ahead), ``bootstorm`` (6 s of reboots every
0.13 s: new boot id, clock from 0), ``answer-ahead1s-first`` (only the first answer 1 s ahead),
``backlog`` (not the board: the host stops reading for 2.5 s, then drains the queue at 1 ms a
frame, as a loaded machine did).
"""

from __future__ import annotations

import heapq
import logging

import numpy as np

from spiel_edge.device.stamp_guard import StampGuard
from spiel_edge.device.timesync import TimeSyncEstimator

__all__ = ["FAULTS", "run"]

FAULTS = (
    "step+5s",
    "step-2s",
    "wrap2s",
    "backwards",
    "stuck",
    "garbage",
    "u64max",
    "ahead1s",
    "answer-ahead1s-first",
    "alternating30ms",
    "bootstorm",
    "backlog",
)
SPAN_US = 64 / 22_000 * 1e6  # one acquisition: 64 samples at 22 kHz
T0 = 1000e6  # the host's clock at the start (us)


class _Board:
    def __init__(self, drift_ppm: float, fault: str, duration_us: float) -> None:
        self.rate = 1.0 + drift_ppm * 1e-6
        self.fault = fault
        self.fault_at = T0 + 0.5 * duration_us
        self.boots = [T0 - 3e6]  # booted 3 s before the host started syncing
        if fault == "bootstorm":
            self.boots += list(np.arange(self.fault_at, self.fault_at + 6e6, 0.13e6))

    def boot(self, t: float) -> int:
        return max(k for k, b in enumerate(self.boots) if b <= t)

    def clock(self, t: float) -> float:
        """The clock that stamps the acquisitions (us since boot)."""
        b = self.boots[self.boot(t)]
        value = (t - b) * self.rate
        f, at = self.fault, (self.fault_at - b) * self.rate
        if f == "wrap2s":
            return float(np.floor(value % 2e6))
        if t >= self.fault_at:
            if f == "step+5s":
                value += 5e6
            elif f == "step-2s":
                value -= 2e6
            elif f == "backwards":
                value = at - (value - at)
            elif f == "stuck":
                value = at
        return float(np.floor(max(value, 0.0)))

    def answer(self, t: float, k: int, rng: np.random.Generator) -> float:
        """The board time in the k-th TIME_SYNC answer, read at true host time t."""
        value = self.clock(t)
        f = self.fault
        if f == "garbage" and k % 7 == 6:
            return float(rng.integers(0, 2**64 - 1, dtype=np.uint64, endpoint=True))
        if f == "u64max" and k % 7 == 6:
            return float(2**64 - 1)
        if f == "ahead1s" or (f == "answer-ahead1s-first" and k == 0):
            return value + 1e6
        if f == "alternating30ms" and k % 2:
            return value + 30e3
        return value


def _schedule(duration_us: float) -> list[float]:
    """Send times: a burst of 4, then every 0.1 s for 64 exchanges, then every 0.25 s."""
    out = [T0 + k * 1e3 for k in range(4)]
    t = out[-1]
    while t < T0 + duration_us:
        t += 0.1e6 if len(out) < 64 else 0.25e6
        out.append(t)
    return out


def run(
    *,
    drift_ppm: float = 0.0,
    jitter_us: float = 1000.0,
    fault: str = "",
    duration_s: float = 120.0,
    rate_hz: float = 30.0,
    seed: int = 0,
) -> dict:
    """One simulated run: coverage of the stated uncertainty, stamps backwards, fallbacks."""
    if fault and fault not in FAULTS:
        raise ValueError(f"unknown fault {fault!r} (one of {', '.join(FAULTS)})")
    rng = np.random.default_rng(seed)
    duration_us = duration_s * 1e6
    board = _Board(drift_ppm, fault, duration_us)
    events: list[tuple[float, int, tuple]] = []
    for k, sent in enumerate(_schedule(duration_us)):
        up, down = rng.uniform(0.0, jitter_us, 2)
        read = sent + up
        answer = board.answer(read, k, rng)
        events.append((read + down, 0, (sent, answer, 0x1000 + board.boot(read))))
    t, last = T0 + 1e6 / rate_hz, 0.0
    while t < T0 + duration_us:
        arrival = t + SPAN_US + rng.uniform(0.0, jitter_us)
        stall_end = board.fault_at + 2.5e6
        if fault == "backlog" and t >= board.fault_at:  # read in order, 1 ms apart, from then
            arrival = max(arrival, stall_end, last + 1e3)
        arrival = last = max(arrival, last + 1.0)  # the link and the host's queue are FIFO
        events.append((arrival, 1, (t, board.clock(t))))
        t += 1e6 / rate_hz
    heapq.heapify(events)
    est = TimeSyncEstimator()
    guard = StampGuard(est)
    errors, bounds, stamps, sources, messages = [], [], [], [], 0
    while events:
        seen, kind, data = heapq.heappop(events)
        if kind == 0:
            sent, answer, boot_id = data
            est.add(sent, seen, answer, boot_id)
            messages += len(est.take_messages())
            continue
        truth, board_us = data
        got = guard.stamp(board_us, seen, SPAN_US)
        if got is None:
            continue
        errors.append(got.host_us - truth)
        bounds.append(got.uncertainty_us)
        stamps.append(got.host_us)
        sources.append(got.source == "arrival")
    err, u = np.abs(np.array(errors)), np.array(bounds)
    c = est.counters
    return {
        "drift_ppm": drift_ppm,
        "jitter_us": jitter_us,
        "fault": fault or "none",
        "seed": seed,
        "stamps": int(err.size),
        "within_uncertainty": round(float(np.mean(err <= u)), 4),
        "backwards": int(np.sum(np.diff(np.array(stamps)) < 0)),
        "from_arrival": round(float(np.mean(sources)), 4),
        "p50_error_us": round(float(np.median(err)), 1),
        "p95_error_us": round(float(np.percentile(err, 95)), 1),
        "p50_uncertainty_us": round(float(np.median(u)), 1),
        "log_messages": messages,
        "exchanges": c.exchanges,
        "dropped": c.long_rtt + c.backwards + c.outliers + c.absurd,
        "restarts": c.steps + c.resets,
    }


def sweep(*, duration_s: float = 120.0, seeds: int = 1) -> list[dict]:
    """Drift 0 to +-20,000 ppm at 0.1, 1 and 5 ms of jitter, then every fault at +-1 %."""
    logging.getLogger(__name__).debug("clock sweep: %g s per run, %d seeds", duration_s, seeds)
    out = []
    for seed in range(seeds):
        for jitter in (100.0, 1000.0, 5000.0):
            for drift in (0, 20, -100, 700, -700, 2000, -2000, 10_000, -10_000, 20_000, -20_000):
                out.append(run(drift_ppm=drift, jitter_us=jitter, duration_s=duration_s, seed=seed))
        for i, fault in enumerate(FAULTS):
            drift = 10_000.0 if i % 2 else -10_000.0
            out.append(run(drift_ppm=drift, fault=fault, duration_s=duration_s, seed=seed))
    return out
