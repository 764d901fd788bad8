"""What a SIGKILL (or a power cut) costs a recording: acquisitions lost after `recover`.

    python -m tools.bench.sigkill_loss [--seconds 20 --rounds 3 --rate 100]

Per round: `spiel-edge run --port sim://?scene=model --rate RATE --record R.mcap -o R.ndjson`
runs for SECONDS, is killed with SIGKILL, `spiel-edge recover R.mcap -o F.mcap` rewrites what
can be read, and the acquisitions in F.mcap (read with the official mcap reader) are compared
with the records the run had flushed to R.ndjson (one line per acquisition, flushed each):
lost = records - recovered acquisitions. Also prints the recording's chunk count and the
acquisitions per chunk, the most a kill can cost.
"""

from __future__ import annotations

import argparse
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

CLI = [sys.executable, "-m", "spiel_edge.cli"]


def count_mcap(path: Path) -> tuple[int, int]:
    """(acquisitions, chunks) of a valid MCAP file."""
    from mcap.reader import make_reader

    from spiel_edge.recordings.mcap_reader import ACQUISITION_TOPIC

    with open(path, "rb") as fh:
        reader = make_reader(fh)
        summary = reader.get_summary()
        chunks = len(summary.chunk_indexes) if summary is not None else 0
        count = sum(1 for _ in reader.iter_messages(topics=[ACQUISITION_TOPIC]))
    return count, chunks


def one_round(folder: Path, seconds: float, rate: float) -> dict:
    rec, out, fixed = folder / "r.mcap", folder / "r.ndjson", folder / "f.mcap"
    for path in (rec, out, fixed):
        path.unlink(missing_ok=True)
    proc = subprocess.Popen(
        [*CLI, "run", "--port", "sim://?scene=model", "--rate", str(rate)]
        + ["--record", str(rec), "-o", str(out)],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    deadline = time.monotonic() + 120
    while not (out.exists() and out.stat().st_size) and time.monotonic() < deadline:
        time.sleep(0.05)  # until the stream runs (numba's cache loaded, board answered)
    time.sleep(seconds)
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    with open(out, "rb") as fh:
        records = sum(1 for _ in fh)
    rc = subprocess.run(
        [*CLI, "recover", str(rec), "-o", str(fixed)], capture_output=True, check=False
    ).returncode
    recovered, chunks = count_mcap(fixed)
    return {
        "records": records,
        "recovered": recovered,
        "lost": records - recovered,
        "chunks": chunks,
        "per_chunk": round(recovered / max(chunks, 1), 1),
        "recover_status": rc,
        "bytes": rec.stat().st_size,
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=20.0)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--rate", type=float, default=100.0)
    opts = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        for i in range(opts.rounds):
            r = one_round(Path(tmp), opts.seconds + i * 1.37, opts.rate)
            print(
                f"round {i + 1}: {r['records']} records flushed, {r['recovered']} acquisitions "
                f"recovered, lost {r['lost']}; {r['chunks']} chunks ({r['per_chunk']} "
                f"acquisitions each), {r['bytes']} bytes; recover status {r['recover_status']}"
            )
    return 0


if __name__ == "__main__":
    sys.exit(main())
