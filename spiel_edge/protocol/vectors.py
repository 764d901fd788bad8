"""Test vectors: exact wire bytes for frames, messages and rejected frames.

``build_test_vectors()`` computes them from this implementation; ``test_vectors.json`` is the
frozen copy shipped for firmware tests (the test suite checks that the two agree).
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any

from spiel_edge.protocol import cobs
from spiel_edge.protocol import messages as m
from spiel_edge.protocol.errors import ErrorCode
from spiel_edge.protocol.framing import (
    HEADER,
    MAX_ENCODED_SIZE,
    MAX_PAYLOAD,
    PROTOCOL_VERSION,
    Flags,
    FrameDecoder,
    crc32c,
    encode_frame,
    wrap_body,
)
from spiel_edge.protocol.stream_data import SampleFormat, StreamData

__all__ = ["build_test_vectors", "field_values", "load_test_vectors", "message_from_fields"]


# the repository keeps the vectors beside PROTOCOL.md (firmware_protocol/); not in the wheel
VECTORS_PATH = Path(__file__).resolve().parents[2] / "firmware_protocol" / "test_vectors.json"


def load_test_vectors() -> dict[str, Any]:
    """The repository's ``firmware_protocol/test_vectors.json`` (a checkout, not a wheel)."""
    return json.loads(VECTORS_PATH.read_text())


def field_values(msg: m.Message) -> dict[str, Any]:
    """JSON-able fields of a message; bytes become ``{"hex": ...}``."""
    out: dict[str, Any] = {}
    for f in dataclasses.fields(msg):  # type: ignore[arg-type]
        value = getattr(msg, f.name)
        out[f.name] = {"hex": value.hex()} if isinstance(value, bytes) else value
    return out


def message_from_fields(class_name: str, fields: dict[str, Any]) -> m.Message:
    cls = getattr(m, class_name)
    kwargs = {k: bytes.fromhex(v["hex"]) if isinstance(v, dict) else v for k, v in fields.items()}
    return cls(**kwargs)


def _frame_cases() -> list[tuple[str, int, bytes, int, int, int]]:
    """(name, msg_type, payload, seq, flags, aux) covering COBS run boundaries and flags."""
    return [
        ("empty", 0x0004, b"", 0, 0, 0),
        ("zeros", 0x0004, bytes(8), 1, 0, 0),
        ("one_byte", 0x1234, b"\x55", 0xFFFF, int(Flags.RESPONSE), 0xDEADBEEF),
        ("run_254", 0x0013, bytes(range(1, 255)), 7, int(Flags.STREAM), 1),
        ("run_255", 0x0013, bytes([0xAA]) * 255, 8, int(Flags.STREAM | Flags.MORE), 2),
        ("all_flags", 0xFFFF, bytes(range(256)), 42, 0x1F, 0x01020304),
        ("max_payload", 0x0013, bytes((i * 7 + 3) & 0xFF for i in range(MAX_PAYLOAD)), 3, 8, 9),
    ]


def _frames() -> list[dict[str, Any]]:
    out = []
    for name, msg_type, payload, seq, flags, aux in _frame_cases():
        header = HEADER.pack(PROTOCOL_VERSION, flags, msg_type, seq, len(payload), aux)
        out.append(
            {
                "name": name,
                "version": PROTOCOL_VERSION,
                "flags": flags,
                "msg_type": msg_type,
                "seq": seq,
                "aux": aux,
                "payload_len": len(payload),
                "payload_hex": payload.hex(),
                "header_hex": header.hex(),
                "crc": crc32c(header + payload),
                "wire_hex": encode_frame(msg_type, payload, seq=seq, flags=flags, aux=aux).hex(),
            }
        )
    return out


def _sample_messages() -> list[m.Message]:
    ramp = b"".join(i.to_bytes(2, "little") for i in range(0, 4000, 500))
    return [
        m.Hello(1, 1, 8256, 0),
        m.HelloResponse(
            1,
            1,
            1,
            4,
            8256,
            4096,
            int(m.Capability.STREAM | m.Capability.CONFIG),
            m.SCHEMA_HASH,
            0x5EED1234,
            "1.0.0",
            0x1209,
            0x5E1E,
            "SPL-000123",
        ),
        m.DeviceInfoRequest(),
        m.DeviceInfo(2, 4, 12, 40000, 1_000_000, 123456, 2350, "spiel-tx4"),
        m.ErrorResponse(int(ErrorCode.CORRUPT), int(m.MsgType.CONFIG_COMMIT), "crc mismatch"),
        m.Ping(b"\x00\x01\x02hello"),
        m.Pong(b"\x00\x01\x02hello"),
        m.Reboot(int(m.RebootMode.BOOTLOADER), 250),
        m.RebootResponse(),
        m.StreamStart(100, 20.0, 4096, int(SampleFormat.I16_RF), 0x0F),
        m.StreamStartResponse(0, 0, 400000, 4096, 4, int(SampleFormat.I16_RF)),
        m.StreamStop(),
        m.StreamStopResponse(100, 400),
        m.StreamStatusRequest(),
        m.StreamStatus(1, 10, 40, 0, 2, 1),
        StreamData(7, 2, 4, int(SampleFormat.U16_ENVELOPE), 400000, 1_234_567_890, ramp),
        StreamData(8, 0, 3, int(SampleFormat.I16_RF), 250000, 2**40 + 5, b"\xff\x7f\x00\x80"),
        StreamData(9, 1, 3, int(SampleFormat.F32), 100000, 0, b"\x00\x00\x80\x3f"),
        m.ConfigRead(0, 256, int(m.ConfigSource.STAGING)),
        m.ConfigReadResponse(0, b"[spiel]\nrate=20\n"),
        m.ConfigWrite(0, b"[spiel]\nrate=20\n"),
        m.ConfigWriteResponse(16),
        m.ConfigCommit(16, crc32c(b"[spiel]\nrate=20\n")),
        m.ConfigCommitResponse(1, 3, 16, crc32c(b"[spiel]\nrate=20\n")),
        m.ConfigStatusRequest(),
        m.ConfigStatus(1, 0, 4096, 2, 12, 0x11111111, 1, 3, 16, 0x22222222, 1),
        *_v2_messages(),
    ]


