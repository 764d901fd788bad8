"""How much of a recording survives damage, and how much memory replay needs.

    python -m tools.bench.mcap_damage [--acquisitions 300] [--flips 1000] [--cuts 200]

Records the vendored real acquisitions (cycled) as `run --record` would, then inverts one byte
(or cuts the file) at offsets spread over the whole file and counts the acquisitions the reader
still delivers intact; then the reader's peak memory (tracemalloc) for recordings of growing
size. Prints one JSON object.
"""

from __future__ import annotations

import argparse
import json
import logging
import tempfile
import time
import tracemalloc
from pathlib import Path

import numpy as np

from spiel_edge.data import load_subset
from spiel_edge.profile.schema import load_profile
from spiel_edge.recordings.mcap_reader import iter_mcap_recordings
from spiel_edge.recordings.mcap_writer import McapSink
from spiel_edge.safety.limits import InputLimits
from tools.bench.damage import count_intact, damage_sweep, sample_offsets


def record(path: Path, n: int) -> Path:
    subset = load_subset()
    with McapSink(path) as sink:
        for i in range(n):
            meta = {"seq": i, "timestamp_ns": 1_000_000 + i, "background": subset.backgrounds[0]}
            sink.write_acquisition(meta, subset.frames[i % len(subset.frames)])
            sink.write({"seq": i, "position_mm": [1.0, 2.0, 3.0], "reason": None})
    return path


def peak_memory(path: Path, limits: InputLimits) -> int:
    tracemalloc.start()
    for _ in iter_mcap_recordings(path, limits):
        pass
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    return peak


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--acquisitions", type=int, default=300)
    parser.add_argument("--flips", type=int, default=1000)
    parser.add_argument("--cuts", type=int, default=200)
    args = parser.parse_args()
    logging.disable(logging.WARNING)
    limits = InputLimits.for_profile(load_profile("spiel-icra23"))
    with tempfile.TemporaryDirectory() as tmp:
        path = record(Path(tmp) / "rec.mcap", args.acquisitions)
        size = path.stat().st_size
        started = time.monotonic()
        flips = damage_sweep(path, sample_offsets(size, args.flips, seed=7))
        cuts = damage_sweep(path, sample_offsets(size, args.cuts, seed=8), kind="cut")
        fractions = np.array([r.fraction for r in flips])
        cut_loss = [max(0.0, r.offset / size - r.fraction) for r in cuts]
        memory = {}
        for n in (300, 3000, 30000):
            big = record(Path(tmp) / f"r{n}.mcap", n)
            memory[n] = {"bytes": big.stat().st_size, "peak_bytes": peak_memory(big, limits)}
        print(
            json.dumps(
                {
                    "acquisitions": args.acquisitions,
                    "file_bytes": size,
                    "intact_undamaged": count_intact(path),
                    "flips": len(flips),
                    "flip_replayed_min": round(float(fractions.min()), 4),
                    "flip_replayed_mean": round(float(fractions.mean()), 4),
                    "flips_below_90pct": int((fractions < 0.9).sum()),
                    "cuts": len(cuts),
                    "cut_worst_loss_beyond_cut": round(max(cut_loss), 4),
                    "sweep_s": round(time.monotonic() - started, 1),
                    "reader_peak_memory": memory,
                }
            )
        )


if __name__ == "__main__":
    main()
