"""Benchmark of the live path against the live-link targets; one JSON object on stdout.

    python -m tools.bench.bench_live [--acquisitions 3000] [--rate 500]

- pty: ``spiel-edge simulate --pty`` in its own process, the pipeline here reading the pty at
  ``--rate`` (target >= 500/s with no drops) and at rate 0 (as fast as the link allows);
  latency from an acquisition's last byte read to its record written (target median <= 2 ms).
- ber: the in-process virtual board with ber=1e-4: damaged acquisitions the board made vs
  those the host counted, undamaged ones not processed (target 0).
- unplug: 20 unplug/replug cycles, seconds from the board's return to its first acquisition
  (target <= 2 s).
"""

from __future__ import annotations

import argparse
import io
import json
import select
import subprocess
import sys
import threading
import time

import numpy as np

from spiel_edge.device import DeviceSession
from spiel_edge.outputs.sink import Sink
from spiel_edge.pipeline.factory import build_pipeline
from spiel_edge.profile.schema import load_profile
from spiel_edge.runtime.loop import LiveRunner, warm_up
from spiel_edge.sim.protocol_sim import device_for_url

CLI = [
    sys.executable,
    "-c",
    "import sys; from spiel_edge.cli import main; sys.exit(main(sys.argv[1:]))",
]


class NullSink(Sink):
    def write(self, record: dict) -> None:
        json.dumps(record, separators=(",", ":"))  # the cost of an NDJSON line, without the I/O


def pty_run(pipeline, n: int, rate: float) -> dict:
    server = subprocess.Popen(
        [*CLI, "simulate", "--pty"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )
    try:
        select.select([server.stdout], [], [], 30)
        path = server.stdout.readline().strip()
        session = DeviceSession(path)
        runner = LiveRunner(session, pipeline, NullSink(), keep_latencies=True)
        with session:
            session.start_stream(rate_hz=rate, n_samples=pipeline.profile.acquisition.n_samples)
            t0 = time.perf_counter()
            runner.run(threading.Event(), frames=n)
            seconds = time.perf_counter() - t0
            runner.refresh_device_counters()
            counts = session.counts()
    finally:
        server.terminate()
        server.wait(5)
    lat = np.array(runner.stats.all_latencies_us) / 1e3
    return {
        "port": path,
        "rate_hz": rate,
        "acquisitions": n,
        "seconds": round(seconds, 3),
        "achieved_per_s": round(n / seconds, 1),
        "lost": counts["lost"],
        "overruns": counts["overruns"],
        "latency_ms": {
            "median": round(float(np.median(lat)), 3),
            "p95": round(float(np.percentile(lat, 95)), 3),
            "max": round(float(lat.max()), 3),
        },
    }


def ber_run(n: int) -> dict:
    url = "sim://bench-ber?ber=1e-4&seed=7"
    with DeviceSession(url) as session:
        session.start_stream(rate_hz=0)
        delivered = set()
        for acq in session.acquisitions():
            delivered.add(acq.index)
            if len(delivered) >= n:
                break
        delivered |= {a.index for a in session.assembly.ready}
        counts = session.counts()
    last = max(delivered)
    damaged = {k for k in device_for_url(url).faults.stats.damaged if k <= last}
    return {
        "acquisitions_sent": last + 1,
        "damaged_by_board": len(damaged),
        "counted_lost_by_host": counts["lost"],
        "undamaged_not_processed": len(set(range(last + 1)) - delivered - damaged),
        "damaged_processed": len(delivered & damaged),
        "crc_errors": counts["crc_errors"],
    }


def unplug_run(cycles: int = 20) -> dict:
    url = f"sim://bench-unplug?unplug_after=50&unplug_ms=100&unplug_count={cycles}&scene=model"
    device = device_for_url(url)
    delays, previous = [], None
    with DeviceSession(url) as session:
        session.start_stream(rate_hz=500)
        for acq in session.acquisitions():
            if acq.index == 0 and previous is not None:
                delays.append(time.monotonic() - device.plug_times[-1])
            previous = acq.index
            if session.counters.reconnects == cycles and acq.index >= 5:
                break
    return {
        "cycles": cycles,
        "reconnect_s": {
            "median": round(float(np.median(delays)), 3),
            "max": round(float(np.max(delays)), 3),
        },
    }


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--acquisitions", type=int, default=3000)
    ap.add_argument("--rate", type=float, default=500.0)
    args = ap.parse_args()
    pipeline = build_pipeline(load_profile())
    warm_up(pipeline)
    result = {
        "pipeline": type(pipeline.associator).__name__,
        "pty_at_rate": pty_run(pipeline, args.acquisitions, args.rate),
        "pty_max_rate": pty_run(pipeline, args.acquisitions, 0.0),
        "ber_1e-4": ber_run(args.acquisitions),
        "unplug": unplug_run(),
    }
    out = io.StringIO()
    json.dump(result, out)
    print(out.getvalue())


if __name__ == "__main__":
    main()
