"""Fused output latency over Zenoh on loopback (docs/robot.md): 4 board processes, 1 fuser.

    python -m tools.bench.robot_latency [--frames 600] [--robot virtual-4] [--port 7461]
        [--load N] [--realtime PRIORITY]

Starts ``spiel-edge fuse --robot R`` listening on tcp/127.0.0.1:PORT, then one
``spiel-edge run --port sim://NAME?scene=robot... --zenoh robot/NAME --rate 1/period`` per
board (each a process, peer-connected to the fuser), and reads the fused records' ``latency_ms``
(time the record was written minus the latest ``host_time`` among its boards' records: the
last board's acquisition reaching its host; one clock, loopback). Complete cycles only (every
board present), after the first 40. Prints one JSON object.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from spiel_edge.robot.description import load_robot


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--robot", default="virtual-4")
    ap.add_argument("--frames", type=int, default=600, help="acquisitions per board")
    ap.add_argument("--port", type=int, default=7461)
    ap.add_argument("--max-targets", type=int, default=4)
    ap.add_argument("--load", type=int, default=0, help="busy processes beside the robot's")
    ap.add_argument("--realtime", type=int, default=None, metavar="PRIORITY")
    args = ap.parse_args(argv)
    realtime = [] if args.realtime is None else ["--realtime", str(args.realtime)]
    busy = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(args.load)]
    try:
        record = _measure(args, realtime)
    finally:
        for p in busy:
            p.kill()
            p.wait()
    print(json.dumps({**record, "load_processes": args.load, "realtime": args.realtime}))


def _measure(args, realtime: list[str]) -> dict:
    robot = load_robot(args.robot)
    exe = [sys.executable, "-m", "spiel_edge.cli"]
    rate = 1000.0 / robot.trigger.period_ms
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        endpoint = f"tcp/127.0.0.1:{args.port}"
        off = "scouting: { multicast: { enabled: false } }"
        (tmp / "sub.json5").write_text(
            f'{{ mode: "peer", listen: {{ endpoints: ["{endpoint}"] }}, {off} }}'
        )
        (tmp / "pub.json5").write_text(
            f'{{ mode: "peer", connect: {{ endpoints: ["{endpoint}"] }}, {off} }}'
        )
        out = tmp / "fused.ndjson"
        fuse = subprocess.Popen(
            [
                *exe,
                "fuse",
                "--robot",
                args.robot,
                "--zenoh-config",
                str(tmp / "sub.json5"),
                "--idle",
                "3",
                "-o",
                str(out),
                *realtime,
            ],
            stderr=subprocess.PIPE,
            text=True,
        )
        time.sleep(1.0)
        env = {**os.environ, "ZENOH_CONFIG": str(tmp / "pub.json5")}
        boards = []
        for b in robot.boards:
            boards.append(
                subprocess.Popen(
                    [
                        *exe,
                        "run",
                        "--port",
                        b.port,
                        "--zenoh",
                        b.key,
                        "--frames",
                        str(args.frames),
                        "--rate",
                        f"{rate:g}",
                        "--max-targets",
                        str(args.max_targets),
                        "-o",
                        os.devnull,
                        "--no-track",
                        *realtime,
                    ],
                    env=env,
                    stderr=subprocess.DEVNULL,
                )
            )
        for p in boards:
            p.wait(timeout=600)
        _, err = fuse.communicate(timeout=120)
        records = [json.loads(line) for line in out.read_text().splitlines()]
    complete = [r for r in records[40:] if not r["missing"] and "latency_ms" in r]
    lat = np.array([r["latency_ms"] for r in complete])
    every = np.array([r["latency_ms"] for r in records if "latency_ms" in r])
    return {
        "boards": len(robot.boards),
        "fused_records": len(records),
        "complete_cycles": int(lat.size),
        "latency_ms_median": round(float(np.median(lat)), 3) if lat.size else None,
        "latency_ms_p95": round(float(np.percentile(lat, 95)), 3) if lat.size else None,
        "fuser_ms_median": _q([r.get("fuser_ms") for r in complete], 50),
        "fuser_ms_p95": _q([r.get("fuser_ms") for r in complete], 95),
        "latency_ms_p95_every_record": round(float(np.percentile(every, 95)), 3)
        if every.size
        else None,
        "fuse_summary": err.strip().splitlines()[-1] if err.strip() else "",
        "load": os.getloadavg()[0],
    }


def _q(values, q: float) -> float | None:
    """The q-th percentile of the values given (None: none)."""
    v = np.array([x for x in values if x is not None], float)
    return round(float(np.percentile(v, q)), 3) if v.size else None


if __name__ == "__main__":
    main()
