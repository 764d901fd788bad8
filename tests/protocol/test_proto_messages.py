"""Messages: round trip of every type through the wire, forward-compat rule, errors table."""

from __future__ import annotations

import struct

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from spiel_edge.protocol import (
    MAX_PAYLOAD,
    MAX_SAMPLES_PER_FRAME,
    REGISTRY,
    SAMPLE_SIZE,
    SCHEMA_HASH,
    ConfigWrite,
    ErrorCode,
    ErrorResponse,
    Flags,
    Frame,
    FrameDecoder,
    Hello,
    HelloResponse,
    MessageError,
    MsgType,
    Ping,
    ProtocolError,
    RemoteError,
    SampleFormat,
    StreamData,
    StreamStart,
    UnknownMessageError,
    decode_message,
    decode_payload,
    describe_error,
    encode_message,
)

from .strategies import any_message, message_of, stream_data


def test_registry_covers_every_msg_type_both_ways() -> None:
    keys = set(REGISTRY)
    for t in MsgType:
        if t is MsgType.ERROR:
            assert (t, True) in keys and (t, False) not in keys
        elif t in (MsgType.STREAM_DATA, MsgType.HEARTBEAT, MsgType.LOG):  # device-originated
            assert (t, False) in keys and (t, True) not in keys
        else:
            assert {(t, False), (t, True)} <= keys, t.name
    assert all(isinstance(cls._STRUCT, struct.Struct) for cls in REGISTRY.values())


@pytest.mark.parametrize("cls", list(REGISTRY.values()), ids=lambda c: c.__name__)
@settings(max_examples=40, deadline=None)
@given(data=st.data())
def test_each_type_round_trips_through_the_wire(cls: type, data: st.DataObject) -> None:
    msg = data.draw(message_of(cls))
    seq, aux = data.draw(st.integers(0, 0xFFFF)), data.draw(st.integers(0, 2**32 - 1))
    wire = encode_message(msg, seq=seq, aux=aux)
    cut = data.draw(st.integers(0, len(wire)))
    decoder = FrameDecoder()
    [frame] = decoder.feed(wire[:cut]) + decoder.feed(wire[cut:])
    assert (frame.seq, frame.aux, frame.is_response) == (seq, aux, cls.RESPONSE)
    assert decode_message(frame) == msg


@settings(max_examples=100, deadline=None)
@given(msgs=st.lists(any_message(), min_size=1, max_size=20), cuts=st.lists(st.integers(0, 5000)))
def test_message_stream_round_trips_under_chunking(msgs: list, cuts: list[int]) -> None:
    stream = b"".join(encode_message(m, seq=i) for i, m in enumerate(msgs))
    points = sorted({min(c, len(stream)) for c in cuts} | {0, len(stream)})
    decoder = FrameDecoder()
    frames = [
        f for a, b in zip(points, points[1:], strict=False) for f in decoder.feed(stream[a:b])
    ]
    assert [decode_message(f) for f in frames] == msgs


