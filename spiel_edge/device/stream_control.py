"""Streaming and reconnection for the device session: start, stop and status of the board's
stream, the acquisitions as they arrive, and waiting for an unplugged board to come back
(same serial number) before resuming the stream it had."""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Iterator
from dataclasses import replace

import numpy as np

from spiel_edge.device.acquisitions import LiveAcquisition
from spiel_edge.device.iq import iq_amplitude
from spiel_edge.device.sanity import FirmwareError, board_name
from spiel_edge.errors import (
    DeviceDisconnectedError,
    DeviceError,
    DeviceRequestError,
    DeviceTimeoutError,
)
from spiel_edge.link.discover import find_again
from spiel_edge.protocol import (
    MAX_RETRIES,
    Capability,
    SampleFormat,
    StreamStart,
    StreamStartResponse,
    StreamStatus,
    StreamStatusRequest,
    StreamStop,
)
from spiel_edge.protocol.errors import ErrorCode
from spiel_edge.protocol.stream_data import SAMPLE_SIZE, STREAM_HEADER

log = logging.getLogger(__name__)

RECONNECT_POLL_S = 0.05  # how often to look for a board that went away


class StreamingMixin:
    """Mixed into DeviceSession, whose state (link, assembly, inbox, counters) it uses."""

    protocol_version: int
    max_payload: int
    _status_base: StreamStatus | None

    # --- streaming -----------------------------------------------------------------------

    def start_stream(
        self,
        *,
        rate_hz: float = 50.0,
        n_samples: int = 0,
        n_acquisitions: int = 0,
        channel_mask: int = 0,
        sample_format: int = SampleFormat.U16_ENVELOPE,
        start_at_us: int = 0,
    ) -> StreamStartResponse:
        """Start streaming (stopping any stream the board still runs). ``channel_mask``: the
        physical channels to stream (0: all); a subset needs protocol version 2, where the
        acquisitions' rows are the mask's channels in increasing order. ``sample_format``
        I16_IQ asks for I/Q pairs (protocol 2; the acquisitions then carry envelope and phase).
        ``start_at_us``: acquisition 0 at that time of the board's clock (protocol 2 and
        Capability.START_AT; :meth:`board_time_at` converts a Unix time); a restart after
        the board came back starts at once."""
        if channel_mask and self.protocol_version < 2:
            raise DeviceError(
                f"{self.url}: a channel subset needs protocol version 2; the board speaks "
                f"{self.protocol_version}"
            )
        if not 0 <= start_at_us < 1 << 64:
            raise DeviceError(
                f"{self.url}: start_at_us {start_at_us} is not a time of the board's clock"
            )
        if start_at_us and not self.offers_start_at():
            raise DeviceError(
                f"{self.url}: the board cannot start a stream at a time of its clock "
                "(no START_AT capability under protocol 2)"
            )
        frame = STREAM_HEADER.size + SAMPLE_SIZE[SampleFormat.U16_ENVELOPE] * n_samples
        if n_samples and frame > self.max_payload:
            raise DeviceError(
                f"{self.url}: {n_samples} samples per channel need {frame}-byte stream frames; "
                f"the board's HELLO allows {self.max_payload} (max_payload)"
            )
        request = StreamStart(
            n_acquisitions, float(rate_hz), n_samples, sample_format, channel_mask, start_at_us
        )
        if sample_format == SampleFormat.I16_IQ:  # compile (or load) the kernel before data flows
            warm = np.zeros((1, 2), dtype=np.int16)
            iq_amplitude(warm)
            warm.setflags(write=False)  # reassembled samples are read-only views: their own type
            iq_amplitude(warm)
        self._stop_quietly()
        if self._status_base is None:  # the board's since-boot counters before this run
            self._status_base = self._request_status()
        self.assembly.begin(channel_mask)
        answer = self.request(request)
        assert isinstance(answer, StreamStartResponse)
        self.assembly.sanity.expect(board_name(self.url, self.hello), self.hello, answer)
        self.assembly.started(answer.first_acquisition)
        # a restart (the board came back, its clock restarted) starts at once
        self.stream, self._stream_request = answer, replace(request, start_at_us=0)
        self._last_data = time.monotonic() + self._wait_for_start_s(start_at_us)
        return answer

    def start_stream_at(self, unix_s: float, **stream) -> StreamStartResponse | None:
        """:meth:`start_stream` with acquisition 0 at Unix time ``unix_s``, named in the
        board's clock (START_AT, through TIME_SYNC); None where the board cannot be told (no
        START_AT, clocks not synced) or refused it (logged): then the caller sends
        STREAM_START at that moment instead."""
        board_at = self.board_time_at(unix_s) if self.offers_start_at() else None
        if board_at is None:
            return None
        try:
            return self.start_stream(start_at_us=board_at, **stream)
        except DeviceRequestError as exc:  # e.g. a clock mapping gone wrong
            log.warning("%s: the board refused a start on its clock (%s)", self.url, exc)
            return None

    def offers_start_at(self) -> bool:
        """STREAM_START can name a start on the board's clock (protocol 2, START_AT)."""
        return self._offers(Capability.START_AT)

    def _wait_for_start_s(self, start_at_us: int) -> float:
        """How long the stream will be silent before its first acquisition (the stall
        watchdog waits that much longer); 0 when it starts at once or cannot be mapped."""
        at = self.stamp(start_at_us) if start_at_us else None
        return max(0.0, at[0] - time.time()) if at else 0.0

    def stop_stream(self, *, retries: int = MAX_RETRIES) -> None:
        self._stream_request = None
        try:
            self.request(StreamStop(), retries=retries)
        finally:
            self.assembly.stop()

    def _stop_quietly(self) -> None:
        try:
            self.request(StreamStop())
        except DeviceRequestError as exc:  # some firmware refuses to stop what is not running
            if exc.code != ErrorCode.BAD_STATE:
                raise

    def stream_status(self) -> StreamStatus:
        """The board's counters (since its boot); ``counts()`` reports them from the start
        of this session's stream."""
        status = self._request_status()
        self.device_status = status
        return status

    def _request_status(self) -> StreamStatus:
        status = self.request(StreamStatusRequest())
        if not isinstance(status, StreamStatus):
            raise DeviceError(f"STREAM_STATUS answered with {type(status).__name__}")
        return status

    def acquisitions(self, stop: threading.Event | None = None) -> Iterator[LiveAcquisition]:
        """Acquisitions as they arrive, until ``stop`` is set; survives unplugs when
        ``reconnect`` is on (else DeviceDisconnectedError ends it)."""
        stop = stop or threading.Event()
        ready = self.assembly.ready
        while not stop.is_set():
            if ready:
                yield self.assembly.pop()  # counted as delivered here
                continue
            try:
                self._pump()
            except (DeviceDisconnectedError, DeviceTimeoutError) as exc:
                if not self.reconnect:
                    raise
                self._recover(exc, stop)

    def newest_only(self, max_behind_s: float = 0.0, max_reads: int = 64) -> int:
        """Read what the link holds now (never waiting) and drop every ready acquisition
        more than ``max_behind_s`` (board time) older than the newest, which is always kept:
        a host behind its board (interpreted kernels) rides out a hiccup within that bound
        and beyond it processes the newest and counts the others, instead of queueing
        without bound. How many were dropped."""
        link = self._require_link()
        for _ in range(max_reads):
            data = link.read(0.0)
            if not data:
                break
            ns = time.perf_counter_ns()
            self._inbox.extend((frame, ns) for frame in self.decoder.feed(data))
        while self._inbox:
            self._dispatch(*self._inbox.popleft())
        ready = self.assembly.ready
        if not ready:
            return 0
        oldest_kept = ready[-1].timestamp_us - max_behind_s * 1e6
        dropped = 0
        while len(ready) > 1 and ready[0].timestamp_us < oldest_kept:
            ready.popleft()
            dropped += 1
        return dropped

    def _pump(self) -> None:
        while self._inbox:
            self._dispatch(*self._inbox.popleft())
        if self.assembly.ready:
            return
        self._fill(self.poll_s)
        while self._inbox:
            self._dispatch(*self._inbox.popleft())
        self._link_services_tick()
        if self._stream_request is not None:
            self._check_progress()
        if self._stream_request is not None and time.monotonic() - self._last_data > self.stall_s:
            self._check_alive()

    def no_progress_limit_s(self) -> float:
        """How long a stream may go without a whole acquisition: 5 stall periods, or 3 of
        the board's acquisition periods when they are longer (10 s by default)."""
        request = self._stream_request
        period = 1.0 / request.rate_hz if request is not None and request.rate_hz > 0 else 0.0
        return max(5.0 * self.stall_s, 3.0 * period)

    def _check_progress(self) -> None:
        """A board that sends stream frames from which no acquisition can be assembled is
        reported (FirmwareError naming it) instead of being waited for without end."""
        assembly = self.assembly
        waited = time.monotonic() - assembly.progress_at
        if assembly.frames_since and waited > self.no_progress_limit_s():
            stats = assembly.assembler.stats
            raise FirmwareError(
                f"{board_name(self.url, self.hello)}: {assembly.frames_since} stream frames in "
                f"{waited:.1f} s but no whole acquisition (incomplete {stats.incomplete}, duplicates {stats.duplicates}, stale "
                f"{stats.stale}, inconsistent {stats.inconsistent}): a firmware bug; stopped"
            )

    def _check_alive(self) -> None:
        """No data for a while: a board that does not answer is treated as gone; one that
        stopped streaming by itself is asked to start again."""
        status = self.stream_status()
        self._last_data = time.monotonic()
        silent = time.monotonic() - self.assembly.frame_at
        if status.streaming and silent > self.no_progress_limit_s():
            raise FirmwareError(
                f"{board_name(self.url, self.hello)}: says it is streaming but sent no stream "
                f"data for {silent:.1f} s: a firmware bug; stopped"
            )
        if not status.streaming and self._stream_request is not None:
            log.warning("%s: the board stopped streaming; starting again", self.url)
            self.counters.restarts += 1
            self._resume_stream()

    def _resume_stream(self) -> None:
        request = self._stream_request
        if request is not None:
            self.start_stream(
                rate_hz=request.rate_hz,
                n_samples=request.n_samples,
                n_acquisitions=request.n_acquisitions,
                sample_format=request.sample_format,
                channel_mask=request.channel_mask,
            )

    # --- reconnection --------------------------------------------------------------------

    def _recover(self, cause: Exception, stop: threading.Event) -> None:
        self.counters.disconnects += 1
        log.warning("%s; waiting for the board to come back", cause)
        self.assembly.stop()
        self._drop_link()
        lost_at = time.monotonic()
        while not stop.wait(RECONNECT_POLL_S):
            if self.on_waiting is not None:
                self.on_waiting(time.monotonic() - lost_at)
            if (
                self.reconnect_timeout_s is not None
                and time.monotonic() - lost_at > self.reconnect_timeout_s
            ):
                raise DeviceDisconnectedError(
                    f"{self.url}: the board did not come back within {self.reconnect_timeout_s:g} s"
                )
            try:
                self._reopen()
            except DeviceError as exc:
                log.debug("%s: not back yet: %s", self.url, exc)
                self._drop_link()
                continue
            self.counters.reconnects += 1
            log.warning(
                "%s: board back after %.2f s; streaming again", self.url, time.monotonic() - lost_at
            )
            return

    def _reopen(self) -> None:
        candidates = [self.url]
        moved = find_again(self.identity) if self.identity is not None else None
        if moved and moved != self.url:
            candidates.append(moved)
        error: DeviceError | None = None
        for url in candidates:
            try:
                self._connect(url)
                self._resume_stream()
                return
            except DeviceError as exc:
                error = exc
                self._drop_link()
        assert error is not None
        raise error
