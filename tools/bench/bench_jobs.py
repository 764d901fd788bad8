"""Wall and CPU time of ``spiel-edge replay --jobs N`` on a folder, runs alternating.

CPU time counts every process the command starts, the fork server's workers too (this tool
makes itself a child subreaper, so orphaned descendants are reaped here). Linux only.

    python -m tools.bench.bench_jobs FOLDER --background BG --jobs 1 2 --rounds 3
"""

from __future__ import annotations

import argparse
import ctypes
import json
import os
import resource
import statistics
import subprocess
import sys
import time

PR_SET_CHILD_SUBREAPER = 36


def timed_run(argv: list[str]) -> tuple[float, float, float]:
    """(wall s, user s, system s) of ``argv`` and all its descendants."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    start = time.perf_counter()
    proc = subprocess.run(argv, stdout=subprocess.DEVNULL, check=False)
    while True:  # orphans (the fork server) come to us: wait for all of them
        try:
            os.wait()
        except ChildProcessError:
            break
    wall = time.perf_counter() - start
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if proc.returncode not in (0, 1):
        raise SystemExit(f"{' '.join(argv)}: exit status {proc.returncode}")
    return wall, after.ru_utime - before.ru_utime, after.ru_stime - before.ru_stime


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("folder")
    parser.add_argument("--background")
    parser.add_argument("--jobs", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--rounds", type=int, default=3)
    args = parser.parse_args()
    libc = ctypes.CDLL(None, use_errno=True)
    if libc.prctl(PR_SET_CHILD_SUBREAPER, 1, 0, 0, 0) != 0:
        raise SystemExit("prctl(PR_SET_CHILD_SUBREAPER) failed")
    base = [sys.executable, "-m", "spiel_edge.cli", "replay", args.folder]
    if args.background:
        base += ["--background", args.background]
    runs: dict[int, list[tuple[float, float, float]]] = {j: [] for j in args.jobs}
    for _ in range(args.rounds):
        for jobs in args.jobs:  # alternating, so the machine's load falls on both alike
            runs[jobs].append(timed_run([*base, "--jobs", str(jobs)]))
    summary = {
        str(jobs): {
            "wall_s": [round(r[0], 2) for r in rs],
            "user_s": [round(r[1], 2) for r in rs],
            "sys_s": [round(r[2], 2) for r in rs],
            "median_wall_s": round(statistics.median(r[0] for r in rs), 2),
            "median_user_s": round(statistics.median(r[1] for r in rs), 2),
        }
        for jobs, rs in runs.items()
    }
    print(json.dumps(summary, indent=1))


if __name__ == "__main__":
    main()
