"""Coverage of the stated stamp uncertainty over drift, jitter and bad clocks (issue 43).

    python -m tools.bench.clock_faults                 # the sweep: 120 simulated s per run
    python -m tools.bench.clock_faults --seeds 3 --duration 300
    python -m tools.bench.clock_faults --drift-ppm 20000 --fault wrap2s   # one run

Deterministic simulated clocks (spiel_edge/measure/clock_faults.py): drift 0 to +-20,000 ppm
at 0.1, 1 and 5 ms of jitter, then each fault at +-10,000 ppm and 1 ms. Prints one JSON
object: every run, and the summary (the worst coverage, stamps backwards, log messages).
"""

from __future__ import annotations

import argparse
import json

from spiel_edge.measure.clock_faults import FAULTS, run, sweep


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--duration", type=float, default=120.0, help="simulated s per run")
    parser.add_argument("--seeds", type=int, default=1)
    parser.add_argument("--drift-ppm", type=float, default=None, help="one run at this drift")
    parser.add_argument("--jitter-us", type=float, default=1000.0)
    parser.add_argument("--fault", choices=FAULTS, default="")
    args = parser.parse_args()
    if args.drift_ppm is not None or args.fault:
        runs = [
            run(
                drift_ppm=args.drift_ppm or 0.0,
                jitter_us=args.jitter_us,
                fault=args.fault,
                duration_s=args.duration,
                seed=s,
            )
            for s in range(args.seeds)
        ]
    else:
        runs = sweep(duration_s=args.duration, seeds=args.seeds)
    drift = [r for r in runs if r["fault"] == "none"]
    faults = [r for r in runs if r["fault"] != "none"]
    summary = {
        "runs": len(runs),
        "stamps": sum(r["stamps"] for r in runs),
        "worst_within_uncertainty_drift": min(
            (r["within_uncertainty"] for r in drift), default=None
        ),
        "worst_within_uncertainty_fault": min(
            (r["within_uncertainty"] for r in faults), default=None
        ),
        "stamps_backwards": sum(r["backwards"] for r in runs),
        "most_log_messages": max(r["log_messages"] for r in runs),
        "met": all(r["within_uncertainty"] >= 0.95 and r["backwards"] == 0 for r in runs),
    }
    print(json.dumps({"summary": summary, "runs": runs}, indent=1))


if __name__ == "__main__":
    main()
