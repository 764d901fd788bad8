"""One SHA-256 per live path over its records: a change to how runs are assembled, the same
records? (docs/live-api.md)

    python -m tools.bench.live_records

Runs, each as a child process of this checkout (``PYTHONPATH`` picks another):
``run --port sim://`` (the vendored recordings) and on a model scene of two fixed targets, 300
records at ``--rate 0 --max-targets 4``; ``run --robot`` over the four boards of virtual-4 with
their ports on that fixed scene, 150 fused records. Without tracking, and with the fields that
come from the wall clock left out (host and board times, stamps and their uncertainty,
latency) and a fused record's targets sorted (they come in the order the boards' threads
reported), these records depend on the acquisitions alone: two runs of one checkout give the
same digests, so two checkouts' digests say whether their records are the same. (The movers of
virtual-4's own scene, and tracking, follow the wall clock: no two runs are equal there.)
Prints one JSON object.
"""

from __future__ import annotations

import hashlib
import json
import re
import subprocess
import sys
import tempfile
from pathlib import Path

from spiel_edge.robot import robot_path

CLOCK_FIELDS = {
    "host_time",
    "acquired",
    "latency_ms",
    "device_time_us",
    "stamp_host",
    "stamp_uncertainty_us",
    "stamp_source",
}
SCENE = "scene=model&targets=40,20,180;-60,30,250&seed=2"


def _without_clock(value):
    if isinstance(value, dict):
        return {k: _without_clock(v) for k, v in value.items() if k not in CLOCK_FIELDS}
    if isinstance(value, list):
        return [_without_clock(v) for v in value]
    return value


def _digest(args: list[str], out: Path) -> dict:
    proc = subprocess.run(
        [sys.executable, "-m", "spiel_edge.cli", *args, "-o", str(out)],
        capture_output=True,
        text=True,
        timeout=600,
    )
    if proc.returncode != 0:
        raise RuntimeError(f"spiel-edge {' '.join(args)}: exit {proc.returncode}: {proc.stderr}")
    h = hashlib.sha256()
    lines = out.read_text().splitlines()
    for line in lines:
        record = _without_clock(json.loads(line))
        if "boards" in record:  # fused: targets in the order their boards' reports came
            record["targets"] = sorted(record["targets"], key=lambda t: json.dumps(t))
        h.update(json.dumps(record, sort_keys=True).encode())
    return {"records": len(lines), "sha256": h.hexdigest()}


def static_robot(folder: Path) -> Path:
    """virtual-4 with every board on the fixed model scene."""
    text = robot_path("virtual-4").read_text()
    text = re.sub(r'port = "sim://(\w+)\?[^"]*"', rf'port = "sim://\1?{SCENE}"', text)
    path = folder / "static-4.toml"
    path.write_text(text)
    return path


def main() -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        run = ["run", "--rate", "0", "--frames", "300", "--max-targets", "4", "--no-track"]
        return {
            "run_replay_scene": _digest([*run, "--port", "sim://"], folder / "a.ndjson"),
            "run_model_scene": _digest([*run, "--port", f"sim://?{SCENE}"], folder / "b.ndjson"),
            "run_robot_static_4": _digest(
                ["run", "--robot", str(static_robot(folder)), "--no-track", "--frames", "150"],
                folder / "c.ndjson",
            ),
        }


if __name__ == "__main__":
    print(json.dumps(main()))
