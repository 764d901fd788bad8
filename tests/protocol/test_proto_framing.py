"""Framing: exact bytes, round trips under arbitrary chunking, resync, bounded buffer."""

from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from spiel_edge.protocol import (
    MAX_ENCODED_SIZE,
    MAX_PAYLOAD,
    MAX_WIRE_SIZE,
    Flags,
    Frame,
    FrameDecoder,
    FrameError,
    ProtocolError,
    encode_frame,
)
from spiel_edge.protocol.framing import crc32c


def chunked(data: bytes, cuts: list[int]) -> list[bytes]:
    """Split ``data`` at the (sorted, clipped) cut points."""
    points = sorted({min(c, len(data)) for c in cuts} | {0, len(data)})
    return [data[a:b] for a, b in zip(points, points[1:], strict=False)]


def decode_all(chunks: list[bytes]) -> tuple[list[Frame], FrameDecoder]:
    decoder = FrameDecoder()
    frames = [f for chunk in chunks for f in decoder.feed(chunk)]
    return frames, decoder


def test_crc32c_check_value() -> None:
    assert crc32c(b"123456789") == 0xE3069283


def test_worked_example_bytes() -> None:
    # PROTOCOL.md worked example 1: type 0x8001, seq 1, payload "ab"
    wire = encode_frame(0x8001, b"ab", seq=1)
    body = bytes.fromhex("01 00 0180 0100 0200 00000000 6162")
    assert crc32c(body) == 0xBEAD6F22
    assert wire == bytes.fromhex("02 01 04 01 80 01 02 02 01 01 01 01 07 61 62 22 6f ad be 00")


def test_header_fields_round_trip() -> None:
    wire = encode_frame(
        0xBEEF, b"xyz", seq=0xFFFF, flags=Flags.RESPONSE | Flags.MORE, aux=2**32 - 1
    )
    assert wire.count(0) == 1 and wire.endswith(b"\x00")
    assert FrameDecoder().feed(wire) == [Frame(0xBEEF, 0xFFFF, 0x11, 2**32 - 1, b"xyz")]


@pytest.mark.parametrize(
    "kwargs",
    [{"seq": -1}, {"seq": 1 << 16}, {"aux": 1 << 32}, {"flags": 0x20}, {"flags": 0x100}],
)
def test_encode_rejects_out_of_range(kwargs: dict) -> None:
    with pytest.raises(FrameError):
        encode_frame(1, b"", **kwargs)
    with pytest.raises(FrameError):
        encode_frame(1 << 16, b"")


def test_encode_rejects_oversize_payload_and_errors_are_value_errors() -> None:
    assert len(encode_frame(1, bytes(MAX_PAYLOAD))) <= MAX_WIRE_SIZE
    with pytest.raises(FrameError) as info:
        encode_frame(1, bytes(MAX_PAYLOAD + 1))
    assert isinstance(info.value, ProtocolError) and isinstance(info.value, ValueError)


def test_worst_case_encoded_size_fits_bound() -> None:
    wire = encode_frame(0x0101, b"\x01" * MAX_PAYLOAD, seq=0x0101, flags=1, aux=0x01010101)
    assert len(wire) - 1 <= MAX_ENCODED_SIZE
    assert len(FrameDecoder().feed(wire)) == 1


frame_args = st.tuples(
    st.integers(0, 0xFFFF),
    st.integers(0, 0xFFFF),
    st.integers(0, 0x1F),
    st.integers(0, 2**32 - 1),
)


