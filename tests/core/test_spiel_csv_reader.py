"""The compiled integer scanner reads exactly what the general parser reads."""

import numpy as np
import pytest

from spiel_edge.errors import InputError
from spiel_edge.recordings.spiel_csv import read_frames


@pytest.mark.parametrize(
    "data",
    [
        b"1 2 3\n4 5 6\n",
        b"1,2,3\r\n4,5,6\r\n\n",
        b"-0 2\n3 -4",
        b"1.5 2\n3 4\n",
        b"1e3 2\n3 4\n",
        b"12345678901234567890 1\n2 3\n",
        b"+1 2\n3 4\n",
        b"0\t15 860\n0 8 54\n",
        b"1 2\r3 4\r",
    ],
)
def test_scanner_matches_the_general_parser(tmp_path, data):
    path = tmp_path / "a_frames.csv"
    path.write_bytes(data)
    rows = [line.replace(",", " ").split() for line in data.decode().splitlines() if line.strip()]
    got, want = read_frames(path), np.array(rows, dtype=np.float64)
    assert got.dtype == want.dtype == np.float64
    assert np.array_equal(got, want) and np.array_equal(np.signbit(got), np.signbit(want))


@pytest.mark.parametrize(
    "data, message",
    [
        (b"", "empty file"),
        (b"\n\n", "empty file"),
        (b"1 2\n3\n", "different sample counts"),
        (b"1 x\n2 3\n", "not numeric"),
        (b"1 nan\n2 3\n", "NaN or infinite"),
        (b"-\n", "not numeric"),
        (b"\xff\xfe 1\n", "not text"),
    ],
)
def test_bad_files_keep_their_messages(tmp_path, data, message):
    path = tmp_path / "a_frames.csv"
    path.write_bytes(data)
    with pytest.raises(InputError, match=message):
        read_frames(path)


def test_real_recordings_read_alike(subset, tmp_path):
    frames = subset.frames[0].astype(np.int64)
    path = tmp_path / "r_frames.csv"
    path.write_text("\n".join(" ".join(str(v) for v in row) for row in frames) + "\n")
    assert np.array_equal(read_frames(path), frames.astype(np.float64))
