"""AcquisitionAssembler: completion in any channel order, gap, duplicate and stale rules."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from spiel_edge.protocol import AcquisitionAssembler, SampleFormat, StreamData


def acquisition(index: int, n_ch: int = 3, n: int = 8, ts: int = 1000) -> list[StreamData]:
    rows = (np.arange(n_ch * n).reshape(n_ch, n) * 7 + index % 1000).astype("<i2")
    return [
        StreamData(index, c, n_ch, SampleFormat.I16_RF, 48000, ts + index % 1000, rows[c].tobytes())
        for c in range(n_ch)
    ]


def feed_all(asm: AcquisitionAssembler, frames: list[tuple[StreamData, int]]) -> list:
    return [a for m, c in frames if (a := asm.feed(m, c)) is not None]


def test_complete_acquisition_in_any_channel_order() -> None:
    asm = AcquisitionAssembler()
    frames = acquisition(5)
    assert asm.feed(frames[2], 0) is None and asm.feed(frames[0], 1) is None
    acq = asm.feed(frames[1], 2)
    assert acq is not None
    assert (acq.index, acq.timestamp_us, acq.sample_rate_hz) == (5, 1005, 48000)
    assert acq.samples.shape == (3, 8) and acq.samples.dtype == np.dtype("<i2")
    assert np.array_equal(acq.samples[1], frames[1].samples_array())
    assert asm.stats.acquisitions == 1 and asm.stats.gaps == 0


def test_gap_drops_incomplete_acquisition_and_counts_missing_frames() -> None:
    asm = AcquisitionAssembler()
    a0, a1 = acquisition(0), acquisition(1)
    stream = [(a0[0], 0), (a0[2], 2), (a1[0], 3), (a1[1], 4), (a1[2], 5)]  # counter 1 lost
    out = feed_all(asm, stream)
    assert [a.index for a in out] == [1]
    assert asm.stats.gaps == 1 and asm.stats.incomplete == 1


def test_duplicates_and_stale_frames_are_ignored() -> None:
    asm = AcquisitionAssembler()
    a0, a1 = acquisition(0, n_ch=2), acquisition(1, n_ch=2)
    assert asm.feed(a0[0], 0) is None
    assert asm.feed(a0[0], 0) is None  # repeated counter
    assert asm.feed(a0[0], 1) is None  # same channel again with a new counter
    assert asm.feed(a0[1], 2) is not None
    assert asm.feed(a0[1], 3) is None  # channel of an acquisition already delivered
    assert asm.feed(a1[0], 4) is None
    assert asm.feed(a0[0], 5) is None  # older acquisition while a1 is pending
    assert asm.feed(a1[1], 6) is not None
    assert asm.stats.duplicates == 2 and asm.stats.stale == 2 and asm.stats.acquisitions == 2


def test_inconsistent_channel_is_rejected() -> None:
    asm = AcquisitionAssembler()
    a = acquisition(3, n_ch=2)
    assert asm.feed(a[0], 0) is None
    bad = StreamData(3, 1, 2, SampleFormat.I16_RF, 44100, a[1].timestamp_us, a[1].samples)
    assert asm.feed(bad, 1) is None
    assert asm.stats.inconsistent == 1
    assert asm.feed(StreamData(4, 5, 2), 2) is None  # channel >= n_channels
    assert asm.stats.inconsistent == 2 and asm.stats.incomplete == 1


def test_index_and_counter_wrap_around() -> None:
    asm = AcquisitionAssembler()
    out = []
    counter = 2**32 - 2
    for index in (2**32 - 1, 0, 1):
        for m in acquisition(index, n_ch=2):
            out += [a for a in [asm.feed(m, counter & 0xFFFFFFFF)] if a]
            counter += 1
    assert [a.index for a in out] == [2**32 - 1, 0, 1]
    assert asm.stats.gaps == 0 and asm.stats.stale == 0


def test_flush_and_reset() -> None:
    asm = AcquisitionAssembler()
    asm.feed(acquisition(0)[0], 10)
    asm.flush()
    assert asm.stats.incomplete == 1
    asm.reset()  # a new stream restarts counters and indices
    out = feed_all(asm, [(m, i) for i, m in enumerate(acquisition(0))])
    assert len(out) == 1 and asm.stats.gaps == 0


@settings(max_examples=150, deadline=None)
@given(
    n_acq=st.integers(1, 12),
    n_ch=st.integers(1, 4),
    lost=st.sets(st.integers(0, 47)),
    data=st.data(),
)
def test_random_loss_yields_exactly_the_intact_acquisitions(n_acq, n_ch, lost, data) -> None:
    sent = []
    for i in range(n_acq):
        frames = acquisition(i, n_ch=n_ch, n=4)
        sent += data.draw(st.permutations(frames))
    lost = {k for k in lost if k < len(sent)}
    start = data.draw(st.integers(0, 2**32 - 1))
    asm = AcquisitionAssembler()
    kept = [(m, (start + k) & 0xFFFFFFFF) for k, m in enumerate(sent) if k not in lost]
    out = feed_all(asm, kept)
    intact = [i for i in range(n_acq) if not any(i * n_ch <= k < (i + 1) * n_ch for k in lost)]
    assert [a.index for a in out] == intact
    for a in out:
        expect = np.stack([f.samples_array() for f in acquisition(a.index, n_ch=n_ch, n=4)])
        assert np.array_equal(a.samples, expect)
    # lost frames after the last kept one are undetectable; all others count as gaps
    last_kept = max((k for k in range(len(sent)) if k not in lost), default=-1)
    first_kept = min((k for k in range(len(sent)) if k not in lost), default=len(sent))
    assert asm.stats.gaps == sum(first_kept < k < last_kept for k in lost)
    touched = {kept_m.acquisition for kept_m, _ in kept}
    pending = 1 if kept and kept[-1][0].acquisition not in {a.index for a in out} else 0
    assert asm.stats.incomplete == len(touched) - len(out) - pending