@settings(max_examples=150, deadline=None)
@given(
    frames=st.lists(st.tuples(frame_args, st.binary(max_size=600)), min_size=1, max_size=8),
    big=st.integers(0, MAX_PAYLOAD),
    cuts=st.lists(st.integers(0, 40_000), max_size=30),
)
def test_round_trip_under_arbitrary_chunking(frames: list, big: int, cuts: list[int]) -> None:
    sent = [Frame(t, s, f, a, p) for (t, s, f, a), p in frames]
    sent.append(Frame(0x13, 1, 8, 2, bytes(range(256)) * (big // 256) + bytes(big % 256)))
    stream = b"".join(fr.encode() for fr in sent)
    got, decoder = decode_all(chunked(stream, cuts))
    assert got == sent
    assert decoder.stats.frames == len(sent) and decoder.stats.errors == 0
    assert decoder.buffered == 0


def test_byte_at_a_time() -> None:
    sent = [Frame(7, i, 0, i, bytes([i]) * i) for i in range(20)]
    stream = b"".join(f.encode() for f in sent)
    got, _ = decode_all([stream[i : i + 1] for i in range(len(stream))])
    assert got == sent


def test_every_payload_size_round_trips() -> None:
    decoder = FrameDecoder()
    for n in range(MAX_PAYLOAD + 1):
        payload = bytes((i * 31 + n) & 0xFF for i in range(n)) if n < 600 else bytes(n)
        [frame] = decoder.feed(encode_frame(3, payload, seq=n & 0xFFFF))
        assert frame.payload == payload
    assert decoder.stats.errors == 0


@settings(max_examples=300, deadline=None)
@given(data=st.binary(max_size=3000), cuts=st.lists(st.integers(0, 3000), max_size=10))
def test_garbage_never_raises_and_chunking_does_not_matter(data: bytes, cuts: list[int]) -> None:
    whole, d1 = decode_all([data])
    parts, d2 = decode_all(chunked(data, cuts))
    assert whole == parts == []
    assert d1.stats == d2.stats
    assert d2.buffered <= MAX_ENCODED_SIZE


def test_resync_after_corrupted_frame() -> None:
    good1, good2 = encode_frame(1, b"one", seq=1), encode_frame(1, b"two", seq=2)
    bad = bytearray(encode_frame(1, b"bad", seq=3))
    bad[-3] ^= 0x01
    frames, decoder = decode_all([good1 + bytes(bad) + good2])
    assert [f.payload for f in frames] == [b"one", b"two"]
    assert decoder.stats.crc == 1


def test_truncated_frame_then_next_frame_is_lost_only_once() -> None:
    good = encode_frame(1, b"payload", seq=9)
    # A truncated frame merges with the next one up to its delimiter: one piece dropped.
    frames, decoder = decode_all([good[:5], good, good])
    assert [f.seq for f in frames] == [9]
    assert decoder.stats.errors == 1


def test_buffer_is_bounded_and_recovers() -> None:
    decoder = FrameDecoder()
    for _ in range(30):
        assert decoder.feed(b"\x07" * 1000) == []
        assert decoder.buffered <= MAX_ENCODED_SIZE
    assert decoder.stats.oversize == 1
    assert decoder.feed(b"\x07\x00" + encode_frame(2, b"ok")) == [Frame(2, payload=b"ok")]
    assert decoder.stats.oversize == 1 and decoder.stats.errors == 1


def test_oversize_piece_in_one_chunk() -> None:
    decoder = FrameDecoder()
    assert decoder.feed(b"\x01" * (MAX_ENCODED_SIZE + 1) + b"\x00") == []
    assert decoder.stats.oversize == 1


def test_reset_drops_partial_frame() -> None:
    decoder = FrameDecoder()
    wire = encode_frame(1, b"abc")
    decoder.feed(wire[:4])
    decoder.reset()
    assert decoder.buffered == 0
    assert decoder.feed(wire[4:]) == []


def test_leading_delimiters_are_not_errors() -> None:
    frames, decoder = decode_all([b"\x00\x00\x00" + encode_frame(1) + b"\x00"])
    assert len(frames) == 1 and decoder.stats.errors == 0


def test_accepts_bytearray_and_memoryview() -> None:
    wire = encode_frame(5, b"mv")
    assert FrameDecoder().feed(bytearray(wire)) == FrameDecoder().feed(memoryview(wire))
