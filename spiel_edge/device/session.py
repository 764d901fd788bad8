"""The device session: handshake, requests with retries, streaming and reconnection.

Single-threaded and never blocking longer than ``poll_s``: every read has a timeout, so a
stop event (SIGINT/SIGTERM in the CLI) is seen within one poll. Frames are handled in
arrival order: while a request waits for its answer, stream frames keep being assembled.

Requests carry a sequence number; a lost answer is retried with the same number at most
MAX_RETRIES times, and the board answers a repeated number from its cache without executing
the request again. When the link goes away (unplug, EIO, a board that stops answering) the
session closes it, waits for the same board (same serial number) to come back, handshakes
and resumes the stream it had: the caller's loop keeps running.
"""

from __future__ import annotations

import logging
import random
import time
from collections import deque
from collections.abc import Callable
from dataclasses import asdict, dataclass
from typing import Any

from spiel_edge.device.acquisitions import StreamAssembly
from spiel_edge.device.config import ConfigTransferMixin
from spiel_edge.device.hello import check_hello, link_payload, version_refused
from spiel_edge.device.link_services import SessionLinkServices
from spiel_edge.device.sanity import sanitized_hello
from spiel_edge.device.stream_control import StreamingMixin
from spiel_edge.errors import (
    ConfigError,
    DeviceDisconnectedError,
    DeviceError,
    DeviceRequestError,
    DeviceTimeoutError,
)
from spiel_edge.link import Link, LinkIdentity, open_link
from spiel_edge.protocol import (
    MAX_PAYLOAD,
    MAX_PROTOCOL_VERSION,
    MAX_RETRIES,
    MAX_WIRE_SIZE,
    MIN_PROTOCOL_VERSION,
    SCHEMA_HASH,
    ErrorResponse,
    FrameDecoder,
    Hello,
    HelloResponse,
    Message,
    MessageError,
    StreamStart,
    StreamStartResponse,
    StreamStatus,
    decode_message,
    encode_message,
)
from spiel_edge.protocol.errors import ErrorCode
from spiel_edge.protocol.framing import Frame
from spiel_edge.safety.shown import escape

log = logging.getLogger(__name__)

POLL_S = 0.05  # the longest any single read blocks
BUSY_DELAY_S = 0.05  # before asking a BUSY board again
LINK_BYTES_PER_S = 1e6  # the slowest link (full-speed USB) for size-dependent timeouts
TIMEOUT_SCALE_ENV = "SPIEL_REQUEST_TIMEOUT_SCALE"


def request_timeout_scale(environ: dict[str, str] | None = None) -> float:
    """``SPIEL_REQUEST_TIMEOUT_SCALE``: every request's timeout times this factor (1-100), for a
    board that answers slowly (an emulated board on a loaded machine, a bridge on a busy hub);
    1 where unset. ConfigError in one line for anything else."""
    import os

    text = (os.environ if environ is None else environ).get(TIMEOUT_SCALE_ENV, "").strip()
    if not text:
        return 1.0
    try:
        scale = float(text)
    except ValueError:
        scale = float("nan")
    if not 1.0 <= scale <= 100.0:  # NaN fails too
        raise ConfigError(f"{TIMEOUT_SCALE_ENV}={escape(text)[:40]!r}: not a number from 1 to 100")
    return scale


@dataclass
class SessionCounters:
    retries: int = 0  # requests sent again after a lost answer
    timeouts: int = 0  # requests still unanswered after all retries
    stale: int = 0  # answers that came after their request had been retried or given up
    unexpected: int = 0  # frames that are neither answers nor stream data
    disconnects: int = 0  # times the link went away
    reconnects: int = 0  # times it came back and the stream resumed
    restarts: int = 0  # streams the board had stopped by itself (restarted)


