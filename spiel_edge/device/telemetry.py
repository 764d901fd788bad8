"""What the board says by itself (protocol version 2): HEARTBEAT and LOG frames.

Pure apart from logging: the session hands it each frame with the time it arrived. Heartbeats
tell the session the board is alive between acquisitions (``silent_for``); log lines go to the
``spiel_edge.board_config`` logger (the journal under systemd), with the board named, their text made
printable and bounded, and at most ``rate_per_s`` lines a second (a token bucket): a board that
floods its log costs a counter, never the host's disk.
"""

from __future__ import annotations

import logging
from dataclasses import asdict, dataclass

from spiel_edge.protocol.link_messages import (
    KNOWN_ERROR_FLAGS,
    BoardState,
    ErrorFlag,
    Heartbeat,
    LogMessage,
)
from spiel_edge.safety.shown import escape

__all__ = ["BoardTelemetry", "TelemetryCounters"]

board_log = logging.getLogger("spiel_edge.board_config")

TEXT_MAX = 200  # characters of one forwarded line
RATE_PER_S = 20.0  # lines per second forwarded at most
BURST = 40.0
SUMMARY_EVERY_S = 10.0  # how often suppressed lines are summed up
MISSED_BEATS = 3  # heartbeats missed before the board is called silent
SLACK_S = 0.1  # on top of MISSED_BEATS periods: scheduling and link delays (then a probe)


def _level(severity: int) -> int:
    """syslog severity -> logging level."""
    if severity <= 3:
        return logging.ERROR
    if severity == 4:
        return logging.WARNING
    if severity <= 6:
        return logging.INFO
    return logging.DEBUG


def _printable(text: str) -> str:
    clean = escape(text[: TEXT_MAX + 1])  # the one escaping function (safety/shown.py)
    return clean if len(clean) <= TEXT_MAX else clean[:TEXT_MAX] + "..."


@dataclass
class TelemetryCounters:
    heartbeats: int = 0
    board_logs: int = 0  # LOG lines received
    board_logs_suppressed: int = 0  # received but not forwarded (host rate limit)
    board_logs_dropped: int = 0  # dropped on the board (its own rate limit or queue)
    unknown_flags: int = 0  # heartbeats with error flags this host does not know

    def as_dict(self) -> dict[str, int]:
        return asdict(self)


class BoardTelemetry:
    def __init__(self, name: str, *, rate_per_s: float = RATE_PER_S, burst: float = BURST):
        self.name = name  # how the board is named in the host's log
        self.rate_per_s, self.burst = rate_per_s, burst
        self.counters = TelemetryCounters()
        self.period_s: float | None = None  # heartbeat period in effect; None: not expected
        self.last_beat: float | None = None  # host monotonic time of the last heartbeat
        self.last: Heartbeat | None = None
        self._tokens = burst
        self._refilled: float | None = None
        self._suppressed_since_summary = 0
        self._summary_at: float | None = None
        self._flags_reported = 0
        self._flags_seen = 0

    def expect(self, period_ms: int, now: float) -> None:
        """The board confirmed a heartbeat period (0: none)."""
        self.period_s = period_ms / 1000.0 if period_ms else None
        self.last_beat = now

    def heartbeat(self, beat: Heartbeat, now: float) -> None:
        self.counters.heartbeats += 1
        previous = self.last
        self.last, self.last_beat = beat, now
        if beat.period_ms:
            self.period_s = beat.period_ms / 1000.0
        unknown = beat.error_flags & ~KNOWN_ERROR_FLAGS
        if unknown:
            self.counters.unknown_flags += 1
            if unknown & ~self._flags_reported:
                self._flags_reported |= unknown
                board_log.warning(
                    "%s: heartbeat with unknown error flags 0x%08x (a newer firmware?); ignored",
                    self.name,
                    unknown,
                )
        known = beat.error_flags & KNOWN_ERROR_FLAGS
        new = known & ~self._flags_seen
        if new:
            names = ", ".join(f.name.lower() for f in ErrorFlag if f and new & f)
            quiet = ErrorFlag.TRIAL_IMAGE | ErrorFlag.DEFAULT_CONFIG  # states, not faults
            level = logging.INFO if not new & ~quiet else logging.WARNING
            board_log.log(level, "%s: the board reports %s", self.name, names)
        self._flags_seen = known
        if beat.state == BoardState.ERROR and (
            previous is None or previous.state != BoardState.ERROR
        ):
            board_log.warning("%s: the board reports an error state", self.name)

    def silent_for(self, now: float) -> float | None:
        """Seconds since the last heartbeat when that is more than MISSED_BEATS periods."""
        if self.period_s is None or self.last_beat is None:
            return None
        quiet = now - self.last_beat
        return quiet if quiet > MISSED_BEATS * self.period_s + SLACK_S else None

    def log_line(self, line: LogMessage, now: float) -> None:
        c = self.counters
        c.board_logs += 1
        c.board_logs_dropped += line.dropped
        if self._refilled is not None:
            self._tokens = min(self.burst, self._tokens + (now - self._refilled) * self.rate_per_s)
        self._refilled = now
        if self._tokens < 1.0:
            c.board_logs_suppressed += 1
            self._suppressed_since_summary += 1
            if self._summary_at is None:
                self._summary_at = now + SUMMARY_EVERY_S
            self.summarise(now)
            return
        self._tokens -= 1.0
        self.summarise(now)
        dropped = f" ({line.dropped} earlier lines dropped by the board)" if line.dropped else ""
        board_log.log(_level(line.level), "%s: %s%s", self.name, _printable(line.text), dropped)

    def summarise(self, now: float, *, force: bool = False) -> None:
        if not self._suppressed_since_summary:
            return
        if force or (self._summary_at is not None and now >= self._summary_at):
            board_log.warning(
                "%s: %d board log lines not shown (more than %g lines/s)",
                self.name,
                self._suppressed_since_summary,
                self.rate_per_s,
            )
            self._suppressed_since_summary = 0
            self._summary_at = now + SUMMARY_EVERY_S
