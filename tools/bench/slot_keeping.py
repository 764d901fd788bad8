"""Boards in different processes keeping their trigger slots on the shared clock (``run
--slot``, docs/robot.md).

    python -m tools.bench.slot_keeping [--frames 1200] [--robot virtual-4] [--load N] [--free]
        [--no-start-at]

Starts one ``spiel-edge run --port <board's sim port> --slot ROBOT:BOARD`` process per board
of the robot at once (as if each were on its own computer; here they share this computer's
clock), each writing its records. Per board, from the records' ``stamp_host`` (the pulse on
the host's Unix clock, TIME_SYNC) after the first 80 acquisitions: the phase against its slot
(median and p95 of its magnitude, the share within the robot's sync margin) and the restarts
its process reported. Across boards: the share of acquisitions whose window another board's
pulse reached (``Schedule.hears`` on the measured pulses, without the marker's margin for clock
uncertainty). ``--load
N`` runs N busy processes beside them; ``--free``: the same processes without ``--slot`` (each
stream started when its process is ready, at the robot's rate), for comparison;
``--no-start-at``: boards without START_AT (``start_at=0``), each start sent at its slot's
moment instead of named in the board's clock. Prints one JSON object.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from spiel_edge.robot.description import load_robot
from spiel_edge.robot.schedule import Schedule
from spiel_edge.robot.slot_keeper import SlotKeeper

SKIP = 80  # acquisitions per board before the figures: the starts settle


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--robot", default="virtual-4")
    ap.add_argument("--frames", type=int, default=1200, help="acquisitions per board")
    ap.add_argument("--load", type=int, default=0, help="busy processes beside the boards'")
    ap.add_argument("--free", action="store_true", help="without --slot, for comparison")
    ap.add_argument("--no-start-at", action="store_true", help="boards without START_AT")
    args = ap.parse_args(argv)
    robot = load_robot(args.robot)
    busy = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(args.load)]
    try:
        pulses, restarts = _run(args, robot)
    finally:
        for p in busy:
            p.kill()
            p.wait()
    figures = _figures(robot, pulses, restarts)
    print(
        json.dumps(
            {
                **figures,
                "slotted": not args.free,
                "start_at": not args.no_start_at,
                "load_processes": args.load,
            }
        )
    )


def _run(args, robot) -> tuple[dict[str, np.ndarray], dict[str, int]]:
    exe = [sys.executable, "-m", "spiel_edge.cli", "run"]
    with tempfile.TemporaryDirectory() as tmp:
        procs = {}
        for b in robot.boards:
            out = Path(tmp) / f"{b.name}.ndjson"
            timing = ["--slot", f"{args.robot}:{b.name}"]
            if args.free:
                timing = ["--rate", f"{1000.0 / robot.trigger.period_ms:g}"]
            port = b.port
            if args.no_start_at:
                port += ("&" if "?" in port else "?") + "start_at=0"
            cmd = [*exe, "--port", port, *timing, "--frames", str(args.frames), "-o", out]
            procs[b.name] = (subprocess.Popen(cmd, stderr=subprocess.PIPE, text=True), out)
        pulses, restarts = {}, {}
        for name, (proc, out) in procs.items():
            _, err = proc.communicate(timeout=600)
            line = next((x for x in err.splitlines() if x.startswith("slot: ")), "slot: -1 ")
            restarts[name] = int(line.split()[1])
            stamps = [json.loads(x).get("stamp_host") for x in out.read_text().splitlines()]
            pulses[name] = np.array([s for s in stamps if s is not None][SKIP:])
    return pulses, restarts


def _figures(robot, pulses: dict[str, np.ndarray], restarts: dict[str, int]) -> dict:
    schedule = Schedule.from_robot(robot)
    margin_ms = schedule.margin_s * 1e3
    boards = {}
    for b in robot.boards:
        keeper = SlotKeeper.from_robot(robot, b.name)
        phase = np.abs([keeper.phase_error(t) for t in pulses[b.name]]) * 1e3
        boards[b.name] = {
            "acquisitions": int(phase.size),
            "restarts": restarts[b.name],
            "phase_ms_median": round(float(np.median(phase)), 3) if phase.size else None,
            "phase_ms_p95": round(float(np.percentile(phase, 95)), 3) if phase.size else None,
            "within_margin": round(float(np.mean(phase <= margin_ms)), 4) if phase.size else None,
        }
    reached = total = 0
    for name, own in pulses.items():
        others = np.sort(np.concatenate([p for n, p in pulses.items() if n != name]))
        for t in own:  # another board's pulse within this one's window (or its guard before)
            lo = np.searchsorted(others, t - schedule.guard_s)
            hi = np.searchsorted(others, t + schedule.window_s, "right")
            # the measured pulses: no margin for clock uncertainty on top (the marker adds it)
            reached += any(schedule.hears(t, u, margin_s=0.0) for u in others[lo:hi])
            total += 1
    return {
        "boards": boards,
        "margin_ms": margin_ms,
        "acquisitions_reached_by_another_pulse": round(reached / max(total, 1), 4),
    }


if __name__ == "__main__":
    os.environ.setdefault("PYTHONUNBUFFERED", "1")
    main()
