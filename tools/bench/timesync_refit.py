"""CPU of one TIME_SYNC exchange's refit (docs/first-start.md, "Round 4", the CPU at 50/s).

    python -m tools.bench.timesync_refit [REPEATS]

``TimeSyncEstimator.add`` over 700 simulated exchanges (0.1 s apart, 0.3-1 ms round trips,
100 ppm drift), thread time per call: the median over exchanges 20-64 (the window filling,
the session's fast phase) and over 560-700 (a full window of 512); the best of REPEATS runs.
"""

import json
import os
import random
import statistics
import sys
import time

from spiel_edge.device.timesync import TimeSyncEstimator


def refit_us(repeats: int = 3) -> dict:
    filling, full = [], []
    for _ in range(repeats):
        estimator, rng, t, times = TimeSyncEstimator(), random.Random(1), 1e6, []
        for _ in range(700):
            t += 100_000.0
            rtt = 300.0 + rng.random() * 700.0
            board = (t + rtt * rng.random()) * 1.0001 + 5e6
            t0 = time.thread_time()
            estimator.add(t, t + rtt, board, 7)
            times.append(time.thread_time() - t0)
        filling.append(statistics.median(times[20:64]))
        full.append(statistics.median(times[560:700]))
    return {
        "window_20_64_us": round(min(filling) * 1e6),
        "window_512_us": round(min(full) * 1e6),
        "load": [round(v, 2) for v in os.getloadavg()],
    }


if __name__ == "__main__":
    print(json.dumps(refit_us(int(sys.argv[1]) if len(sys.argv) > 1 else 3)))
