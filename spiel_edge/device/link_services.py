"""The device session's protocol version 2 side: clock sync, heartbeat and board logs.

Mixed into DeviceSession. After a HELLO that chose version 2 and offers the capabilities, the
session syncs the clocks at once (a short burst of TIME_SYNC exchanges), asks for heartbeats
and log lines, and from then on syncs every ``sync_period_s`` while it pumps the stream and
watches the heartbeat: a board silent for more than three periods is named and treated as
gone (the reconnect path), before the stream's own stall timeout would notice. A version-1
board gets none of these requests.
"""

from __future__ import annotations

import logging
import time

from spiel_edge.device.stamp_guard import StampGuard
from spiel_edge.device.telemetry import BoardTelemetry
from spiel_edge.device.timesync import TimeSyncEstimator
from spiel_edge.errors import DeviceError, DeviceTimeoutError
from spiel_edge.protocol import Capability, decode_message
from spiel_edge.protocol.errors import MessageError
from spiel_edge.protocol.framing import Frame
from spiel_edge.protocol.link_messages import (
    HEARTBEAT,
    LOG,
    Heartbeat,
    LogLevel,
    LogMessage,
    Telemetry,
    TelemetryResponse,
    TimeSync,
    TimeSyncResponse,
)

log = logging.getLogger(__name__)

SYNC_PERIOD_S = 0.25  # TIME_SYNC exchanges while streaming
SYNC_BURST = 4  # exchanges right after the handshake
HEARTBEAT_MS = 500  # the period the host asks for
SYNC_TIMEOUT_S = 0.25  # an answer later than this is useless for the clock anyway
PROBE_S = 0.2  # heartbeats late: a board that does not answer within this has stopped


