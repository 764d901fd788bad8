"""The shipped test_vectors.json: up to date, and every vector decodes as documented."""

from __future__ import annotations

import json

import pytest

from spiel_edge.protocol import (
    HEADER_SIZE,
    FrameDecoder,
    decode_message,
    encode_frame,
    encode_message,
    load_test_vectors,
)
from spiel_edge.protocol.framing import crc32c
from spiel_edge.protocol.vectors import build_test_vectors, message_from_fields

from .regen_vectors import render

VECTORS = load_test_vectors()


def test_shipped_vectors_match_the_implementation() -> None:
    assert json.loads(render()) == VECTORS, "run: python -m tests.protocol.regen_vectors"
    assert build_test_vectors()["schema_hash"] == VECTORS["schema_hash"]


def test_crc_check_value() -> None:
    check = VECTORS["crc32c_check"]
    assert crc32c(check["input_ascii"].encode()) == check["crc"] == 0xE3069283


@pytest.mark.parametrize("v", VECTORS["frames"], ids=lambda v: v["name"])
def test_frame_vectors(v: dict) -> None:
    payload, wire = bytes.fromhex(v["payload_hex"]), bytes.fromhex(v["wire_hex"])
    assert (
        encode_frame(v["msg_type"], payload, seq=v["seq"], flags=v["flags"], aux=v["aux"]) == wire
    )
    header = bytes.fromhex(v["header_hex"])
    assert len(header) == HEADER_SIZE and crc32c(header + payload) == v["crc"]
    [frame] = FrameDecoder().feed(wire)
    assert (frame.msg_type, frame.seq, frame.flags, frame.aux) == (
        v["msg_type"],
        v["seq"],
        v["flags"],
        v["aux"],
    )
    assert frame.payload == payload


@pytest.mark.parametrize("v", VECTORS["messages"], ids=lambda v: v["class"])
def test_message_vectors(v: dict) -> None:
    msg = message_from_fields(v["class"], v["fields"])
    assert msg.pack().hex() == v["payload_hex"]
    wire = bytes.fromhex(v["wire_hex"])
    assert encode_message(msg, seq=v["seq"], aux=v["aux"]) == wire
    [frame] = FrameDecoder().feed(wire)
    assert frame.msg_type == v["msg_type"] and frame.is_response == v["response"]
    assert decode_message(frame) == msg


@pytest.mark.parametrize("v", VECTORS["invalid"], ids=lambda v: v["name"])
def test_invalid_vectors_are_dropped_and_counted(v: dict) -> None:
    decoder = FrameDecoder()
    assert decoder.feed(bytes.fromhex(v["wire_hex"])) == []
    counts = decoder.stats.as_dict()
    assert counts[v["error"]] == 1 and decoder.stats.errors == 1


def test_stream_vector() -> None:
    v = VECTORS["stream"]
    wire = bytes.fromhex(v["wire_hex"])
    decoder = FrameDecoder()
    frames = [f for i in range(len(wire)) for f in decoder.feed(wire[i : i + 1])]
    got = [{"seq": f.seq, "flags": f.flags, "payload_hex": f.payload.hex()} for f in frames]
    assert got == v["frames"] and decoder.stats.as_dict() == v["stats"]
    assert v["stats"]["crc"] == 1 and v["stats"]["frames"] == 2
