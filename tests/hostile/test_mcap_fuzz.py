"""MCAP fuzz: one byte of a finalized 300-acquisition recording inverted, or the file cut, at
offsets spread over the whole file. Each must replay >= 90 % of its acquisitions (a cut: all
of those before it, less one chunk), and `recover` must turn it into a valid file."""

from __future__ import annotations

import logging
import struct

import pytest
from mcap.reader import make_reader

from spiel_edge.recordings.recover import recover
from tools.bench.damage import count_intact, sample_offsets

TOTAL = 300
FLIPS, CUTS = 64, 32


@pytest.fixture(scope="module")
def original(recording):
    return recording.read_bytes()


@pytest.fixture(autouse=True)
def _quiet(caplog):
    caplog.set_level(logging.ERROR, logger="spiel_edge.recordings.mcap_reader")


def _offsets(n: int, seed: int) -> list[int]:
    return sample_offsets(150_000, n, seed=seed)  # about the recording's size; clamped below


@pytest.mark.parametrize("index", range(FLIPS))
def test_one_flipped_byte_replays_90_percent(original, tmp_path, index):
    offset = min(_offsets(FLIPS, 1)[index], len(original) - 1)
    damaged = bytearray(original)
    damaged[offset] ^= 0xFF
    path = tmp_path / "flip.mcap"
    path.write_bytes(bytes(damaged))
    intact = count_intact(path)
    assert intact >= 0.9 * TOTAL, f"offset {offset}: {intact} of {TOTAL}"


def test_a_damaged_length_running_past_the_end_is_not_taken_for_a_cut(original, tmp_path):
    """One flipped bit in the length of a record between chunks (here the first message
    index) must not end the replay as if the file were cut there."""
    pos = 8  # after the magic: walk the top-level records to the first message index
    while original[pos] != 0x07:
        pos += 9 + struct.unpack_from("<Q", original, pos + 1)[0]
    damaged = bytearray(original)
    damaged[pos + 1 + 3] ^= 0x01  # + 16 MiB: past the end of the file, within the chunk bound
    path = tmp_path / "length.mcap"
    path.write_bytes(bytes(damaged))
    assert count_intact(path) >= 0.9 * TOTAL


@pytest.mark.parametrize("index", range(CUTS))
def test_a_cut_replays_what_came_before(original, tmp_path, index):
    offset = min(_offsets(CUTS, 2)[index], len(original))
    path = tmp_path / "cut.mcap"
    path.write_bytes(original[:offset])
    intact = count_intact(path)
    before = TOTAL * offset / len(original)
    assert intact >= before - 40, f"cut at {offset}: {intact}, about {before:.0f} before it"


@pytest.mark.parametrize("offset_share", [0.0005, 0.3, 0.6, 0.95])
def test_recover_writes_a_valid_recording(original, tmp_path, offset_share):
    damaged = bytearray(original)
    offset = int(len(original) * offset_share)
    damaged[offset] ^= 0xFF
    src, dst = tmp_path / "bad.mcap", tmp_path / "good.mcap"
    src.write_bytes(bytes(damaged[: len(damaged) - 100]))  # damaged and unfinalized
    result = recover(src, dst)
    with open(dst, "rb") as fh:  # the official reader accepts it, summary and all
        reader = make_reader(fh)
        summary = reader.get_summary()
        counted = sum(1 for _ in reader.iter_messages(topics=["/spiel/acquisition"]))
    assert summary is not None and counted == result.messages["/spiel/acquisition"]
    assert count_intact(dst) == count_intact(src) >= 0.9 * TOTAL - 25
    assert src.read_bytes() == bytes(damaged[: len(damaged) - 100])  # the input untouched
