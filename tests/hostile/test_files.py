"""Hostile recordings: spiel-csv frames files of every bad kind, and MCAP files with hostile
payloads, zero-filled or garbage tails. Each is one input error (or the whole replay refused),
never a traceback, never unbounded memory or time."""

from __future__ import annotations

import json
import os
import time
import tracemalloc

import numpy as np
import pytest
from mcap.writer import Writer

from spiel_edge.profile.schema import load_profile
from spiel_edge.recordings.mcap_reader import iter_mcap_recordings
from spiel_edge.recordings.spiel_csv import read_frames
from spiel_edge.safety.limits import InputLimits

GOOD_ROW = " ".join(["100"] * 64)
LIMITS = InputLimits.for_profile(load_profile("spiel-icra23"))

BAD_FRAMES = {
    "empty": "",
    "blank": "\n\n   \n",
    "binary": b"\x00\x01\x02\xff" * 100,
    "not-utf8": b"\xff\xfe" + GOOD_ROW.encode(),
    "ragged": "\n".join([GOOD_ROW] * 3 + ["1 2 3"]),
    "token-10MB": "9" * (10 << 20),
    "nan": "\n".join([GOOD_ROW] * 3 + [GOOD_ROW.replace("100", "nan", 1)]),
    "inf": "\n".join([GOOD_ROW] * 3 + [GOOD_ROW.replace("100", "inf", 1)]),
    "overflow": "\n".join([GOOD_ROW] * 3 + [GOOD_ROW.replace("100", "1e400", 1)]),
    "3-channels": "\n".join([GOOD_ROW] * 3),
    "65-samples": "\n".join([GOOD_ROW + " 1"] * 4),
    "1000-channels": "\n".join([GOOD_ROW] * 1000),
    "words": "\n".join(["a b c d"] * 4),
    "hex": "\n".join([" ".join(["0x10"] * 64)] * 4),
    "huge-int": "\n".join([" ".join(["1" * 5000] * 64)] * 4),
}


def _write(path, content) -> None:
    if isinstance(content, bytes):
        path.write_bytes(content)
    else:
        path.write_text(content)


@pytest.mark.parametrize("kind", sorted(BAD_FRAMES))
def test_bad_frames_file_is_one_input_error(cli, tmp_path, kind):
    folder = tmp_path / "in"
    folder.mkdir()
    _write(folder / f"{kind}_frames.csv", BAD_FRAMES[kind])
    out = tmp_path / "out.ndjson"
    ran = cli("replay", folder, "--association", "geometric", "-o", out)
    assert ran.status == 1, ran
    record = json.loads(out.read_text())
    assert record["error"].startswith(f"{kind}_frames.csv") and len(record["error"]) < 400


def test_a_500_MB_frames_file_is_refused_by_its_size_unread(tmp_path):
    path = tmp_path / "big_frames.csv"
    with open(path, "wb") as fh:
        fh.truncate(500 << 20)  # sparse: costs no disk
    tracemalloc.start()
    started = time.monotonic()
    with pytest.raises(Exception, match="more than a frame of the profile's shape"):
        read_frames(path, LIMITS)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert time.monotonic() - started < 1.0 and peak < 1 << 20


def test_background_folder_missing_a_file(cli, tmp_path, csv_folder):
    frames, _ = csv_folder
    empty_bg = tmp_path / "bg"
    empty_bg.mkdir()
    ran = cli("replay", frames, "--background", empty_bg, "-o", tmp_path / "o.ndjson")
    assert ran.status == 1


# --- MCAP payloads -------------------------------------------------------------------------


def _mcap(path, payloads: list[bytes], good: int = 3) -> None:
    """``good`` valid acquisitions, then the hostile payloads, then ``good`` more."""
    frames = [[100] * 64] * 4
    with open(path, "wb") as fh:
        writer = Writer(fh)
        writer.start()
        schema = writer.register_schema("s", "jsonschema", b"{}")
        channel = writer.register_channel("/spiel/acquisition", "json", schema)
        data = [json.dumps({"seq": i, "frames": frames}).encode() for i in range(good)]
        more = [json.dumps({"seq": 100 + i, "frames": frames}).encode() for i in range(good)]
        for seq, payload in enumerate(data + payloads + more):
            writer.add_message(channel, log_time=seq, data=payload, publish_time=seq, sequence=seq)
        writer.finish()


