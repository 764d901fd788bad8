"""The board side of spiel_edge.protocol: answers requests and streams a scene's acquisitions.

Pure state machine driven by the caller's clock: ``receive(bytes, now)`` returns the frames
to send back, ``due(now, room)`` the stream frames whose time has come. Requests are
answered once per sequence number: a repeated request (the host retrying after a lost
response) gets the cached response and is not executed again. A HELLO starts a new host
session and clears that cache.
"""

from __future__ import annotations

import logging
import math
import random
from collections import OrderedDict
from dataclasses import dataclass, field

import numpy as np

from spiel_edge.link.usb_ids import BOARD_USB_IDS
from spiel_edge.protocol import (
    MAX_PAYLOAD,
    MAX_PROTOCOL_VERSION,
    MIN_PAYLOAD,
    SCHEMA_HASH,
    Capability,
    ErrorCode,
    ErrorResponse,
    Flags,
    FrameDecoder,
    Hello,
    MessageError,
    Ping,
    Pong,
    SampleFormat,
    StreamStart,
    StreamStartResponse,
    StreamStatus,
    StreamStop,
    StreamStopResponse,
    decode_message,
    encode_message,
)
from spiel_edge.protocol import messages as m
from spiel_edge.protocol.framing import Frame
from spiel_edge.protocol.stream_data import SAMPLE_SIZE, STREAM_HEADER
from spiel_edge.sim.board_acquire import AcquireMixin
from spiel_edge.sim.board_link_services import BoardLinkServices
from spiel_edge.sim.config_slots import BoardConfigMixin
from spiel_edge.sim.faults import Outgoing
from spiel_edge.sim.firmware_slots import FirmwareFlash
from spiel_edge.sim.flash import Flash
from spiel_edge.sim.scenes import EchoModelScene, ReplayScene

log = logging.getLogger(__name__)

FIRMWARE_VERSION = "sim-0.1.0"  # of the factory image (sim/firmware_slots.py)
MAX_RATE_HZ = 10000.0
MAX_SAMPLES = 4096
SAMPLE_SIZE_U16 = 2
RESPONSE_CACHE = 16
_MASK = 0xFFFFFFFF


@dataclass
class _Stream:
    rate_hz: float
    n_samples: int
    remaining: int | None  # None: endless
    next_time: float
    scheduled: int = 0  # acquisitions sent or skipped: n_acquisitions counts both
    sent: int = 0  # acquisitions of this stream sent whole (STREAM_STOP's acquisitions_sent)
    seq: int = 0  # the STREAM_START's seq, echoed by its STREAM_DATA frames
    sample_format: int = SampleFormat.U16_ENVELOPE
    channels: tuple[int, ...] = ()  # the physical channels streamed (the resolved mask)

    @property
    def period(self) -> float:
        return 1.0 / self.rate_hz if self.rate_hz > 0 else 0.0


@dataclass
class BoardStats:
    acquisitions_sent: int = 0
    frames_sent: int = 0
    overruns: int = 0
    requests: int = 0
    repeated: int = 0  # requests answered from the cache (not executed again)
    executed: dict[int, int] = field(default_factory=dict)  # msg_type -> times executed

    def count(self, msg_type: int) -> None:
        self.executed[msg_type] = self.executed.get(msg_type, 0) + 1


# The request table: every request this board answers, its handler and the lowest protocol
# version it is answered under (version 2: board_link_services.py). The C core's table (firmware/core/
# device.c, requests[]) has the same rows: tests/firmware/test_core_scope.py.
REQUESTS: dict[type, tuple[str, int]] = {
    Hello: ("_hello", 1),
    m.DeviceInfoRequest: ("_device_info", 1),
    Ping: ("_ping", 1),
    m.Reboot: ("_reboot", 1),
    StreamStart: ("_stream_start", 1),
    StreamStop: ("_stream_stop", 1),
    m.StreamStatusRequest: ("_stream_status", 1),
    m.ConfigRead: ("_config_read", 1),
    m.ConfigWrite: ("_config_write", 1),
    m.ConfigCommit: ("_config_commit", 1),
    m.ConfigStatusRequest: ("_config_status", 1),
    m.TimeSync: ("_time_sync", 2),
    m.Telemetry: ("_telemetry", 2),
    m.FwInfoRequest: ("_fw_info", 2),
    m.FwBegin: ("_fw_begin", 2),
    m.FwWrite: ("_fw_write", 2),
    m.FwVerify: ("_fw_verify", 2),
    m.FwTest: ("_fw_test", 2),
    m.FwConfirm: ("_fw_confirm", 2),
}