class SessionLinkServices:
    """Needs from DeviceSession: request(), hello, url, _sent_ns, _answer_ns."""

    def _link_services_init(self) -> None:
        self.sync_period_s = SYNC_PERIOD_S
        self.heartbeat_ms = HEARTBEAT_MS
        self.clock = TimeSyncEstimator()
        self.stamps = StampGuard(self.clock)
        self._fallback_said: str | None = None
        self._last_unix = 0.0
        self.telemetry = BoardTelemetry(self.url)
        self._next_sync = 0.0
        self._wall_minus_perf_ns = time.time_ns() - time.perf_counter_ns()
        self._sent_ns = 0
        self._answer_ns = 0
        self.sync_timeouts = 0  # TIME_SYNC exchanges without an answer (not session timeouts)

    def _offers(self, capability: int) -> bool:
        hello = self.hello
        return bool(hello and hello.protocol_version >= 2 and hello.capabilities & capability)

    def _link_services_start(self) -> None:
        """After every handshake (a reconnect too)."""
        hello = self.hello
        assert hello is not None
        self.telemetry.name = f"board {hello.serial or '?'} ({self.url})"
        if self.clock.boot_id is not None and self.clock.boot_id != hello.boot_id:
            self.clock.reset(hello.boot_id)
        if self._offers(Capability.TELEMETRY):
            answer = self.request(Telemetry(self.heartbeat_ms, LogLevel.INFO, 20))
            if isinstance(answer, TelemetryResponse):
                self.telemetry.expect(answer.heartbeat_ms, time.monotonic())
        else:
            self.telemetry.period_s = None
        if self._offers(Capability.TIME_SYNC):
            for _ in range(SYNC_BURST):
                self.sync_clock()

    # --- clock -----------------------------------------------------------------------------

    def sync_clock(self) -> bool:
        """One TIME_SYNC exchange into the estimator; False if it gave nothing."""
        self._next_sync = time.monotonic() + self.clock.interval(self.sync_period_s)
        if not self._offers(Capability.TIME_SYNC):
            return False
        try:
            answer = self.request(
                TimeSync(time.perf_counter_ns() // 1000),
                timeout_s=SYNC_TIMEOUT_S,
                retries=0,
                probe=True,
            )
        except DeviceTimeoutError:
            self.sync_timeouts += 1
            return False  # the stream goes on; the next exchange will do
        if not isinstance(answer, TimeSyncResponse):
            return False
        self._wall_minus_perf_ns = time.time_ns() - time.perf_counter_ns()
        used = self.clock.add(
            self._sent_ns / 1000.0, self._answer_ns / 1000.0, answer.board_time_us, answer.boot_id
        )
        for message in self.clock.take_messages():
            log.warning("%s: %s", self.telemetry.name, message)
        return used

    def stamp(self, board_us: int) -> tuple[float, float] | None:
        """(Unix seconds, uncertainty us) of a board time, or None while unsynced."""
        mapped = self.clock.map(board_us)
        if mapped is None:
            return None
        host_us, uncertainty = mapped
        return (host_us * 1000.0 + self._wall_minus_perf_ns) / 1e9, uncertainty

    def stamp_acquisition(
        self, board_us: int, received_ns: int, span_us: float
    ) -> tuple[float, float, str] | None:
        """An acquisition's (Unix s, uncertainty us, source): the board's clock mapped, or,
        where that contradicts the acquisition, its arrival (device/stamp_guard.py); None
        while unsynced."""
        got = self.stamps.stamp(board_us, received_ns / 1000.0, span_us)
        if got is None:
            return None
        if got.source == "arrival" and self.stamps.reason != self._fallback_said:
            self._fallback_said = self.stamps.reason  # said once per reason, not per record
            log.warning(
                "%s: %s: stamps from the host's arrival time (+-%.1f ms) until it agrees again",
                self.telemetry.name,
                self.stamps.reason,
                got.uncertainty_us / 1000.0,
            )
        elif got.source == "board" and self._fallback_said is not None:
            self._fallback_said = None
            log.info("%s: stamps from the board's clock again", self.telemetry.name)
        unix, u = (got.host_us * 1000.0 + self._wall_minus_perf_ns) / 1e9, got.uncertainty_us
        if unix < self._last_unix:  # the wall clock's offset re-read since: never backwards
            u += (self._last_unix - unix) * 1e6
            unix = self._last_unix
        self._last_unix = unix
        return unix, u, got.source

    def board_time_at(self, unix_s: float) -> int | None:
        """The board's clock (us since boot) when the Unix clock reads ``unix_s``, or None
        while unsynced (the inverse of :meth:`stamp`)."""
        board_us = self.clock.unmap((unix_s * 1e9 - self._wall_minus_perf_ns) / 1000.0)
        return None if board_us is None else round(board_us)

    # --- frames the board sends by itself --------------------------------------------------

    def _link_services_frame(self, frame: Frame, ns: int) -> bool:
        if frame.is_response or frame.msg_type not in (HEARTBEAT, LOG):
            return False
        try:
            msg = decode_message(frame)
        except MessageError as exc:
            log.debug("%s: bad telemetry frame: %s", self.url, exc)
            self.assembly.bad_messages += 1
            return True
        now = time.monotonic()
        if isinstance(msg, Heartbeat):
            self.telemetry.heartbeat(msg, now)
        elif isinstance(msg, LogMessage):
            self.telemetry.log_line(msg, now)
        return True

    def _link_services_tick(self) -> None:
        """From the stream loop: periodic sync and the heartbeat watch."""
        now = time.monotonic()
        silent = self.telemetry.silent_for(now)
        if silent is not None:
            if self._answers():  # the host was slow (load, a long pause), not the board
                log.debug("%s: heartbeat late by %.1f s but the board answers", self.url, silent)
                self.telemetry.last_beat = time.monotonic()
                return
            self.telemetry.last_beat = None  # once per silence
            raise DeviceTimeoutError(
                f"{self.telemetry.name}: no heartbeat for {time.monotonic() - now + silent:.1f} s "
                f"(period {self.telemetry.period_s:g} s) and no answer: the board stopped"
            )
        self.telemetry.summarise(now)
        if now >= self._next_sync and self._offers(Capability.TIME_SYNC):
            try:
                self.sync_clock()
            except DeviceError as exc:
                log.debug("%s: time sync: %s", self.url, exc)

    def _answers(self) -> bool:
        """A quick request: does the board answer at all (any answer counts)?"""
        try:
            self.request(
                TimeSync(time.perf_counter_ns() // 1000), timeout_s=PROBE_S, retries=0, probe=True
            )
        except DeviceTimeoutError:
            return False
        except DeviceError:
            return True  # an error answer is an answer
        return True

    def link_service_counts(self) -> dict[str, int]:
        c = self.clock.counters
        return {
            **self.telemetry.counters.as_dict(),
            "sync_exchanges": c.used,
            "sync_dropped": c.long_rtt + c.backwards + c.outliers + self.sync_timeouts,
        }