def _v2_messages() -> list[m.Message]:
    """Protocol version 2: one of every message (PROTOCOL.md section 14)."""
    sha = bytes(range(32))
    return [
        m.TimeSync(1_700_000_000_123_456),
        m.TimeSyncResponse(1_700_000_000_123_456, 987_654_321, 0x5EED1234),
        m.Telemetry(500, int(m.LogLevel.INFO), 20),
        m.TelemetryResponse(500, int(m.LogLevel.INFO), 20),
        m.Heartbeat(123456, int(m.BoardState.STREAMING), 0, 500, 0x12, 0x5EED1234, 123_456_789),
        m.LogMessage(int(m.LogLevel.WARNING), 3, 123_456_789, "overrun at acquisition 17"),
        m.FwInfoRequest(),
        m.FwInfo(
            0,
            int(m.BootState.CONFIRMED),
            0,
            0,
            65536,
            "posix",
            int(m.SlotState.VERIFIED),
            "1.0.0",
            2048,
            0x11111111,
            int(m.SlotState.PARTIAL),
            "",
            512,
            0x22222222,
        ),
        m.FwBegin(2048, 0x11111111, sha),
        m.FwBeginResponse(1, 65536),
        m.FwWrite(1024, bytes(range(16))),
        m.FwWriteResponse(1040),
        m.FwVerify(1),  # FwVerifyFlag.ASYNC
        m.FwVerifyResponse(1, 2048, 0x11111111, sha),
        m.FwTest(100),
        m.FwTestResponse(1),
        m.FwConfirm(),
        m.FwConfirmResponse(1, int(m.BootState.CONFIRMED)),
        StreamData(
            10,
            3,
            4,
            int(SampleFormat.I16_IQ),
            21875,
            5_000_000,
            b"\x01\x00\xff\xff\x00\x80\xff\x7f",
        ),
    ]


def _messages() -> list[dict[str, Any]]:
    out = []
    for i, msg in enumerate(_sample_messages()):
        seq, aux = (i * 257) & 0xFFFF, (0x100 + i if isinstance(msg, StreamData) else 0)
        wire = m.encode_message(msg, seq=seq, aux=aux)
        out.append(
            {
                "class": type(msg).__name__,
                "msg_type": int(msg.MSG_TYPE),
                "response": msg.RESPONSE,
                "seq": seq,
                "aux": aux,
                "fields": field_values(msg),
                "payload_hex": msg.pack().hex(),
                "wire_hex": wire.hex(),
            }
        )
    return out


def _header(version: int = 1, flags: int = 0, length: int | None = None, payload: bytes = b"ab"):
    n = len(payload) if length is None else length
    return HEADER.pack(version, flags, 0x0004, 1, n, 0) + payload


def _bad_crc(body: bytes) -> bytes:
    return cobs.encode(body + (crc32c(body) ^ 1).to_bytes(4, "little")) + b"\x00"


def _invalid() -> list[dict[str, Any]]:
    cases = [
        ("crc", "crc", _bad_crc(_header())),
        ("version_2", "version", wrap_body(_header(version=2))),
        ("version_0", "version", wrap_body(_header(version=0))),
        ("unknown_flag_0x20", "flags", wrap_body(_header(flags=0x20))),
        ("unknown_flag_0x80", "flags", wrap_body(_header(flags=0x80))),
        ("payload_len_too_big", "length", wrap_body(_header(length=3))),
        ("payload_len_too_small", "length", wrap_body(_header(length=1))),
        ("short_body", "length", wrap_body(b"\x01\x00\x04")),
        ("cobs_code_past_end", "cobs", b"\x05\x01\x02\x00"),
        ("oversize", "oversize", b"\x01" * (MAX_ENCODED_SIZE + 1) + b"\x00"),
    ]
    return [{"name": n, "error": e, "wire_hex": w.hex()} for n, e, w in cases]


def _stream() -> dict[str, Any]:
    """Garbage, a frame, a corrupted frame, a frame: only the intact ones come out."""
    a = encode_frame(0x0004, b"first", seq=1)
    b = _bad_crc(HEADER.pack(PROTOCOL_VERSION, 0, 0x0004, 2, 6, 0) + b"broken")
    c = encode_frame(0x0004, b"second", seq=3, flags=int(Flags.RESPONSE))
    wire = b"\x13\x37garbage\x00" + a + b"\x00\x00" + b + c
    decoder = FrameDecoder()
    frames = decoder.feed(wire)
    return {
        "wire_hex": wire.hex(),
        "frames": [
            {"seq": f.seq, "flags": f.flags, "payload_hex": f.payload.hex()} for f in frames
        ],
        "stats": decoder.stats.as_dict(),
    }


def build_test_vectors() -> dict[str, Any]:
    return {
        "description": "spiel-edge firmware protocol test vectors; see PROTOCOL.md",
        "protocol_version": PROTOCOL_VERSION,
        "max_payload": MAX_PAYLOAD,
        "max_encoded_size": MAX_ENCODED_SIZE,
        "schema_hash": m.SCHEMA_HASH,
        "crc32c_check": {"input_ascii": "123456789", "crc": crc32c(b"123456789")},
        "frames": _frames(),
        "messages": _messages(),
        "invalid": _invalid(),
        "stream": _stream(),
    }
