"""Write the A-scans file the posix reference firmware streams (firmware_protocol/firmware).

The firmware (targets/posix) reads no CSV: this tool turns spiel-csv recordings (one
``*_frames.csv`` per acquisition, in name order, as ``spiel-edge replay`` reads them) or the
vendored subset into one little-endian binary file, which the firmware loops over in order:

    offset  size  field
    0       4     magic "SPAS"
    4       2     version (1)
    6       2     n_channels
    8       2     n_samples
    10      2     reserved (0)
    12      4     n_acquisitions
    16      4     sample_rate_hz (integer Hz)
    20      ...   u16 samples [acquisition][channel][sample]

    python -m tools.release.firmware_scans OUT.spas --folder RECORDINGS [--sample-rate 22000]
    python -m tools.release.firmware_scans OUT.spas --subset
"""

from __future__ import annotations

import argparse
import struct
import sys
from pathlib import Path

import numpy as np

HEADER = struct.Struct("<4sHHHHII")
MAGIC = b"SPAS"
U16_MAX = 65535


def write_scans(path: str | Path, frames: np.ndarray, sample_rate_hz: int) -> Path:
    """``frames`` (acquisitions, channels, samples), rounded and clipped to uint16."""
    arr = np.asarray(frames, dtype=np.float64)
    if arr.ndim != 3 or 0 in arr.shape or arr.shape[1] > 32:
        raise ValueError(f"frames must be (acquisitions, 1..32 channels, samples), got {arr.shape}")
    rows = np.clip(np.rint(arr), 0, U16_MAX).astype("<u2")
    n_acq, n_ch, n_s = rows.shape
    path = Path(path)
    path.write_bytes(
        HEADER.pack(MAGIC, 1, n_ch, n_s, 0, n_acq, int(sample_rate_hz)) + rows.tobytes()
    )
    return path


def read_folder(folder: str | Path) -> np.ndarray:
    """Every ``*_frames.csv`` of a spiel-csv folder, in name order (as replay reads them)."""
    from spiel_edge.recordings.spiel_csv import frame_files, read_frames

    return np.stack([read_frames(p) for p in frame_files(folder)])


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("output")
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument("--folder", help="spiel-csv recordings")
    source.add_argument("--subset", action="store_true", help="the vendored spiel-icra23 subset")
    parser.add_argument("--sample-rate", type=int, default=22000, help="Hz (default 22000)")
    args = parser.parse_args(argv)
    try:
        if args.subset:
            from spiel_edge.data import load_subset

            frames = load_subset().frames
        else:
            frames = read_folder(args.folder)
        path = write_scans(args.output, frames, args.sample_rate)
    except (OSError, ValueError) as exc:
        print(f"firmware_scans: {exc}", file=sys.stderr)
        return 1
    except Exception as exc:  # InputError of a bad recording: one line, no traceback
        print(f"firmware_scans: {exc}", file=sys.stderr)
        return 1
    print(f"{path}: {frames.shape[0]} acquisitions of {frames.shape[1]} x {frames.shape[2]}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
