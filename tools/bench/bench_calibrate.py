"""Benchmark: calibrate from 1000 acquisitions (target: <= 10 s including echo extraction).

    python -m tools.bench.bench_calibrate [--n 1000]

Uses the vendored recordings (z = 90 mm excluded), repeated to the requested count.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from spiel_edge.calibrate import calibrate_echoes, extract_echoes
from spiel_edge.data import load_subset
from spiel_edge.profile.schema import load_profile


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--n", type=int, default=1000)
    args = ap.parse_args()
    data = load_subset()
    keep = np.flatnonzero(data.truth_mm[:, 2] != 90.0)
    idx = np.resize(keep, args.n)
    profile = load_profile("spiel-icra23")
    extract_echoes(profile, data.frames[:2], data.backgrounds[:2])  # numba compile / cache load
    t0 = time.perf_counter()
    cand = extract_echoes(profile, data.frames[idx], data.backgrounds[idx])
    t1 = time.perf_counter()
    cal = calibrate_echoes(cand, data.truth_mm[idx], profile)
    t2 = time.perf_counter()
    print(
        f"{args.n} acquisitions: echo extraction {t1 - t0:.2f} s, solve {t2 - t1:.2f} s, total {t2 - t0:.2f} s "
        f"({len(cal.observations)} echoes, {cal.rounds} rounds)"
    )


if __name__ == "__main__":
    main()