class DeviceSession(StreamingMixin, ConfigTransferMixin, SessionLinkServices):
    """``with DeviceSession("sim://") as dev: dev.start_stream(rate_hz=50); for a in dev.acquisitions(stop): ...``"""

    def __init__(
        self,
        url: str,
        *,
        reconnect: bool = True,
        reconnect_timeout_s: float | None = None,
        poll_s: float = POLL_S,
        stall_s: float = 2.0,
        link_options: dict[str, Any] | None = None,
    ):
        self.url = url
        self.reconnect = reconnect
        self.reconnect_timeout_s = reconnect_timeout_s
        # called with the seconds waited, every poll while the board is away: a service keeps
        # its watchdog fed (the process is healthy, it is waiting on purpose)
        self.on_waiting: Callable[[float], None] | None = None
        self.poll_s = poll_s
        self.stall_s = stall_s  # no stream data this long: ask the board whether it is alive
        self.link_options = link_options or {}
        self.timeout_scale = request_timeout_scale()
        self.counters = SessionCounters()
        self.assembly = StreamAssembly()
        self.decoder = FrameDecoder()
        self.hello: HelloResponse | None = None
        # negotiated by HELLO: the protocol version and the largest payload of this link
        self.protocol_version = MIN_PROTOCOL_VERSION
        self.max_payload = MAX_PAYLOAD
        self.identity: LinkIdentity | None = None
        self.stream: StreamStartResponse | None = None
        self.device_status: StreamStatus | None = None
        self._link: Link | None = None
        self._inbox: deque[tuple[Frame, int]] = deque()
        self._seq = random.getrandbits(16)
        self._stream_request: StreamStart | None = None
        # The board's STREAM_STATUS counters are since its boot (PROTOCOL.md 6.4): the run's
        # own figures are the counters minus their values when the run's stream began
        # (``_status_base``, per boot), plus what earlier boots of the same run counted.
        self._status_base: StreamStatus | None = None
        self._overruns_before = 0
        self._rx_errors_before = 0
        self._last_data = time.monotonic()
        self._link_services_init()
        self.assembly.stamp = self.stamp_acquisition  # board time -> host time, once synced

    # --- connection ----------------------------------------------------------------------

    def __enter__(self) -> DeviceSession:
        self.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def open(self) -> HelloResponse:
        """Open the link and handshake; DeviceError (with a hint) when that fails."""
        self._connect(self.url)
        assert self.hello is not None
        return self.hello

    def close(self) -> None:
        """Stop the stream (best effort, short) and close the link."""
        if self._link is not None and self._stream_request is not None:
            try:
                self.stop_stream(retries=0)
            except DeviceError as exc:
                log.debug("stop on close: %s", exc)
        self._drop_link()

    def _connect(self, url: str) -> None:
        self._link = open_link(url, **self.link_options)
        self.decoder.reset()
        self._inbox.clear()
        try:
            self._handshake()
        except BaseException:
            self._drop_link()
            raise

    def _handshake(self) -> None:
        try:
            hello = self.request(Hello(MIN_PROTOCOL_VERSION, MAX_PROTOCOL_VERSION, MAX_PAYLOAD, 0))
        except DeviceRequestError as exc:
            if exc.code in (ErrorCode.VERSION_TOO_OLD, ErrorCode.VERSION_TOO_NEW):
                raise DeviceError(version_refused(self.url, exc.code)) from exc
            raise
        if not isinstance(hello, HelloResponse):
            raise DeviceError(f"{self.url}: the board answered HELLO with {type(hello).__name__}")
        check_hello(self.url, hello)
        hello = sanitized_hello(hello)  # a board's strings never reach a terminal raw
        previous = self.hello
        if previous is not None and previous.serial and hello.serial != previous.serial:
            raise DeviceError(
                f"{self.url}: a different board answered (serial {hello.serial!r}, expected {previous.serial!r})"
            )
        if hello.schema_hash != SCHEMA_HASH:
            log.warning(
                "%s: firmware %s was built against another protocol schema (0x%08x, host 0x%08x)",
                self.url,
                hello.firmware_version,
                hello.schema_hash,
                SCHEMA_HASH,
            )
        if (
            previous is not None
            and hello.boot_id != previous.boot_id
            and self.device_status is not None
        ):
            self._overruns_before += self._since_start("overruns")
            self._rx_errors_before += self._since_start("rx_errors")
            self.device_status = None
        if previous is not None and hello.boot_id != previous.boot_id:
            self._status_base = None  # a new boot counts from 0: a new baseline at start
        self.hello = hello
        self.protocol_version = hello.protocol_version
        self.max_payload = link_payload(hello)
        assert self._link is not None
        known = self._link.identity()
        self.identity = LinkIdentity(
            self.url,
            known.vid or hello.usb_vid or None,
            known.pid or hello.usb_pid or None,
            known.serial or hello.serial or None,
        )
        log.info(
            "%s: board %s firmware %s, %d channels, protocol %d",
            self.url,
            hello.serial,
            hello.firmware_version,
            hello.n_channels,
            hello.protocol_version,
        )
        self._link_services_start()

    def _drop_link(self) -> None:
        if self._link is not None:
            self._link.close()
            self._link = None

    # --- requests ------------------------------------------------------------------------

    def request(
        self,
        msg: Message,
        *,
        timeout_s: float | None = None,
        retries: int = MAX_RETRIES,
        probe: bool = False,
        retry_busy: bool = True,
    ) -> Message:
        """Send a request and return its answer; DeviceRequestError on an error answer,
        DeviceTimeoutError when ``1 + retries`` tries got none. BUSY is retried after a short
        delay with a new sequence number (PROTOCOL.md section 10), unless ``retry_busy`` is
        False (the caller must know the board said BUSY: FW_VERIFY's silence after it).
        ``probe``: an optional exchange (clock sync) whose silence is not counted in
        ``counters.timeouts``."""
        for attempt in range(1 + retries):
            answer = self._exchange(msg, timeout_s, retries, probe)
            if not (
                retry_busy
                and isinstance(answer, ErrorResponse)
                and answer.code == ErrorCode.BUSY
                and attempt < retries
            ):
                break
            time.sleep(BUSY_DELAY_S)
        if isinstance(answer, ErrorResponse):
            raise DeviceRequestError(
                f"{self.url}: {type(msg).__name__}: {answer.to_exception()}",
                answer.code,
                answer.request_type,
            )
        return answer

    def _exchange(
        self, msg: Message, timeout_s: float | None, retries: int, probe: bool = False
    ) -> Message:
        """One request number: send, and re-send on silence, until an answer comes."""
        link = self._require_link()
        self._seq = (self._seq + 1) & 0xFFFF
        seq = self._seq
        wire = encode_message(msg, seq=seq)
        if timeout_s is None:  # the type's timeout plus both frames' time on a 1 MB/s link
            timeout_s = type(msg).TIMEOUT_S + (len(wire) + MAX_WIRE_SIZE) / LINK_BYTES_PER_S
            timeout_s *= self.timeout_scale
        for attempt in range(1 + retries):
            if attempt:
                self.counters.retries += 1
                log.debug("%s: retry %d of %s (seq %d)", self.url, attempt, type(msg).__name__, seq)
            self._sent_ns = time.perf_counter_ns()
            link.write(wire)
            answer = self._await(seq, msg.MSG_TYPE, time.monotonic() + timeout_s)
            if answer is not None:
                return answer
        if not probe:  # a probe's silence (a clock sync) is its caller's to count
            self.counters.timeouts += 1
        raise DeviceTimeoutError(
            f"{self.url}: no answer to {type(msg).__name__} after {1 + retries} tries of "
            f"{timeout_s:.3g} s ({self.decoder_summary()})"
        )

    def decoder_summary(self) -> str:
        """What came back meanwhile: a board that talks garbage differs from a silent one."""
        stats = self.decoder.stats
        bad = {k: v for k, v in stats.as_dict().items() if k != "frames" and v}
        if not stats.frames and not bad:
            return "nothing was received"
        detail = ", ".join(f"{k} {v}" for k, v in bad.items())
        return f"frames decoded {stats.frames}" + (f"; undecodable: {detail}" if detail else "")

    def _await(self, seq: int, msg_type: int, deadline: float) -> Message | None:
        while True:
            while self._inbox:
                frame, ns = self._inbox.popleft()
                if (
                    frame.is_response
                    and frame.seq == seq
                    and frame.msg_type in (msg_type, ErrorResponse.MSG_TYPE)
                ):
                    try:
                        answer = decode_message(frame)
                        self._answer_ns = ns
                        return answer
                    except MessageError as exc:  # valid CRC but a payload we cannot read
                        log.warning("%s: unreadable answer: %s", self.url, exc)
                        continue
                self._dispatch(frame, ns)
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                return None
            self._fill(min(remaining, self.poll_s))

    def _fill(self, timeout_s: float) -> None:
        data = self._require_link().read(timeout_s)
        if data:
            ns = time.perf_counter_ns()
            self._inbox.extend((frame, ns) for frame in self.decoder.feed(data))

    def _dispatch(self, frame: Frame, ns: int) -> None:
        if self._link_services_frame(frame, ns):
            return
        if self.assembly.feed(frame, ns):
            self._last_data = time.monotonic()
        elif frame.is_response:
            self.counters.stale += 1
        else:
            self.counters.unexpected += 1

    def _require_link(self) -> Link:
        if self._link is None:
            raise DeviceDisconnectedError(f"{self.url}: not connected")
        return self._link

    # --- reporting -----------------------------------------------------------------------

    def _since_start(self, field: str) -> int:
        """A board counter counted from the start of this run's stream on the current boot."""
        status = self.device_status
        if status is None:
            return 0
        base = self._status_base
        return (getattr(status, field) - (getattr(base, field) if base else 0)) & 0xFFFFFFFF

    def counts(self) -> dict[str, int]:
        """Every counter in one flat dict (see the README for their meaning)."""
        assembler = self.assembly.assembler.stats
        decoder = self.decoder.stats
        return {
            "acquisitions": self.assembly.acquisitions,
            "lost": self.assembly.lost,
            "damaged": assembler.incomplete,
            "gaps": assembler.gaps,
            "jumps": self.assembly.jumps + assembler.jumps,
            "duplicates": assembler.duplicates,
            "crc_errors": decoder.crc,
            "framing_errors": decoder.errors - decoder.crc,
            "bad_messages": self.assembly.bad_messages,
            "overruns": self._overruns_before + self._since_start("overruns"),
            "device_rx_errors": self._rx_errors_before + self._since_start("rx_errors"),
            **asdict(self.counters),
            **self.link_service_counts(),
        }
