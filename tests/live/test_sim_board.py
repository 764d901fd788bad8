"""The virtual board as a protocol state machine: answers, deduplication, streaming."""

from __future__ import annotations

import numpy as np
import pytest

from spiel_edge.device.annotation import ANNOTATION_TYPE, Annotation
from spiel_edge.profile.schema import load_profile
from spiel_edge.protocol import (
    ErrorCode,
    ErrorResponse,
    Flags,
    FrameDecoder,
    Hello,
    HelloResponse,
    MsgType,
    Ping,
    StreamData,
    StreamStart,
    StreamStartResponse,
    StreamStop,
    decode_message,
    encode_frame,
    encode_message,
)
from spiel_edge.sim.board import VirtualBoard
from spiel_edge.sim.scenes import EchoModelScene, ReplayScene


def answers(board: VirtualBoard, msg, seq: int, now: float = 0.0):
    out = board.receive(encode_message(msg, seq=seq), now)
    frames = FrameDecoder().feed(b"".join(o.wire for o in out))
    return [(f.seq, decode_message(f)) for f in frames]


@pytest.fixture(scope="module")
def replay_scene():
    return ReplayScene()


def test_hello_reports_identity_and_negotiates(replay_scene):
    board = VirtualBoard(replay_scene, serial="B1", vid=0x1234, pid=0x5678)
    [(seq, hello)] = answers(board, Hello(1, 3), seq=7)
    assert seq == 7 and isinstance(hello, HelloResponse)
    assert (hello.serial, hello.usb_vid, hello.usb_pid, hello.n_channels) == (
        "B1",
        0x1234,
        0x5678,
        4,
    )
    assert (hello.protocol_version, hello.min_version, hello.max_version) == (2, 1, 2)
    [(_, old)] = answers(board, Hello(1, 1), seq=8)  # a version-1 host gets version 1
    assert old.protocol_version == 1
    [(_, too_new)] = answers(board, Hello(3, 4), seq=9)
    assert isinstance(too_new, ErrorResponse) and too_new.code == ErrorCode.VERSION_TOO_NEW
    v1 = VirtualBoard(replay_scene, protocol=1)  # ?protocol=1: a version-1 board
    [(_, hello)] = answers(v1, Hello(1, 2), seq=1)
    assert (hello.protocol_version, hello.max_version) == (1, 1)


def test_repeated_sequence_number_is_answered_not_executed(replay_scene):
    board = VirtualBoard(replay_scene)
    first = answers(board, StreamStart(rate_hz=100), seq=41)
    again = answers(board, StreamStart(rate_hz=100), seq=41)
    assert first == again and isinstance(first[0][1], StreamStartResponse)
    assert board.stats.executed[MsgType.STREAM_START] == 1 and board.stats.repeated == 1
    answers(board, StreamStart(rate_hz=100), seq=42)  # a new request is executed
    assert board.stats.executed[MsgType.STREAM_START] == 2


def test_hello_starts_a_new_session_and_forgets_cached_answers(replay_scene):
    board = VirtualBoard(replay_scene)
    answers(board, Ping(b"a"), seq=5)
    answers(board, Hello(), seq=6)
    [(_, pong)] = answers(board, Ping(b"b"), seq=5)  # same seq after HELLO: executed again
    assert pong.data == b"b"


def test_bad_requests_get_error_answers(replay_scene):
    board = VirtualBoard(replay_scene)
    out = board.receive(_raw_request(0x0999, seq=2), 0.0)
    [(seq, err)] = [
        (f.seq, decode_message(f)) for f in FrameDecoder().feed(b"".join(o.wire for o in out))
    ]
    assert seq == 2 and err.code == ErrorCode.UNSUPPORTED
    bad_starts = (
        StreamStart(sample_format=1),
        StreamStart(n_samples=128),
        StreamStart(rate_hz=-1.0),
        StreamStart(channel_mask=0b0011),
    )
    for seq, bad in enumerate(bad_starts, start=3):
        [(_, err)] = answers(board, bad, seq=seq)
        assert isinstance(err, ErrorResponse) and err.code in (
            ErrorCode.INVALID,
            ErrorCode.UNSUPPORTED,
        )
    assert not board.streaming


def _raw_request(msg_type: int, seq: int) -> bytes:
    return encode_frame(msg_type, b"", seq=seq)


def stream_frames(board: VirtualBoard, now: float, room: int = 1 << 20):
    return FrameDecoder().feed(b"".join(o.wire for o in board.due(now, room)))


