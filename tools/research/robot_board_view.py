"""What one board of the virtual robot reports about one mover, acquisition by acquisition
(docs/robot.md, "Crossings": why a mover goes unreported in the gap between two fields of view).

    python -m tools.research.robot_board_view --seed 0 --board right --mover 3 --first 840 --last 870
    python -m tools.research.robot_board_view --crossings 0,1,2,3,4,5

The same world, schedule and pipeline as ``tools.bench.robot_eval --mode scheduled``. Per
acquisition of ``--board``: the mover's range and angle off the board's facing, the nearest
other mover's range difference (two reflectors at one range from a board echo together on
every channel), and the board's targets (range, distance from the mover). One line each.

``--crossings SEEDS``: over whole runs (2000 cycles) of those seeds, the crossings tracked before
(tools/bench/robot_score.py) split by whether another mover stood within ``RANGE_MM`` in range of the mover,
seen from the board it enters, for at least half of the ``LOOK`` cycles after it; kept and
failed in each group. One JSON object.
"""

from __future__ import annotations

import argparse
import json

import numpy as np

from spiel_edge.pipeline.factory import build_pipeline
from spiel_edge.profile.schema import load_profile
from spiel_edge.robot.description import load_robot
from spiel_edge.robot.fusion import reports_targets
from spiel_edge.sim.robot import RobotWorld
from tools.bench import robot_score as score
from tools.bench.robot_offline import simulate
from tools.bench.virtual_robot import run_virtual_robot

RANGE_MM = 15.0  # two echoes closer than about two samples (7.8 mm each) merge


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--robot", default="virtual-4")
    ap.add_argument("--movers", type=int, default=5)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--board", default="right")
    ap.add_argument("--mover", type=int, default=0)
    ap.add_argument("--first", type=int, default=0, help="first acquisition of the board")
    ap.add_argument("--last", type=int, default=30, help="last acquisition of the board")
    ap.add_argument("--crossings", metavar="SEEDS", help="comma-separated seeds: the summary")
    args = ap.parse_args(argv)
    robot = load_robot(args.robot)
    pipeline = build_pipeline(load_profile(robot.boards[0].profile), None, "none")
    pipeline.set_max_targets(4)
    if args.crossings:
        seeds = [int(x) for x in args.crossings.split(",")]
        print(json.dumps(crossings_by_range(robot, pipeline, args.movers, seeds)))
        return
    world = RobotWorld(robot, movers=args.movers, seed=args.seed)
    if args.board not in world.names:
        ap.error(f"--board: one of {', '.join(world.names)}")
    if not 0 <= args.mover < args.movers:
        ap.error(f"--mover: 0 to {args.movers - 1}")
    acqs, _, _ = simulate(world, cycles=args.last + 2, scheduled=True, seed=args.seed)
    for a in acqs:
        if a.board != args.board or not args.first <= a.index <= args.last:
            continue
        res = pipeline.process(
            a.frame.samples.astype(np.float64), a.frame.background.astype(np.float64)
        )
        truth = a.frame.truth_board_mm  # board frame: z is the facing
        ranges = np.linalg.norm(truth, axis=1)
        mine = truth[args.mover]
        off_axis = np.degrees(np.arccos(np.clip(mine[2] / ranges[args.mover], -1.0, 1.0)))
        others = np.delete(ranges, args.mover)
        gap = float(np.min(np.abs(others - ranges[args.mover]))) if len(others) else float("nan")
        targets = [
            (round(float(np.linalg.norm(p))), round(float(np.linalg.norm(p - mine))))
            for p, _, _ in reports_targets(res)
        ]
        print(
            f"{a.index:5d}  mover at {ranges[args.mover]:4.0f} mm, {off_axis:3.0f} deg off; "
            f"another mover {gap:4.0f} mm apart in range; targets (range, off the mover) {targets}"
        )


def crossings_by_range(robot, pipeline, movers: int, seeds: list[int]) -> dict:
    out = {"seeds": seeds, "range_mm": RANGE_MM}
    for group in ("near_in_range", "clear"):
        out[group] = {"kept": 0, "failed": 0}
    for seed in seeds:
        world = RobotWorld(robot, movers=movers, seed=seed)
        figs, records = run_virtual_robot(
            world,
            pipeline,
            cycles=2000,
            scheduled=True,
            seed=seed,
            ghosts=False,
            spec=robot.track_spec(),
        )
        truths = figs.truths
        ids, _ = score.coverage(records, truths)
        primary = score.primary_boards(world, truths)
        for c, j in score.crossings(primary):
            before, after = score.crossing_outcome(ids, c, j)
            if before is None:
                continue  # untracked before: no id to keep
            origin = world.emitters[world.names[primary[c, j]]]
            near = 0
            for k in range(c, min(c + score.LOOK, len(ids))):
                ranges = np.linalg.norm(truths[k] - origin, axis=1)
                near += np.min(np.abs(np.delete(ranges, j) - ranges[j])) < RANGE_MM
            group = "near_in_range" if 2 * near >= score.LOOK else "clear"
            out[group]["kept" if after == before else "failed"] += 1
    return out


if __name__ == "__main__":
    main()
