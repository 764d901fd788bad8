"""Time sync figures (docs/firmware.md, protocol version 2).

    python tools/bench/clock_sync.py                       # 10 simulated minutes, +-200 ppm, 1 ms jitter
    python tools/bench/clock_sync.py --seeds 8 --reset-at 300
    python tools/bench/clock_sync.py --real-time 60        # a live session against sim:// in real time

The simulated run drives the virtual board on a virtual clock through the real codec and
estimator (tools/bench/clock_model.py): ten minutes of board time in about ten seconds.
The real-time run opens a DeviceSession on ``sim://?drift_ppm=..&jitter_us=..``, streams, and
compares every acquisition's ``stamp_host`` with the host time the board really sampled it at.
Prints one JSON object per run.
"""

from __future__ import annotations

import argparse
import json
import threading
import time

import numpy as np


def real_time(seconds: float, drift_ppm: float, jitter_us: float, rate_hz: float) -> dict:
    from spiel_edge.device import DeviceSession
    from spiel_edge.sim.protocol_sim import device_for_url

    url = f"sim://clocktool?scene=replay&drift_ppm={drift_ppm:g}&jitter_us={jitter_us:g}"
    wall_minus_mono = time.time() - time.monotonic()
    errors, bounds = [], []
    with DeviceSession(url) as dev:
        board = device_for_url(url).board
        dev.start_stream(rate_hz=rate_hz)
        end = time.monotonic() + seconds
        for acq in dev.acquisitions(threading.Event()):
            if acq.stamp_host is not None:
                truth = board._boot_time + acq.timestamp_us / (1e6 + board.drift_ppm)
                errors.append(abs(acq.stamp_host - (truth + wall_minus_mono)) * 1e6)
                bounds.append(acq.stamp_uncertainty_us)
            if time.monotonic() > end:
                break
        counts = dev.counts()
    err = np.array(errors)
    return {
        "mode": "real-time",
        "seconds": seconds,
        "drift_ppm": drift_ppm,
        "jitter_us": jitter_us,
        "acquisitions": int(err.size),
        "p50_us": round(float(np.median(err)), 1),
        "p95_us": round(float(np.percentile(err, 95)), 1),
        "within_uncertainty": round(float(np.mean(err <= np.array(bounds))), 4),
        "sync_exchanges": counts["sync_exchanges"],
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--duration", type=float, default=600.0, help="simulated seconds")
    parser.add_argument("--drift-ppm", type=float, default=200.0)
    parser.add_argument("--jitter-us", type=float, default=1000.0)
    parser.add_argument("--reset-at", type=float, default=300.0, help="board reset (s); <0: none")
    parser.add_argument("--seeds", type=int, default=2, help="runs, alternating +-drift")
    parser.add_argument("--real-time", type=float, default=0.0, help="seconds of a live session")
    parser.add_argument("--rate-hz", type=float, default=30.0)
    args = parser.parse_args()
    if args.real_time:
        print(json.dumps(real_time(args.real_time, args.drift_ppm, args.jitter_us, args.rate_hz)))
        return
    from tools.bench.clock_model import simulate

    for seed in range(args.seeds):
        drift = args.drift_ppm if seed % 2 == 0 else -args.drift_ppm
        started = time.perf_counter()
        r = simulate(
            duration_s=args.duration,
            drift_ppm=drift,
            jitter_us=args.jitter_us,
            rate_hz=args.rate_hz,
            reset_at_s=args.reset_at if args.reset_at >= 0 else None,
            seed=seed,
        )
        out = {"mode": "simulated", "seed": seed, "drift_ppm": drift, **r.summary()}
        out["wall_s"] = round(time.perf_counter() - started, 1)
        print(json.dumps(out))


if __name__ == "__main__":
    main()