def test_stream_paces_acquisitions_and_counts_overruns(replay_scene):
    board = VirtualBoard(replay_scene, now=0.0)
    answers(board, StreamStart(rate_hz=100), seq=1, now=0.0)
    frames = stream_frames(board, 0.095)  # due at 0, 10, ..., 90 ms
    data = [StreamData.unpack(f.payload) for f in frames if f.msg_type == MsgType.STREAM_DATA]
    assert len(data) == 40 and [d.acquisition for d in data[::4]] == list(range(10))
    assert [f.aux for f in frames if f.msg_type == MsgType.STREAM_DATA] == list(range(40))
    assert {d.timestamp_us for d in data[4:8]} == {10000}
    assert stream_frames(board, 0.205, room=100) == [] and board.stats.overruns == 11  # 100..200 ms


def test_annotations_carry_truth_and_background_of_the_recording(replay_scene):
    board = VirtualBoard(replay_scene)
    answers(board, StreamStart(rate_hz=0), seq=1)
    frames = stream_frames(board, 0.0, room=4000) + stream_frames(board, 0.01, room=4000)
    notes = [Annotation.unpack(f.payload) for f in frames if f.msg_type == ANNOTATION_TYPE]
    assert len(notes) >= 2
    k = notes[1].acquisition
    np.testing.assert_array_equal(notes[1].truth_mm, replay_scene._truth[k])
    np.testing.assert_array_equal(notes[1].background_rows(), replay_scene._backgrounds[k])
    channel0 = next(
        StreamData.unpack(f.payload)
        for f in frames
        if f.msg_type == MsgType.STREAM_DATA and StreamData.unpack(f.payload).acquisition == k
    )
    np.testing.assert_array_equal(channel0.samples_array(), replay_scene._frames[k][0])


def test_as_fast_as_it_can_is_one_listening_window_apart(replay_scene):
    """Rate 0: back to back, never two acquisitions within one listening window (64 samples at
    22 kHz: 2.9 ms), so the board's stamps advance with its acquisitions (a burst stamped with
    one time reads as a clock that stood still, and the host stops trusting it)."""
    board = VirtualBoard(replay_scene, now=0.0)
    answers(board, StreamStart(rate_hz=0), seq=1, now=0.0)
    data = []
    for now in (0.0, 0.001, 0.0095, 0.0095, 0.05, 0.0531, 0.06):  # a host that reads late
        frames = stream_frames(board, now)
        data += [StreamData.unpack(f.payload) for f in frames if f.msg_type == MsgType.STREAM_DATA]
    stamps = [d.timestamp_us for d in data[::4]]
    assert [d.acquisition for d in data[::4]] == list(range(len(stamps))) and len(stamps) >= 5
    window_us = 64 / 22_000 * 1e6
    assert all(b - a >= window_us - 1 for a, b in zip(stamps, stamps[1:], strict=False))
    assert stamps[-1] <= 60_000  # never ahead of the board's clock (the last read: 60 ms)


def test_stream_frames_follow_the_spec(replay_scene):
    board = VirtualBoard(replay_scene)
    answers(board, StreamStart(rate_hz=100), seq=77)
    [(_, busy)] = answers(board, StreamStart(rate_hz=100), seq=78)
    assert busy.code == ErrorCode.BAD_STATE  # already streaming
    frames = [f for f in stream_frames(board, 0.0) if f.msg_type == MsgType.STREAM_DATA]
    assert {f.seq for f in frames} == {77}  # the STREAM_START's seq
    assert [bool(f.flags & Flags.MORE) for f in frames] == [True, True, True, False]
    answers(board, StreamStop(), seq=79)
    [(_, big)] = answers(board, StreamStart(n_samples=5000), seq=80)
    assert big.code == ErrorCode.TOO_LARGE


def test_finite_stream_stops_by_itself(replay_scene):
    board = VirtualBoard(replay_scene)
    answers(board, StreamStart(n_acquisitions=3, rate_hz=1000), seq=1)
    frames = stream_frames(board, 1.0)
    assert sum(f.msg_type == MsgType.STREAM_DATA for f in frames) == 12 and not board.streaming


def test_model_scene_arrivals_follow_the_pipeline_path_model():
    profile = load_profile()
    target = np.array([30.0, -20.0, 160.0])
    scene = EchoModelScene(profile.geometry, targets_mm=target, noise=0.0)
    frame = scene.frame(0, 64, 0.0)
    echo = frame.samples.astype(float) - frame.background
    g = profile.geometry
    path = np.linalg.norm(target - g.emitter_mm) + np.linalg.norm(target - g.channels_mm, axis=1)
    expected = path / profile.mm_per_sample + g.delays()
    peaks = echo.argmax(axis=1)
    assert np.all(np.abs(peaks - expected) <= 0.5 + 1e-9)
