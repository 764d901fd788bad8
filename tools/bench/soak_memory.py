#!/usr/bin/env python3
"""Memory soak: `spiel-edge run` on the virtual board at 100 Hz with a recording, RSS sampled.

Target (issue 7): a 10-minute run grows memory by < 5 MB, and SIGTERM stops it within 1 s with
a readable recording. Prints one JSON document: RSS after warm-up and at the end, growth, the
least-squares slope (MB per 10 min, the extrapolation), records written, the time SIGTERM took,
and what the recording holds. The run's sd_notify messages go to a socket of ours, so READY and
WATCHDOG pings are counted too.

    python -m tools.bench.soak_memory                      # 600 s
    python -m tools.bench.soak_memory --duration 120 --rate 100
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np


def rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024.0
    raise RuntimeError("no VmRSS")


def drain(sock: socket.socket, counts: dict[str, int]) -> None:
    while True:
        try:
            data = sock.recv(4096).decode()
        except BlockingIOError:
            return
        for line in data.splitlines():
            key = line.split("=", 1)[0]
            counts[key] = counts.get(key, 0) + 1


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument(
        "--duration", type=float, default=600.0, help="seconds of streaming after warm-up"
    )
    ap.add_argument("--rate", type=float, default=100.0, help="acquisitions per second")
    ap.add_argument("--warmup", type=float, default=20.0, help="seconds before the baseline RSS")
    ap.add_argument("--sample-every", type=float, default=2.0, help="seconds between RSS samples")
    ap.add_argument("--port", default="sim://soak", help="board URL (default: the virtual board)")
    ap.add_argument("--keep", action="store_true", help="keep the recording (its path is printed)")
    args = ap.parse_args(argv)

    work = Path(tempfile.mkdtemp(prefix="spiel-soak-"))
    recording = work / "soak.mcap"
    notify_path = work / "notify.sock"
    notify = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    notify.bind(str(notify_path))
    notify.setblocking(False)
    env = {**os.environ, "NOTIFY_SOCKET": str(notify_path), "WATCHDOG_USEC": "10000000"}
    cmd = [
        sys.executable,
        "-c",
        "import sys; from spiel_edge.cli import main; sys.exit(main())",
        "run",
        "--port",
        args.port,
        "--rate",
        str(args.rate),
        "--output",
        os.devnull,
        "--record",
        str(recording),
        "--no-status",
    ]
    log_path = work / "run.log"  # a file, not a pipe: a long run's logs must never block it
    log_file = open(log_path, "w")  # noqa: SIM115 - closed below
    proc = subprocess.Popen(cmd, env=env, stderr=log_file, text=True)
    counts: dict[str, int] = {}
    start = time.monotonic()
    samples: list[tuple[float, float]] = []
    try:
        while time.monotonic() - start < args.warmup + args.duration:
            time.sleep(args.sample_every)
            if proc.poll() is not None:
                raise RuntimeError(
                    f"run exited early ({proc.returncode}): {log_path.read_text()[-2000:]}"
                )
            drain(notify, counts)
            samples.append((time.monotonic() - start, rss_mb(proc.pid)))
        t0 = time.monotonic()
        proc.send_signal(signal.SIGTERM)
        proc.wait(timeout=30)
        stop_s = time.monotonic() - t0
    finally:
        if proc.poll() is None:
            proc.kill()
        log_file.close()
    drain(notify, counts)
    stderr_tail = log_path.read_text().strip().splitlines()[-1:]

    after = np.array([(t, m) for t, m in samples if t >= args.warmup])
    slope_per_s = (
        float(np.polyfit(after[:, 0], after[:, 1], 1)[0]) if len(after) >= 3 else float("nan")
    )
    report = {
        "rate_hz": args.rate,
        "duration_s": args.duration,
        "warmup_s": args.warmup,
        "rss_baseline_mb": round(float(after[0, 1]), 2),
        "rss_end_mb": round(float(after[-1, 1]), 2),
        "rss_max_mb": round(float(after[:, 1].max()), 2),
        "growth_mb": round(float(after[-1, 1] - after[0, 1]), 2),
        "slope_mb_per_10min": round(slope_per_s * 600, 2),
        "sigterm_to_exit_s": round(stop_s, 3),
        "exit_status": proc.returncode,
        "sd_notify": counts,
        "summary": stderr_tail,
    }
    report["recording"] = inspect_recording(recording)
    report["target_met"] = (
        report["growth_mb"] < 5.0 and stop_s < 1.0 and report["recording"]["finalized"]
    )
    print(json.dumps(report, indent=2))
    if args.keep:
        print(f"recording kept: {recording}", file=sys.stderr)
    else:
        recording.unlink(missing_ok=True)
    return 0 if report["target_met"] else 1


def inspect_recording(path: Path) -> dict:
    from mcap.reader import make_reader

    info: dict = {"bytes": path.stat().st_size if path.exists() else 0, "finalized": False}
    try:
        with open(path, "rb") as fh:
            summary = make_reader(fh).get_summary()
    except Exception as exc:  # report, do not crash: the point is to see it
        info["error"] = f"{type(exc).__name__}: {exc}"
        return info
    if summary is not None and summary.statistics is not None:
        info["finalized"] = True
        info["messages"] = {
            summary.channels[c].topic: n
            for c, n in summary.statistics.channel_message_counts.items()
        }
    return info


if __name__ == "__main__":
    sys.exit(main())
