"""The virtual robot's figures (docs/robot.md): cross-talk with and without the schedule,
track ids across fields of view, tracked error against one board's own.

    python -m tools.bench.robot_eval [--cycles 2000] [--movers 5] [--seed 0] [--robot virtual-4]
        [--mode scheduled|free|both] [--keep-marked] [--oracle]

Offline in virtual time (sim/robot.py's simulate: each board's clock with offset and
+-200 ppm drift, link latency), every acquisition through the pipeline (--max-targets 4, no
learned ToA correction: the echo model's envelope), then the host side and the fusion of
spiel_edge/robot. ``--oracle`` adds ``oracle_association``: the same fused targets associated
to the movers by the truth, one track per mover with the same filter and coasting (what a
perfect association would keep; robot/score.py). Prints one JSON object per mode.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time

from spiel_edge.pipeline.factory import build_pipeline
from spiel_edge.profile.schema import load_profile
from spiel_edge.robot.description import load_robot
from spiel_edge.robot.virtual_run import run_virtual_robot
from spiel_edge.sim.robot import RobotWorld


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--robot", default="virtual-4")
    ap.add_argument("--cycles", type=int, default=2000, help="acquisitions per board")
    ap.add_argument("--movers", type=int, default=5)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--max-targets", type=int, default=4)
    ap.add_argument("--mode", choices=["scheduled", "free", "both"], default="both")
    ap.add_argument("--keep-marked", action="store_true", help="fuse marked acquisitions too")
    ap.add_argument(
        "--track", action="append", default=[], metavar="KEY=VALUE", help="[track] override"
    )
    ap.add_argument("--no-ghosts", action="store_true", help="skip the clean-frame comparison")
    ap.add_argument("--oracle", action="store_true", help="also the truth's association")
    args = ap.parse_args(argv)
    robot = load_robot(args.robot)
    profile = load_profile(robot.boards[0].profile)
    pipeline = build_pipeline(profile, None, "none")
    pipeline.set_max_targets(args.max_targets)
    spec = robot.track_spec()
    for item in args.track:
        key, _, value = item.partition("=")
        kind = type(getattr(spec, key))
        spec = dataclasses.replace(
            spec, **{key: kind(float(value)) if kind is int else kind(value)}
        )
    modes = ["free", "scheduled"] if args.mode == "both" else [args.mode]
    for mode in modes:
        world = RobotWorld(robot, movers=args.movers, seed=args.seed)
        t = time.time()
        figs, _ = run_virtual_robot(
            world,
            pipeline,
            cycles=args.cycles,
            scheduled=mode == "scheduled",
            seed=args.seed,
            ghosts=not args.no_ghosts,
            drop_marked=not args.keep_marked,
            spec=spec,
            oracle=args.oracle,
        )
        out = {"mode": mode, "seed": args.seed, "movers": args.movers, **figs.summary()}
        out["wall_s"] = round(time.time() - t, 1)
        print(json.dumps(out), flush=True)


if __name__ == "__main__":
    main()