class VirtualBoard(BoardConfigMixin, BoardLinkServices, AcquireMixin):
    def __init__(
        self,
        scene: ReplayScene | EchoModelScene,
        *,
        serial: str = "SIM0001",
        vid: int = BOARD_USB_IDS[0][0],
        pid: int = BOARD_USB_IDS[0][1],
        flash: Flash | None = None,
        seed: int = 0,
        now: float = 0.0,
        protocol: int = MAX_PROTOCOL_VERSION,
        max_payload: int = MAX_PAYLOAD,
        drift_ppm: float = 0.0,
        firmware: FirmwareFlash | None = None,
        sync_fault: str = "",
        heartbeat_flags: int = 0,
        log_flood: float = 0.0,
    ):
        self.scene = scene
        self.serial, self.vid, self.pid = serial, vid, pid
        self.max_version = protocol  # the highest protocol version this board speaks
        self.board_max_payload = max_payload  # HELLO max_payload: what it sends or accepts
        self.flash = flash or Flash()
        self._link_services_init(drift_ppm, firmware, sync_fault, heartbeat_flags, log_flood)
        self.stats = BoardStats()
        self.tx_dropped = 0  # set by the line: frames lost on the way out
        self._rng = random.Random(seed)
        self._decoder = FrameDecoder()
        self.reboot_at: float | None = None
        self.boot(now)

    # --- power ---------------------------------------------------------------------------

    def boot(self, now: float) -> None:
        """Power on: a new boot id, no stream, empty RAM (staging, response cache)."""
        self.boot_id = self._rng.getrandbits(32)
        self._boot_time = now
        self._decoder.reset()
        self._cache: OrderedDict[int, tuple[int, bytes]] = OrderedDict()
        self._staging = bytearray()
        self._stream: _Stream | None = None
        self._acquisition = 0
        self._counter = 0
        self._last_background: np.ndarray | None = None
        self._request_seq = 0
        self.reboot_at = None
        self.version = 1  # negotiated by HELLO
        self.max_payload = self.board_max_payload  # of the link: min(board, host's HELLO)
        self._link_services_boot(now)  # the bootloader's choice of firmware image, telemetry
        on_boot = getattr(self.scene, "on_boot", None)  # a scene on the host's clock (robot)
        if on_boot is not None:
            on_boot(now)

    @property
    def streaming(self) -> bool:
        return self._stream is not None

    @property
    def rx_errors(self) -> int:
        return self._decoder.stats.errors

    # --- host -> board -------------------------------------------------------------------

    def receive(self, data: bytes, now: float) -> list[Outgoing]:
        """Decode requests and return their responses (PowerCut propagates)."""
        out = []
        if self.silent:  # a firmware that hangs at start: it reads nothing
            return out
        if now < self._blocked_until:  # a blocking check (FW_VERIFY): what comes is lost
            return out
        for frame in self._decoder.feed(data):
            wire = self._answer(frame, now)
            if wire is not None:
                out.append(Outgoing(wire))
        return out

    def _answer(self, frame: Frame, now: float) -> bytes | None:
        if frame.flags & (Flags.RESPONSE | Flags.STREAM):
            return None  # not a request
        self.stats.requests += 1
        cached = self._cache.get(frame.seq)
        if cached is not None and cached[0] == frame.msg_type and frame.msg_type != m.MsgType.HELLO:
            self.stats.repeated += 1
            return cached[1]
        try:
            request = decode_message(frame)
        except MessageError as exc:
            code = ErrorCode.UNSUPPORTED if "unknown message" in str(exc) else ErrorCode.INVALID
            response: m.Message = ErrorResponse(code, frame.msg_type, str(exc)[:200])
        else:
            self.stats.count(frame.msg_type)
            self._request_seq = frame.seq
            response = self._execute(request, now)
        wire = encode_message(response, seq=frame.seq, version=self.version)
        if frame.msg_type == m.MsgType.HELLO:
            self._cache.clear()
        self._cache[frame.seq] = (frame.msg_type, wire)
        while len(self._cache) > RESPONSE_CACHE:
            self._cache.popitem(last=False)
        return wire

    def _execute(self, req: m.Message, now: float) -> m.Message:
        entry = REQUESTS.get(type(req))
        if entry is None:
            return ErrorResponse(
                ErrorCode.UNSUPPORTED, req.MSG_TYPE, "not a request this board handles"
            )
        name, version = entry
        refused = self._need_v2(req) if version >= 2 else None  # board_link_services.py
        return refused if refused is not None else getattr(self, name)(req, now)

    # --- session -------------------------------------------------------------------------

    def _hello(self, req: Hello, now: float) -> m.Message:
        top = self.max_protocol()  # the board's, capped by the running image's range
        speaks = f"board speaks 1-{top}"
        if req.max_version < 1:
            return ErrorResponse(ErrorCode.VERSION_TOO_OLD, req.MSG_TYPE, speaks)
        if req.min_version > top:
            return ErrorResponse(ErrorCode.VERSION_TOO_NEW, req.MSG_TYPE, speaks)
        if 0 < req.max_payload < MIN_PAYLOAD:
            return ErrorResponse(
                ErrorCode.INVALID, req.MSG_TYPE, f"max_payload below the minimum {MIN_PAYLOAD}"
            )
        self.version = min(req.max_version, top)
        self.max_payload = min(req.max_payload or MAX_PAYLOAD, self.board_max_payload)
        caps = Capability.STREAM | Capability.CONFIG | Capability.BULK
        caps |= self.link_service_capabilities()
        return m.HelloResponse(
            self.version,
            1,
            top,
            self.scene.n_channels,
            self.board_max_payload,
            MAX_SAMPLES,
            int(caps),
            SCHEMA_HASH,
            self.boot_id,
            self.firmware_version,
            self.vid,
            self.pid,
            self.serial,
        )

    def _device_info(self, req: m.Message, now: float) -> m.Message:
        speed = getattr(self.scene, "speed", 343.0)
        celsius = 273.15 * ((speed / 331.3) ** 2 - 1.0)
        return m.DeviceInfo(
            1,
            self.scene.n_channels,
            16,
            175000,
            100000,
            int((now - self._boot_time) * 1000) & _MASK,
            max(-32768, min(32767, round(celsius * 100))),
            "spiel-sim",
        )

    def _ping(self, req: Ping, now: float) -> m.Message:
        if len(req.data) + 2 <= self.max_payload:
            return Pong(req.data)
        return ErrorResponse(ErrorCode.TOO_LARGE, req.MSG_TYPE, "data exceeds max_payload - 2")

    def _reboot(self, req: m.Reboot, now: float) -> m.Message:
        self.reboot_at = now + req.delay_ms / 1000.0
        return m.RebootResponse()

    # --- streaming -----------------------------------------------------------------------

    def _stream_start(self, req: StreamStart, now: float) -> m.Message:
        n_ch = self.scene.n_channels
        n_samples = req.n_samples or self.scene.n_samples
        every = (1 << n_ch) - 1
        mask = req.channel_mask or every
        error = None
        if self.streaming:
            error = (ErrorCode.BAD_STATE, "a stream is already running; stop it first")
        elif req.sample_format == SampleFormat.I16_IQ and (
            self.version < 2 or not hasattr(self.scene, "iq_supported")
        ):
            error = (ErrorCode.UNSUPPORTED, "I/Q samples need protocol 2 and scene=model")
        elif req.sample_format not in (SampleFormat.U16_ENVELOPE, SampleFormat.I16_IQ):
            error = (ErrorCode.UNSUPPORTED, "this board sends U16_ENVELOPE or I16_IQ samples")
        elif mask & ~every:
            error = (ErrorCode.INVALID, "channel_mask names absent channels")
        elif self.version < 2 and mask != every:
            # version 1 numbers the channels of a subset 0..n-1, losing which they are
            error = (ErrorCode.UNSUPPORTED, "channel subsets need protocol version 2")
        elif (
            n_samples > MAX_SAMPLES
            or STREAM_HEADER.size + n_samples * SAMPLE_SIZE[SampleFormat(req.sample_format)]
            > self.max_payload
        ):
            error = (ErrorCode.TOO_LARGE, "n_samples too large for max_samples or max_payload")
        elif not self.scene.supports(n_samples):
            error = (
                ErrorCode.UNSUPPORTED,
                f"this scene cannot make {n_samples} samples per channel",
            )
        elif not (math.isfinite(req.rate_hz) and 0.0 <= req.rate_hz <= MAX_RATE_HZ):
            error = (ErrorCode.INVALID, f"rate_hz must be in [0, {MAX_RATE_HZ:g}]")
        due = self.first_due(req.start_at_us, 1.0 / req.rate_hz if req.rate_hz else 0.0, now)
        if not error and due is None:
            error = (ErrorCode.INVALID, "start_at_us more than 60 s ahead")
        if error:
            return ErrorResponse(error[0], req.MSG_TYPE, error[1])
        remaining = req.n_acquisitions or None
        # every stream starts with the background (a new host may be listening)
        self._last_background = None
        channels = tuple(c for c in range(n_ch) if mask >> c & 1)
        self._stream = _Stream(
            req.rate_hz,
            n_samples,
            remaining,
            due,
            seq=self._request_seq,
            channels=channels,
            sample_format=req.sample_format,
        )
        return StreamStartResponse(
            self._acquisition,
            self._counter,
            self.scene.sample_rate_hz,
            n_samples,
            len(channels),
            req.sample_format,
            mask,
        )

    def _stream_stop(self, req: StreamStop, now: float) -> m.Message:
        sent = self._stream.sent if self._stream else 0
        self._stream = None
        return StreamStopResponse(sent, self._counter)

    def _stream_status(self, req: m.Message, now: float) -> m.Message:
        s = self.stats
        return StreamStatus(
            int(self.streaming),
            s.acquisitions_sent & _MASK,
            s.frames_sent & _MASK,
            s.overruns & _MASK,
            self.rx_errors & _MASK,
            self.tx_dropped & _MASK,
        )

    def next_due(self) -> float | None:
        times = [t for t in (self.telemetry_next(),) if t is not None]
        if self._stream is not None:
            times.append(self._stream.next_time)
        return min(times) if times else None

    def acquisition_size(self) -> int:
        """Upper bound of the wire bytes of one acquisition (annotations included)."""
        n = self._stream.n_samples if self._stream else self.scene.n_samples
        per = 4 if self._stream and self._stream.sample_format == SampleFormat.I16_IQ else 2
        frame = 12 + 24 + per * n + 4
        return 2 * self.scene.n_channels * (frame + frame // 254 + 3)

    def due(self, now: float, room: int, limit: int | None = None) -> list[Outgoing]:
        """Acquisitions due by ``now`` that fit in ``room`` bytes (the others overrun), at
        most ``limit`` pings."""
        out: list[Outgoing] = self.telemetry_due(now, room)
        room -= sum(len(o.wire) for o in out)
        s = self._stream
        if self.silent:
            return out
        size = self.acquisition_size()
        while s is not None and s.next_time <= now and (limit is None or limit > 0):
            limit = None if limit is None else limit - 1
            if s.period == 0.0 and size > room:
                break  # as fast as possible: wait for the host to drain
            if size > room:
                self.stats.overruns += 1
                self._acquisition = (self._acquisition + 1) & _MASK
            else:
                out += self._acquire(s)
                room -= size
                s.sent += 1
            if s.period:
                s.next_time += s.period
            else:  # as fast as it can: one listening window on, as the C core does (a burst
                # stamped with one time reads as a clock that stood still)
                s.next_time = now + s.n_samples / self.scene.sample_rate_hz
            s.scheduled += 1
            if s.remaining is not None and s.scheduled >= s.remaining:
                self._stream = s = None
        return out

    def skip_to(self, now: float) -> None:
        """Frozen until ``now`` (a stall): pings that should have happened are overruns."""
        s = self._stream
        while s is not None and s.period and s.next_time < now:
            self.stats.overruns += 1
            self._acquisition = (self._acquisition + 1) & _MASK
            s.next_time += s.period
