"""CPU per board-acquisition of ``run --robot`` against one board's ``run`` (docs/robot.md).

    python -m tools.bench.robot_cpu [--short 100] [--long 500] [--robot virtual-4]

Each command runs twice as a child process, ``--short`` and ``--long`` acquisitions per board
(``--frames``), and the CPU time (user + system, from the children's rusage) of the
difference is divided by the extra board-acquisitions, so start-up (imports, the numba cache,
opening the boards) cancels. Commands, all at the robot's period with ``--max-targets 4``:
one board's ``run --port sim://front?scene=robot...``; ``run --robot`` on a copy of the robot
file with that board only; ``run --robot`` with every board. The virtual boards run inside the
measured process in every case (their scene, with cross-talk when several boards share it, is
part of the figure). Prints one JSON object.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
from pathlib import Path

from spiel_edge.robot import robot_path
from spiel_edge.robot.description import load_robot


def _cpu(cmd: list[str]) -> float:
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)


def _one_board_file(robot_file: Path, name: str, tmp: Path) -> Path:
    """The robot file with only board ``name`` (its [[board]] table kept as written)."""
    text = robot_file.read_text()
    head, *tables = text.split("[[board]]")
    keep = [t for t in tables if f'name = "{name}"' in t]
    path = tmp / "one.toml"
    path.write_text(head + "".join("[[board]]" + t for t in keep))
    return path


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--robot", default="virtual-4")
    ap.add_argument("--short", type=int, default=100)
    ap.add_argument("--long", type=int, default=500)
    args = ap.parse_args(argv)
    path = robot_path(args.robot)
    robot = load_robot(path)
    first = robot.boards[0]
    rate = f"{1000.0 / robot.trigger.period_ms:g}"
    exe = [sys.executable, "-m", "spiel_edge.cli", "run", "--max-targets", "4", "-o", os.devnull]
    extra = args.long - args.short
    out = {"load_before": os.getloadavg()[0]}
    with tempfile.TemporaryDirectory() as tmp:
        one = _one_board_file(path, first.name, Path(tmp))
        cases = {
            "run_one_board": ([*exe, "--port", first.port, "--rate", rate], 1),
            "robot_one_board": ([*exe, "--robot", str(one)], 1),
            "robot_all_boards": ([*exe, "--robot", str(path)], len(robot.boards)),
        }
        for name, (cmd, boards) in cases.items():
            short = _cpu([*cmd, "--frames", str(args.short)])
            long = _cpu([*cmd, "--frames", str(args.long)])
            out[f"{name}_ms_per_board_acquisition"] = round(
                1e3 * (long - short) / (extra * boards), 4
            )
    base = out["run_one_board_ms_per_board_acquisition"]
    out["ratio_robot_all_to_run_one"] = round(
        out["robot_all_boards_ms_per_board_acquisition"] / base, 3
    )
    out["ratio_robot_all_to_robot_one"] = round(
        out["robot_all_boards_ms_per_board_acquisition"]
        / out["robot_one_board_ms_per_board_acquisition"],
        3,
    )
    out["load_after"] = os.getloadavg()[0]
    print(json.dumps(out))


if __name__ == "__main__":
    main()
