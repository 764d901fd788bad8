"""Compare the positions of two `spiel-edge run` NDJSON outputs, record by record.

    python -m tools.release.compare_ndjson_positions A.ndjson B.ndjson [--tolerance-mm 0.01]

Used by tools/release/aarch64_smoke.sh (host against emulated arm64). Exit 0 when both files have the
same records (by seq), the same fixes (a position in both or in neither) and every position
(best and per target) agrees within the tolerance; 1 otherwise, naming the first differences.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path


def _positions(record: dict) -> list[list[float] | None]:
    best = record.get("position_mm")
    targets = [t.get("position_mm") for t in record.get("targets") or []]
    return [best, *targets]


def load(path: Path) -> dict[int, list[list[float] | None]]:
    records = {}
    for line in path.read_text(encoding="utf-8").splitlines():
        if line.strip():
            record = json.loads(line)
            records[int(record["seq"])] = _positions(record)
    return records


def compare(a: dict, b: dict, tolerance_mm: float) -> tuple[list[str], float]:
    problems: list[str] = []
    worst = 0.0
    if a.keys() != b.keys():
        problems.append(f"different records: {len(a)} against {len(b)}")
    for seq in sorted(a.keys() & b.keys()):
        if len(a[seq]) != len(b[seq]):
            problems.append(f"seq {seq}: {len(a[seq])} positions against {len(b[seq])}")
            continue
        for pa, pb in zip(a[seq], b[seq], strict=True):
            if (pa is None) != (pb is None):
                problems.append(f"seq {seq}: fix in one output only ({pa} against {pb})")
            elif pa is not None:
                gap = math.dist(pa, pb)
                worst = max(worst, gap)
                if gap > tolerance_mm:
                    problems.append(f"seq {seq}: {pa} against {pb} ({gap:.4f} mm)")
    return problems, worst


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("a", type=Path)
    parser.add_argument("b", type=Path)
    parser.add_argument("--tolerance-mm", type=float, default=0.01)
    args = parser.parse_args(argv)
    a, b = load(args.a), load(args.b)
    problems, worst = compare(a, b, args.tolerance_mm)
    fixes = sum(p is not None for positions in a.values() for p in positions)
    print(f"{len(a)} records, {fixes} positions compared; largest difference {worst:.4f} mm")
    for line in problems[:10]:
        print("  " + line)
    if problems or not a:
        print("positions differ" if problems else "no records", file=sys.stderr)
        return 1
    print(f"positions agree within {args.tolerance_mm} mm")
    return 0


if __name__ == "__main__":
    sys.exit(main())
