"""Message payloads: frozen dataclasses with precompiled ``struct`` layouts and a type registry.

A request and its response share ``MSG_TYPE``; the frame's RESPONSE flag tells them apart, so
the registry is keyed by ``(msg_type, response)``. Failures come back as ``ErrorResponse``
(msg_type ERROR, flags RESPONSE|NACK) echoing the request's seq. Layouts: PROTOCOL.md.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from enum import IntEnum, IntFlag
from typing import ClassVar

from crc32c import crc32c

from spiel_edge.protocol._codec import REGISTRY, Message, register
from spiel_edge.protocol.config_messages import (
    ConfigCommit,
    ConfigCommitResponse,
    ConfigRead,
    ConfigReadResponse,
    ConfigSource,
    ConfigStatus,
    ConfigStatusRequest,
    ConfigWrite,
    ConfigWriteResponse,
)
from spiel_edge.protocol.errors import MessageError, RemoteError, UnknownMessageError
from spiel_edge.protocol.framing import Flags, Frame, encode_frame
from spiel_edge.protocol.link_messages import (  # noqa: F401  (registers the version 2 messages)
    BoardState,
    BootState,
    ErrorFlag,
    FwBegin,
    FwBeginResponse,
    FwConfirm,
    FwConfirmResponse,
    FwInfo,
    FwInfoRequest,
    FwTest,
    FwTestResponse,
    FwVerify,
    FwVerifyResponse,
    FwWrite,
    FwWriteResponse,
    Heartbeat,
    LogLevel,
    LogMessage,
    SelfTest,
    SlotState,
    Telemetry,
    TelemetryResponse,
    TimeSync,
    TimeSyncResponse,
)
from spiel_edge.protocol.stream_data import SampleFormat, StreamData

__all__ = [
    "MAX_PROTOCOL_VERSION",
    "MAX_RETRIES",
    "MIN_PAYLOAD",
    "MIN_PROTOCOL_VERSION",
    "REGISTRY",
    "SCHEMA_HASH",
    "Capability",
    "ConfigCommit",
    "ConfigCommitResponse",
    "ConfigRead",
    "ConfigReadResponse",
    "ConfigSource",
    "ConfigStatus",
    "ConfigStatusRequest",
    "ConfigWrite",
    "ConfigWriteResponse",
    "DeviceInfo",
    "DeviceInfoRequest",
    "ErrorResponse",
    "Hello",
    "HelloResponse",
    "Message",
    "MsgType",
    "Ping",
    "Pong",
    "Reboot",
    "RebootMode",
    "RebootResponse",
    "SampleFormat",
    "StreamData",
    "StreamStart",
    "StreamStartResponse",
    "StreamStatus",
    "StreamStatusRequest",
    "StreamStop",
    "StreamStopResponse",
    "decode_message",
    "decode_payload",
    "encode_message",
    "payload_for_version",
]

MAX_RETRIES = 3  # a request is sent at most 1 + MAX_RETRIES times, always with the same seq
# Protocol (message-layer) versions this package speaks, negotiated by HELLO (PROTOCOL.md
# 6.2); frames keep header version 1 (framing.PROTOCOL_VERSION) in both.
MIN_PROTOCOL_VERSION = 1
MAX_PROTOCOL_VERSION = 2
# The smallest max_payload a HELLO may state (PROTOCOL.md 6.2): every fixed-size message fits.
MIN_PAYLOAD = 64


class MsgType(IntEnum):
    HELLO = 0x0001
    DEVICE_INFO = 0x0002
    ERROR = 0x0003
    PING = 0x0004
    REBOOT = 0x0005
    TIME_SYNC = 0x0006  # version 2
    STREAM_START = 0x0010
    STREAM_STOP = 0x0011
    STREAM_STATUS = 0x0012
    STREAM_DATA = 0x0013
    CONFIG_READ = 0x0020
    CONFIG_WRITE = 0x0021
    CONFIG_COMMIT = 0x0022
    CONFIG_STATUS = 0x0023
    TELEMETRY = 0x0030  # version 2: heartbeat period and log level
    HEARTBEAT = 0x0031  # version 2: device-originated
    LOG = 0x0032  # version 2: device-originated
    FW_INFO = 0x0040  # version 2: firmware slots
    FW_BEGIN = 0x0041
    FW_WRITE = 0x0042
    FW_VERIFY = 0x0043
    FW_TEST = 0x0044
    FW_CONFIRM = 0x0045


class Capability(IntFlag):
    """HELLO capability bits of a device."""

    NONE = 0
    STREAM = 0x01  # STREAM_START/STOP/STATUS/DATA
    CONFIG = 0x02  # CONFIG_READ/WRITE/COMMIT/STATUS with two flash slots
    F32_SAMPLES = 0x04  # SampleFormat.F32
    RF_SAMPLES = 0x08  # SampleFormat.I16_RF
    BULK = 0x10  # also reachable over USB bulk endpoints
    TIME_SYNC = 0x20  # version 2: answers TIME_SYNC (timestamp_us is its clock)
    TELEMETRY = 0x40  # version 2: TELEMETRY, HEARTBEAT and LOG
    FIRMWARE_UPDATE = 0x80  # version 2: FW_INFO/BEGIN/WRITE/VERIFY/TEST/CONFIRM
    IQ_SAMPLES = 0x100  # version 2: SampleFormat.I16_IQ
    START_AT = 0x200  # version 2: STREAM_START's start_at_us (a start on the device's clock)


class RebootMode(IntEnum):
    NORMAL = 0
    BOOTLOADER = 1


# --- session ---------------------------------------------------------------------------


@register
@dataclass(frozen=True)
class Hello(Message):
    """Host -> device: the protocol versions the host speaks."""

    MSG_TYPE: ClassVar[int] = MsgType.HELLO
    _STRUCT: ClassVar[struct.Struct] = struct.Struct("<BBHI")
    min_version: int = 1
    max_version: int = 1
    max_payload: int = 8256  # the largest payload the host accepts
    capabilities: int = 0  # host capability bits, reserved (0)


@register
@dataclass(frozen=True)
class HelloResponse(Message):
    MSG_TYPE: ClassVar[int] = MsgType.HELLO
    RESPONSE: ClassVar[bool] = True
    _STRUCT: ClassVar[struct.Struct] = struct.Struct("<BBBBHHIII16sHH16s")
    protocol_version: int = 1  # chosen: the highest version both sides speak
    min_version: int = 1  # device's supported range
    max_version: int = 1
    n_channels: int = 0  # receiver channels
    max_payload: int = 8256  # the largest payload the device sends or accepts
    max_samples: int = 4096  # samples per channel per acquisition
    capabilities: int = 0  # Capability bits
    schema_hash: int = 0  # SCHEMA_HASH the firmware was built against
    boot_id: int = 0  # random per boot: a change means the device rebooted
    firmware_version: str = ""  # e.g. "1.4.2+g1a2b3c", UTF-8, <= 16 bytes
    usb_vid: int = 0
    usb_pid: int = 0
    serial: str = ""  # board serial, UTF-8, <= 16 bytes


@register
@dataclass(frozen=True)
class DeviceInfoRequest(Message):
    MSG_TYPE: ClassVar[int] = MsgType.DEVICE_INFO


@register
@dataclass(frozen=True)
class DeviceInfo(Message):
    MSG_TYPE: ClassVar[int] = MsgType.DEVICE_INFO
    RESPONSE: ClassVar[bool] = True
    _STRUCT: ClassVar[struct.Struct] = struct.Struct("<HBBIIIh16s")
    hw_revision: int = 0
    n_channels: int = 0
    adc_bits: int = 0
    emitter_freq_hz: int = 0  # emitter centre frequency
    max_sample_rate_hz: int = 0
    uptime_ms: int = 0  # wraps after 49.7 days
    temperature_cdeg: int = 0  # board temperature in 0.01 degC (speed of sound)
    board_name: str = ""  # UTF-8, <= 16 bytes


@register
@dataclass(frozen=True)
class ErrorResponse(Message):
    """Device -> host, flags RESPONSE|NACK: a request failed."""

    MSG_TYPE: ClassVar[int] = MsgType.ERROR
    RESPONSE: ClassVar[bool] = True
    _STRUCT: ClassVar[struct.Struct] = struct.Struct("<HHH")
    _TAIL: ClassVar[str] = "text"
    _TAIL_IS_TEXT: ClassVar[bool] = True
    code: int = 1  # ErrorCode
    request_type: int = 0  # msg_type of the failed request
    text: str = ""  # optional detail, UTF-8

    def to_exception(self) -> RemoteError:
        return RemoteError(self.code, self.text, self.request_type)


@register
@dataclass(frozen=True)
class Ping(Message):
    MSG_TYPE: ClassVar[int] = MsgType.PING
    _STRUCT: ClassVar[struct.Struct] = struct.Struct("<H")
    _TAIL: ClassVar[str] = "data"
    data: bytes = b""  # echoed back in Pong


@register
@dataclass(frozen=True)
class Pong(Message):
    MSG_TYPE: ClassVar[int] = MsgType.PING
    RESPONSE: ClassVar[bool] = True
    _STRUCT: ClassVar[struct.Struct] = struct.Struct("<H")
    _TAIL: ClassVar[str] = "data"
    data: bytes = b""


@register
@dataclass(frozen=True)
class Reboot(Message):
    MSG_TYPE: ClassVar[int] = MsgType.REBOOT
    _STRUCT: ClassVar[struct.Struct] = struct.Struct("<BH")
    mode: int = RebootMode.NORMAL
    delay_ms: int = 100  # the device answers first, then reboots after this delay


@register
@dataclass(frozen=True)
class RebootResponse(Message):
    MSG_TYPE: ClassVar[int] = MsgType.REBOOT
    RESPONSE: ClassVar[bool] = True


# --- streaming -------------------------------------------------------------------------


@register
@dataclass(frozen=True)
class StreamStart(Message):
    MSG_TYPE: ClassVar[int] = MsgType.STREAM_START
    _STRUCT: ClassVar[struct.Struct] = struct.Struct("<IfHBBQ")
    n_acquisitions: int = 0  # 0 = endless, until STREAM_STOP
    rate_hz: float = 10.0  # acquisitions (pings) per second; 0 = as fast as possible
    n_samples: int = 0  # samples per channel; 0 = device default
    sample_format: int = SampleFormat.U16_ENVELOPE
    channel_mask: int = 0  # bit i = receiver i; 0 = all
    # v2, Capability.START_AT: the device clock (us since boot) at which acquisition 0 is due;
    # 0 = at once. A board without the capability ignores it (bytes after what it knows).
    start_at_us: int = 0


@register
@dataclass(frozen=True)
class StreamStartResponse(Message):
    MSG_TYPE: ClassVar[int] = MsgType.STREAM_START
    RESPONSE: ClassVar[bool] = True
    _STRUCT: ClassVar[struct.Struct] = struct.Struct("<IIIHBBI")
    V1_SIZE: ClassVar[int] = 16  # version 1 ends before channel_mask
    first_acquisition: int = 0  # acquisition index of the first STREAM_DATA
    first_counter: int = 0  # aux stream counter of the first STREAM_DATA frame
    sample_rate_hz: int = 0
    n_samples: int = 0
    n_channels: int = 0  # channels per acquisition (bits set in channel_mask)
    sample_format: int = SampleFormat.U16_ENVELOPE
    channel_mask: int = 0  # v2: the channels streamed (physical ids); 0 from a v1 board


@register
@dataclass(frozen=True)
class StreamStop(Message):
    MSG_TYPE: ClassVar[int] = MsgType.STREAM_STOP


@register
@dataclass(frozen=True)
class StreamStopResponse(Message):
    MSG_TYPE: ClassVar[int] = MsgType.STREAM_STOP
    RESPONSE: ClassVar[bool] = True
    _STRUCT: ClassVar[struct.Struct] = struct.Struct("<II")
    acquisitions_sent: int = 0
    next_counter: int = 0  # aux the next STREAM_DATA frame would have had


@register
@dataclass(frozen=True)
class StreamStatusRequest(Message):
    MSG_TYPE: ClassVar[int] = MsgType.STREAM_STATUS


@register
@dataclass(frozen=True)
class StreamStatus(Message):
    MSG_TYPE: ClassVar[int] = MsgType.STREAM_STATUS
    RESPONSE: ClassVar[bool] = True
    _STRUCT: ClassVar[struct.Struct] = struct.Struct("<BIIIII")
    streaming: int = 0  # 1 while a stream runs
    acquisitions_sent: int = 0
    frames_sent: int = 0
    overruns: int = 0  # acquisitions skipped because the link could not keep up
    rx_errors: int = 0  # frames the device's decoder dropped (CRC, COBS, ...)
    dropped: int = 0  # STREAM_DATA frames dropped by the device's transmit queue


register(StreamData)


# --- codec -----------------------------------------------------------------------------


def _schema_hash() -> int:
    """CRC-32C of every wire layout: differs when two builds disagree on a message."""
    lines = [
        f"{t:04x}:{int(r)}:{cls._STRUCT.format}:{cls._TAIL or '-'}"
        for (t, r), cls in sorted(REGISTRY.items())
    ]
    return crc32c("\n".join(lines).encode())


SCHEMA_HASH = _schema_hash()


def encode_message(
    msg: Message, *, seq: int = 0, flags: int = 0, aux: int = 0, version: int = MAX_PROTOCOL_VERSION
) -> bytes:
    """Wire bytes of ``msg``; RESPONSE, NACK and STREAM flags are set from its class;
    ``version``: the negotiated protocol version (:func:`payload_for_version`)."""
    if msg.RESPONSE:
        flags |= Flags.RESPONSE
    if isinstance(msg, ErrorResponse):
        flags |= Flags.NACK
    if isinstance(msg, StreamData):
        flags |= Flags.STREAM
    return encode_frame(
        msg.MSG_TYPE, payload_for_version(msg, version), seq=seq, flags=flags, aux=aux
    )


def payload_for_version(msg: Message, version: int) -> bytes:
    """``msg``'s payload as a board speaking ``version`` sends it: a version-1 board sends the
    version-1 fixed part only (fields added in version 2 are absent, read as 0)."""
    payload = msg.pack()
    v1_size = getattr(msg, "V1_SIZE", None)
    if version < 2 and v1_size is not None:
        return payload[:v1_size]
    return payload


def decode_payload(msg_type: int, payload: bytes, *, response: bool = False) -> Message:
    cls = REGISTRY.get((msg_type, response))
    if cls is None:
        raise UnknownMessageError(msg_type, response)
    try:
        return cls.unpack(payload)
    except (struct.error, UnicodeDecodeError) as exc:
        raise MessageError(f"{cls.__name__}: {exc}") from exc


def decode_message(frame: Frame) -> Message:
    """The message a frame carries; raises UnknownMessageError or MessageError."""
    return decode_payload(frame.msg_type, frame.payload, response=frame.is_response)
