"""PROTOCOL.md stays true: worked examples decode, tables match the code."""

from __future__ import annotations

import re
import struct
from pathlib import Path

import pytest

from spiel_edge.board_config import schema as board_schema
from spiel_edge.protocol import (
    MAX_ENCODED_SIZE,
    MAX_PAYLOAD,
    REGISTRY,
    SCHEMA_HASH,
    ConfigCommit,
    ErrorCode,
    ErrorResponse,
    FrameDecoder,
    Hello,
    MsgType,
    StreamData,
    config_blob,
    decode_message,
)

SPEC = (Path(__file__).resolve().parents[2] / "firmware_protocol" / "PROTOCOL.md").read_text()


def worked_examples() -> list[bytes]:
    """The ``wire`` lines of section 11 (continuation lines are indented hex)."""
    block = SPEC[SPEC.index("## 11. Worked examples") :]
    found = re.findall(r"^wire\s+([0-9a-f ]+(?:\n\s+[0-9a-f ]+)*)$", block, re.M)
    return [bytes.fromhex(" ".join(w.split())) for w in found]


def test_worked_examples_decode_to_the_documented_messages() -> None:
    wires = worked_examples()
    assert len(wires) == 5
    decoder = FrameDecoder()
    frames = [f for w in wires for f in decoder.feed(w)]
    assert decoder.stats.errors == 0 and len(frames) == 5
    assert frames[0].msg_type == 0x8001 and frames[0].payload == b"ab"
    assert decode_message(frames[1]) == Hello(1, 1, 8256, 0)
    assert decode_message(frames[2]) == ErrorResponse(ErrorCode.VERSION_TOO_NEW, 1, "")
    data = decode_message(frames[3])
    assert isinstance(data, StreamData) and frames[3].aux == 16
    assert (data.acquisition, data.channel, data.n_channels, data.timestamp_us) == (5, 1, 3, 10**6)
    assert data.samples_array().tolist() == [10, 4095]
    assert decode_message(frames[4]) == ConfigCommit(16, 0x658090A5)


def test_constants_and_hash_are_documented() -> None:
    assert f"0x{SCHEMA_HASH:08X}" in SPEC
    assert f"| `MAX_PAYLOAD` | {MAX_PAYLOAD} |" in SPEC
    assert f"| `MAX_ENCODED_SIZE` | {MAX_ENCODED_SIZE} |" in SPEC
    assert "0xE3069283" in SPEC


@pytest.mark.parametrize("code", list(ErrorCode), ids=lambda c: c.name)
def test_error_table_matches(code: ErrorCode) -> None:
    assert f"| {int(code)} | {code.name} | {code.text} |" in SPEC


@pytest.mark.parametrize("t", list(MsgType), ids=lambda t: t.name)
def test_message_table_lists_every_type(t: MsgType) -> None:
    row = re.search(rf"^\| 0x{int(t):04x} \| {t.name} \|(.*)$", SPEC, re.M)
    assert row, t.name
    for (msg_type, _), cls in REGISTRY.items():
        if msg_type == t:
            assert f"`{cls.__name__}`" in row.group(1)


def test_documented_sizes_match_struct_sizes() -> None:
    for cls in REGISTRY.values():
        if cls._STRUCT.size and not cls._TAIL and cls is not StreamData:
            assert f"({cls._STRUCT.size} B" in SPEC or f"({cls._STRUCT.size} bytes" in SPEC, cls


def test_config_blob_example_decodes_to_the_documented_values() -> None:
    block = SPEC[SPEC.index("## 13. The board config blob") :]
    found = re.findall(r"^blob\s+([0-9a-f |]+(?:\n\s+[0-9a-f |]+)*)$", block, re.M)
    assert len(found) == 1
    raw = bytes.fromhex(found[0].replace("|", " "))
    documented = {
        "n_samples": 64,
        "decimation": 8,
        "pulse_cycles": 30,
        "blind_zone_samples": 9,
        "sample_rate_hz": 22000.0,
        "carrier_hz": 175000.0,
        "gain_db": 20.0,
        "acquisition_rate_hz": 30.0,
    }
    header = config_blob.unpack_header(raw)
    assert (header.magic, header.version, header.header_size) == (b"SPCF", 1, len(raw))
    assert header.acquisition == documented and header.toml_length == 469
    assert config_blob.pack_header(documented, 469) == raw


_C_TYPE = {"4s": "char[4]", "H": "u16", "I": "u32", "f": "f32"}


def test_config_blob_table_matches_the_layout_and_ranges() -> None:
    section = SPEC[SPEC.index("## 13. The board config blob") :]
    offset = 0
    for name, code, _ in config_blob.HEADER_FIELDS:
        row = re.search(
            rf"^\| {offset} \| {re.escape(_C_TYPE[code])} \| `{name}` \|(.*)$", section, re.M
        )
        assert row, name
        if name in board_schema.ACQUISITION:
            kind, low, high = board_schema.ACQUISITION[name]
            prefix = "int in " if kind is int else ""
            assert row.group(1).endswith(f"| {prefix}[{low:g}, {high:g}] |"), name
        offset += struct.calcsize("<" + code)
    assert f"blob = header ({config_blob.HEADER_SIZE} bytes" in SPEC
