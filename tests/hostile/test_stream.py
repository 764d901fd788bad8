"""A hostile stream: counter and index jumps must not turn into billions of 'lost'
acquisitions; a problem repeated every acquisition is logged once; acquisitions are counted
when delivered (the README's meaning), not when assembled."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from spiel_edge.device.acquisitions import StreamAssembly
from spiel_edge.protocol import StreamData, encode_message
from spiel_edge.protocol.framing import FrameDecoder
from spiel_edge.runtime.once import OncePerProblem

SAMPLES = np.zeros(8, dtype="<u2").tobytes()


def wire(index: int, counter: int, channels: int = 2) -> bytes:
    return b"".join(
        encode_message(
            StreamData(index, c, channels, samples=SAMPLES, sample_rate_hz=1000),
            aux=(counter + c) & 0xFFFFFFFF,
        )
        for c in range(channels)
    )


def fed(indices: list[int], counters: list[int]) -> StreamAssembly:
    tracker = StreamAssembly()
    tracker.begin()
    tracker.started(indices[0])
    decoder = FrameDecoder()
    for index, counter in zip(indices, counters, strict=True):
        for frame in decoder.feed(wire(index, counter)):
            tracker.feed(frame, 0)
    return tracker


@pytest.mark.parametrize(
    "jump", [2**31 - 3, 2**31 + 7, 2**32 - 2, 70_000, 10**6, 2**20], ids=lambda j: f"jump{j}"
)
def test_index_and_counter_jumps_are_not_losses(jump):
    indices = [0, 1, 2, (2 + jump) & 0xFFFFFFFF, (3 + jump) & 0xFFFFFFFF]
    counters = [0, 2, 4, (6 + jump) & 0xFFFFFFFF, (8 + jump) & 0xFFFFFFFF]
    tracker = fed(indices, counters)
    stats = tracker.assembler.stats
    assert tracker.lost < 100 and stats.gaps < 100, (tracker.lost, stats.gaps)
    assert tracker.jumps + stats.jumps >= 1 or jump > 2**31


@pytest.mark.parametrize("gap", [1, 5, 1000])
def test_real_gaps_are_still_counted(gap):
    tracker = fed([0, 1, 2 + gap], [0, 2, 4 + 2 * gap])
    assert tracker.lost == gap and tracker.jumps == 0


def test_acquisitions_counted_when_delivered_not_assembled():
    tracker = fed([0, 1, 2, 3], [0, 2, 4, 6])
    assert len(tracker.ready) == 4 and tracker.acquisitions == 0
    tracker.pop()
    assert tracker.acquisitions == 1


def test_a_repeated_problem_is_logged_once(caplog):
    once = OncePerProblem(logging.getLogger("hostile.test"))
    with caplog.at_level(logging.ERROR, logger="hostile.test"):
        for i in range(1000):
            once.log("frames has shape (200, 8), profile expects (4, 64)", f"acquisition {i}")
    assert len(caplog.records) == 1
    assert once.summary() == ["1000 x frames has shape (200, 8), profile expects (4, 64)"]
