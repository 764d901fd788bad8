"""firmware_protocol: the framed binary protocol between the host and the transducer board.

Pure code, no I/O. Layers: framing (bytes <-> Frame), messages (Frame payload <-> dataclass),
reassembly (STREAM_DATA frames -> acquisitions). The specification is PROTOCOL.md.
"""

from firmware_protocol.errors import (
    ERROR_TEXT,
    ErrorCode,
    FrameError,
    MessageError,
    ProtocolError,
    RemoteError,
    UnknownMessageError,
    describe_error,
)
from firmware_protocol.framing import (
    HEADER_SIZE,
    KNOWN_FLAGS,
    MAX_ENCODED_SIZE,
    MAX_PAYLOAD,
    MAX_WIRE_SIZE,
    PROTOCOL_VERSION,
    DecoderStats,
    Flags,
    Frame,
    FrameDecoder,
    encode_frame,
)
from firmware_protocol.messages import (
    MAX_RETRIES,
    REGISTRY,
    SCHEMA_HASH,
    Capability,
    ConfigCommit,
    ConfigCommitResponse,
    ConfigRead,
    ConfigReadResponse,
    ConfigSource,
    ConfigStatus,
    ConfigStatusRequest,
    ConfigWrite,
    ConfigWriteResponse,
    DeviceInfo,
    DeviceInfoRequest,
    ErrorResponse,
    Hello,
    HelloResponse,
    Message,
    MsgType,
    Ping,
    Pong,
    Reboot,
    RebootMode,
    RebootResponse,
    StreamStart,
    StreamStartResponse,
    StreamStatus,
    StreamStatusRequest,
    StreamStop,
    StreamStopResponse,
    decode_message,
    decode_payload,
    encode_message,
)
from firmware_protocol.reassembly import Acquisition, AcquisitionAssembler, AssemblerStats
from firmware_protocol.stream import (
    MAX_SAMPLES_PER_FRAME,
    SAMPLE_DTYPE,
    SAMPLE_SIZE,
    SampleFormat,
    StreamData,
)
from firmware_protocol.vectors import load_test_vectors

__all__ = [
    "ERROR_TEXT", "HEADER_SIZE", "KNOWN_FLAGS", "MAX_ENCODED_SIZE", "MAX_PAYLOAD",
    "MAX_RETRIES", "MAX_SAMPLES_PER_FRAME", "MAX_WIRE_SIZE", "PROTOCOL_VERSION", "REGISTRY",
    "SAMPLE_DTYPE", "SAMPLE_SIZE", "SCHEMA_HASH",
    "Acquisition", "AcquisitionAssembler", "AssemblerStats", "Capability", "ConfigCommit",
    "ConfigCommitResponse", "ConfigRead", "ConfigReadResponse", "ConfigSource", "ConfigStatus",
    "ConfigStatusRequest", "ConfigWrite", "ConfigWriteResponse", "DecoderStats", "DeviceInfo",
    "DeviceInfoRequest", "ErrorCode", "ErrorResponse", "Flags", "Frame", "FrameDecoder",
    "FrameError", "Hello", "HelloResponse", "Message", "MessageError", "MsgType", "Ping", "Pong",
    "ProtocolError", "Reboot", "RebootMode", "RebootResponse", "RemoteError", "SampleFormat",
    "StreamData", "StreamStart", "StreamStartResponse", "StreamStatus", "StreamStatusRequest",
    "StreamStop", "StreamStopResponse", "UnknownMessageError",
    "decode_message", "decode_payload", "describe_error", "encode_frame", "encode_message",
    "load_test_vectors",
]  # fmt: skip
