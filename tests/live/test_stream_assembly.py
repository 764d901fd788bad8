"""StreamAssembly and LineFaults: pure accounting of what was sent, damaged and delivered."""

from __future__ import annotations

import numpy as np

from spiel_edge.device.acquisitions import StreamAssembly
from spiel_edge.device.annotation import ANNOTATION_TYPE, Annotation, encode_annotations
from spiel_edge.protocol import FrameDecoder, StreamStart, encode_frame, encode_message
from spiel_edge.sim.board import VirtualBoard
from spiel_edge.sim.faults import LineFaults, Outgoing
from spiel_edge.sim.scenes import ReplayScene

SCENE = ReplayScene()


def streamed(n: int) -> list[Outgoing]:
    board = VirtualBoard(SCENE)
    board.receive(encode_message(StreamStart(rate_hz=1000), seq=1), 0.0)
    return board.due((n - 0.5) / 1000, 1 << 22)


def feed(tracker: StreamAssembly, wire: bytes) -> None:
    for frame in FrameDecoder().feed(wire):
        tracker.feed(frame, 0)


def test_frames_before_the_start_answer_are_kept_and_losses_counted():
    out = streamed(6)
    data = [o for o in out if o.acquisition is not None]
    tracker = StreamAssembly()
    tracker.begin()
    # acquisition 0 lost on the way; 1..5 arrive before the (retried) answer
    feed(tracker, b"".join(o.wire for o in out if o.acquisition != 0))
    tracker.started(0)
    assert [a.index for a in tracker.ready] == [1, 2, 3, 4, 5]
    assert tracker.lost == 1 and len(data) == 24


def test_gaps_inside_the_stream_are_lost_acquisitions_and_truth_follows_its_acquisition():
    out = [o for o in streamed(8) if o.acquisition not in (2, 3) or o.exempt]
    tracker = StreamAssembly()
    tracker.begin()
    tracker.started(0)
    feed(tracker, b"".join(o.wire for o in out))
    got = list(tracker.ready)
    assert [a.index for a in got] == [0, 1, 4, 5, 6, 7] and tracker.lost == 2
    for a in got:
        np.testing.assert_array_equal(a.truth_mm, SCENE._truth[a.index])
        np.testing.assert_array_equal(a.background, SCENE._backgrounds[a.index])


def test_malformed_annotations_are_counted_not_fatal():
    tracker = StreamAssembly()
    odd = Annotation(
        1, 0.0, 0.0, 100.0, n_channels=2, first_channel=0, n_samples=3, background=b"\x01" * 5
    )
    truncated = odd.pack()[:-2]  # the tail is shorter than declared
    feed(
        tracker,
        encode_frame(ANNOTATION_TYPE, odd.pack()) + encode_frame(ANNOTATION_TYPE, truncated),
    )
    assert tracker.background is None and tracker.bad_messages == 2
    big = np.arange(4 * 2100, dtype=np.uint16).reshape(4, 2100)  # does not fit one frame
    feed(tracker, b"".join(encode_annotations(9, None, big)))
    np.testing.assert_array_equal(tracker.background, big)


def test_line_faults_mark_a_frame_and_the_one_its_broken_delimiter_swallows():
    frames = [Outgoing(encode_frame(0x13, bytes([k]) * 40, aux=k), acquisition=k) for k in range(3)]
    faults = LineFaults(ber=1.0 / 41, seed=0)
    hits = iter([True, False, False])

    def flip_first_delimiter(data: bytes) -> tuple[bytes, int]:
        return (data[:-1] + b"\x01", 1) if next(hits) else (data, 0)

    faults._flip = flip_first_delimiter
    wire = faults.outgoing(frames)
    assert faults.stats.damaged == {0, 1}
    decoded = FrameDecoder().feed(wire)
    assert [f.aux for f in decoded] == [2]