HOSTILE_PAYLOADS = {
    "deep-nesting": b"[" * 100_000 + b"]" * 100_000,
    "deep-object": b'{"frames":' + b"[" * 50_000 + b"]" * 50_000 + b"}",
    "huge-int": b'{"frames": [[' + b"9" * 5000 + b"]]}",
    "float-overflow": b'{"frames": [[1e400, 1]]}',
    "int-overflow": b'{"frames": [[' + str(10**400).encode() + b"]]}",
    "not-object": b"[1, 2, 3]",
    "null": b"null",
    "not-json": b"\xff\xfe garbage",
    "frames-string": b'{"frames": "abc"}',
    "frames-3d": b'{"frames": [[[1]]]}',
    "frames-missing": b'{"seq": 5}',
    "frames-ragged": b'{"frames": [[1, 2], [3]]}',
    "too-many-channels": json.dumps({"frames": [[1]] * 10_000}).encode(),
    "oversize": b'{"frames": [[' + b"1," * (1 << 20) + b"1]]}",
    "seq-huge": json.dumps({"seq": 10**30, "frames": [[1] * 64] * 4}).encode(),
    "background-crc-bogus": json.dumps({"background_crc": 5, "frames": [[1] * 64] * 4}).encode(),
}


@pytest.mark.parametrize("kind", sorted(HOSTILE_PAYLOADS))
def test_hostile_payload_costs_only_its_message(cli, tmp_path, kind):
    path = tmp_path / "h.mcap"
    _mcap(path, [HOSTILE_PAYLOADS[kind]])
    recs = list(iter_mcap_recordings(path, LIMITS))
    good = [r for r in recs if r.error is None]
    assert len(good) >= 6 - (kind == "seq-huge") * 0, [r.error for r in recs if r.error]
    assert all(len(r.error) < 400 for r in recs if r.error)
    ran = cli("replay", path, "--association", "geometric", "-o", tmp_path / "o.ndjson")
    assert ran.status in (0, 1)


@pytest.mark.parametrize("tail_mb", [1, 64])
def test_zero_filled_tail_is_skipped_fast(recording, tmp_path, tail_mb):
    path = tmp_path / "zeros.mcap"
    data = recording.read_bytes()
    cut = data[: len(data) * 2 // 3]
    with open(path, "wb") as fh:
        fh.write(cut)
        fh.truncate(len(cut) + (tail_mb << 20))  # a crash mid-write leaves zeros
    started = time.monotonic()
    recs = list(iter_mcap_recordings(path))
    assert time.monotonic() - started < 3.0
    assert sum(r.error is None for r in recs) >= 150
    assert "zero fill" in recs[-1].error


@pytest.mark.parametrize("size_mb", [2, 8])
def test_garbage_file_memory_is_bounded(tmp_path, size_mb):
    path = tmp_path / "garbage.mcap"
    rng = np.random.default_rng(size_mb)
    with open(path, "wb") as fh:
        fh.write(b"\x89MCAP0\r\n")
        for _ in range(size_mb):
            fh.write(rng.bytes(1 << 20))
    tracemalloc.start()
    recs = list(iter_mcap_recordings(path, LIMITS))
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert all(r.error is not None for r in recs)
    assert peak < 12 << 20, f"peak {peak / 1e6:.1f} MB for a {size_mb} MB file"


def test_empty_and_magic_only_files(cli, tmp_path):
    for name, content in (("e.mcap", b""), ("m.mcap", b"\x89MCAP0\r\n"), ("x.mcap", b"MCAP")):
        (tmp_path / name).write_bytes(content)
        ran = cli("replay", tmp_path / name, "-o", tmp_path / f"{name}.ndjson")
        assert ran.status in (1, 2)
    assert os.path.getsize(tmp_path / "m.mcap") == 8