@pytest.mark.parametrize("n", [0, 1, 255, 4096, MAX_PAYLOAD - 2])
def test_ping_payload_sizes_up_to_max(n: int) -> None:
    msg = Ping(bytes(range(256)) * (n // 256) + bytes(n % 256))
    [frame] = FrameDecoder().feed(encode_message(msg))
    assert len(frame.payload) == n + 2 and decode_message(frame) == msg
    with pytest.raises(ProtocolError):
        encode_message(Ping(bytes(MAX_PAYLOAD - 1)))


@pytest.mark.parametrize("fmt", list(SampleFormat))
def test_stream_data_max_samples_fit_one_frame(fmt: SampleFormat) -> None:
    n = MAX_SAMPLES_PER_FRAME[fmt]
    assert MAX_SAMPLES_PER_FRAME[SampleFormat.I16_RF] >= 4096
    msg = StreamData(1, 0, 4, fmt, 1000, 5, bytes(n * SAMPLE_SIZE[fmt]))
    [frame] = FrameDecoder().feed(encode_message(msg, aux=3))
    assert frame.flags == Flags.STREAM and frame.aux == 3
    out = decode_message(frame)
    values = 2 * n if fmt == SampleFormat.I16_IQ else n  # an I/Q sample is two int16 values
    assert out == msg and out.n_samples == n and out.samples_array().shape == (values,)


@settings(max_examples=50, deadline=None)
@given(msg=stream_data(max_samples=64), extra=st.binary(max_size=16))
def test_stream_data_ignores_extra_bytes_and_honours_header_size(
    msg: StreamData, extra: bytes
) -> None:
    payload = msg.pack()
    assert StreamData.unpack(payload + extra) == msg
    grown = bytearray(payload[:24] + b"\xee" * 8 + payload[24:])
    grown[7] = 32  # a future 32-byte sub-header: samples move, old receivers still find them
    assert StreamData.unpack(bytes(grown)) == msg


def test_stream_data_errors() -> None:
    with pytest.raises(MessageError):
        StreamData(sample_format=1, samples=b"\x01").pack()
    with pytest.raises(MessageError):
        StreamData(sample_format=9, samples=b"").pack()
    good = StreamData(1, 0, 1, 0, 10, 0, b"\x01\x02\x03\x04").pack()
    with pytest.raises(MessageError):
        StreamData.unpack(good[:-1])  # truncated samples
    with pytest.raises(MessageError):
        StreamData.unpack(good[:10])  # shorter than the sub-header


def test_short_payloads_are_zero_filled_and_extra_bytes_ignored() -> None:
    assert Hello.unpack(b"") == Hello(0, 0, 0, 0)
    assert Hello.unpack(b"\x01\x02") == Hello(1, 2, 0, 0)
    full = Hello(1, 3, 512, 7).pack()
    assert Hello.unpack(full + b"future fields") == Hello(1, 3, 512, 7)
    old = HelloResponse(protocol_version=1, n_channels=4).pack()[:6]
    assert HelloResponse.unpack(old) == HelloResponse(1, 1, 1, 4, 8256, 0, 0, 0, 0, "", 0, 0, "")
    tail = ConfigWrite(5, b"abc").pack()
    assert ConfigWrite.unpack(tail + b"\x99\x99") == ConfigWrite(5, b"abc")
    with pytest.raises(MessageError):
        ConfigWrite.unpack(tail[:-1])


@pytest.mark.parametrize(
    "msg",
    [
        Hello(min_version=256),
        HelloResponse(serial="x" * 17),
        HelloResponse(firmware_version="é" * 9),
        HelloResponse(serial="a\x00b"),
        StreamStart(n_acquisitions=-1),
    ],
)
def test_out_of_range_fields_raise_message_error(msg) -> None:
    with pytest.raises(MessageError):
        msg.pack()


def test_unknown_type_and_direction() -> None:
    with pytest.raises(UnknownMessageError) as info:
        decode_payload(0x7777, b"")
    assert isinstance(info.value, ProtocolError) and info.value.msg_type == 0x7777
    with pytest.raises(UnknownMessageError):
        decode_message(Frame(MsgType.STREAM_DATA, flags=Flags.RESPONSE))


def test_error_response_is_a_nack_and_becomes_remote_error() -> None:
    msg = ErrorResponse(ErrorCode.FLASH_VERIFY_FAILED, MsgType.CONFIG_COMMIT, "slot 1")
    [frame] = FrameDecoder().feed(encode_message(msg, seq=77))
    assert frame.flags == Flags.RESPONSE | Flags.NACK and frame.seq == 77
    exc = decode_message(frame).to_exception()
    assert isinstance(exc, RemoteError) and exc.code == ErrorCode.FLASH_VERIFY_FAILED
    assert "FLASH_VERIFY_FAILED" in str(exc) and "slot 1" in str(exc)


def test_error_table_has_text_for_every_code() -> None:
    assert [c.name for c in ErrorCode][:4] == ["OK", "UNKNOWN", "NO_MEMORY", "INVALID"]
    assert all(c.text and describe_error(int(c)) == c.text for c in ErrorCode)
    assert "999" in describe_error(999)
    assert "999" in str(RemoteError(999))


def test_schema_hash_is_stable() -> None:
    from spiel_edge.protocol import load_test_vectors

    assert load_test_vectors()["schema_hash"] == SCHEMA_HASH
