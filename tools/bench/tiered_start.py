"""A tiered start measured from outside (docs/first-start.md, "Tiered start").

    python -m tools.bench.tiered_start first VENV [ARGS...]   # spiel-edge ARGS: first record, end
    python -m tools.bench.tiered_start pty VENV RATE FRAMES [RUN ARGS...]

``first`` runs ``VENV/bin/spiel-edge ARGS`` and prints the seconds to its first NDJSON record
and to its end, and its records by tier. ``pty`` serves ``spiel-edge simulate --pty`` and runs
``spiel-edge run --port PTY --rate RATE --frames FRAMES`` against it: records by tier, gaps in
the acquisition index, the command's summary. Both print the load average. For an empty cache,
set ``NUMBA_CACHE_DIR`` to a new folder; ``SPIEL_EDGE_TIERED=force`` switches on a warm one.
"""

import json
import os
import subprocess
import sys
import time


def _tiers(records: list[dict]) -> dict:
    out: dict = {}
    for r in records:
        out[r.get("tier", "compiled")] = out.get(r.get("tier", "compiled"), 0) + 1
    return out


def first(venv: str, args: list[str]) -> dict:
    t0 = time.perf_counter()
    proc = subprocess.Popen(
        [f"{venv}/bin/spiel-edge", *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )
    first_s, records = None, []
    for line in proc.stdout:
        if line.startswith("{"):
            first_s = first_s if first_s is not None else time.perf_counter() - t0
            records.append(json.loads(line))
    err = proc.stderr.read()
    proc.wait()
    print(err[-1500:], file=sys.stderr)
    return {
        "first_record_s": None if first_s is None else round(first_s, 2),
        "end_s": round(time.perf_counter() - t0, 2),
        "records": len(records),
        "tiers": _tiers(records),
        "status": proc.returncode,
        "load": [round(v, 2) for v in os.getloadavg()],
    }


def pty(venv: str, rate: str, frames: str, extra: list[str]) -> dict:
    sim = subprocess.Popen(
        [f"{venv}/bin/spiel-edge", "simulate", "--pty"], stdout=subprocess.PIPE, text=True
    )
    try:
        port = sim.stdout.readline().strip()
        t0 = time.perf_counter()
        run = subprocess.run(
            [
                f"{venv}/bin/spiel-edge",
                "run",
                "--port",
                port,
                "--rate",
                rate,
                "--frames",
                frames,
                *extra,
            ],
            capture_output=True,
            text=True,
        )
        wall = time.perf_counter() - t0
    finally:
        sim.terminate()
        sim.wait()
    records = [json.loads(line) for line in run.stdout.splitlines() if line.startswith("{")]
    index = [r["acquisition"] for r in records]
    print(
        "\n".join(line for line in run.stderr.splitlines() if line.strip())[-1500:], file=sys.stderr
    )
    return {
        "rate": rate,
        "records": len(records),
        "tiers": _tiers(records),
        "index_gaps": sum(b - a - 1 for a, b in zip(index, index[1:], strict=False)),
        "wall_s": round(wall, 1),
        "status": run.returncode,
        "load": [round(v, 2) for v in os.getloadavg()],
    }


if __name__ == "__main__":
    if sys.argv[1] == "first":
        print(json.dumps(first(sys.argv[2], sys.argv[3:])))
    else:
        print(json.dumps(pty(sys.argv[2], sys.argv[3], sys.argv[4], sys.argv[5:])))
