"""The virtual robot's figures (docs/robot.md): cross-talk with and without the schedule,
track ids across fields of view, tracked error against one board's own.

    python -m tools.bench.robot_eval [--cycles 2000] [--movers 5] [--seed 0 | --seeds 0,2,3,5-11]
        [--robot virtual-4] [--mode scheduled|free|both] [--keep-marked] [--oracle]

Offline in virtual time (sim/robot.py's simulate: each board's clock with offset and
+-200 ppm drift, link latency), every acquisition through the pipeline (--max-targets 4, no
learned ToA correction: the echo model's envelope), then the host side and the fusion of
spiel_edge/robot. ``--oracle`` adds ``oracle_association``: the same fused targets associated
to the movers by the truth, one track per mover with the same filter and coasting (what a
perfect association would keep; tools/bench/robot_score.py). Prints one JSON object per seed and mode;
with ``--seeds``, then one ``pooled`` object per mode: the crossings kept over every seed with
Wilson's 95 % interval, the like-for-like tracked errors weighted by their pairs, and the
ranges of the marked and ghost shares.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import time

from spiel_edge.pipeline.factory import build_pipeline
from spiel_edge.profile.schema import load_profile
from spiel_edge.robot.description import load_robot
from spiel_edge.sim.robot import RobotWorld
from tools.bench.virtual_robot import run_virtual_robot


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--robot", default="virtual-4")
    ap.add_argument("--cycles", type=int, default=2000, help="acquisitions per board")
    ap.add_argument("--movers", type=int, default=5)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--seeds", type=_seed_list, help="several seeds, e.g. 0,2,3,5-11: pooled too")
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
    runs: dict[str, list[dict]] = {mode: [] for mode in modes}
    for seed in args.seeds or [args.seed]:
        for mode in modes:
            world = RobotWorld(robot, movers=args.movers, seed=seed)
            t = time.time()
            figs, _ = run_virtual_robot(
                world,
                pipeline,
                cycles=args.cycles,
                scheduled=mode == "scheduled",
                seed=seed,
                ghosts=not args.no_ghosts,
                drop_marked=not args.keep_marked,
                spec=spec,
                oracle=args.oracle,
            )
            out = {"mode": mode, "seed": seed, "movers": args.movers, **figs.summary()}
            out["wall_s"] = round(time.time() - t, 1)
            runs[mode].append(out)
            print(json.dumps(out), flush=True)
    if args.seeds:
        for mode, outs in runs.items():
            print(json.dumps({"pooled": pooled(outs), "mode": mode}), flush=True)


def _seed_list(text: str) -> list[int]:
    seeds: list[int] = []
    for part in text.split(","):
        lo, _, hi = part.partition("-")
        seeds += list(range(int(lo), int(hi or lo) + 1))
    if not seeds:
        raise argparse.ArgumentTypeError("no seed")
    return seeds


def wilson(kept: int, n: int, z: float = 1.96) -> tuple[float, float]:
    """Wilson's score interval of a share kept/n (about 95 % at z = 1.96)."""
    if n == 0:
        return (0.0, 1.0)
    p = kept / n
    d = 1 + z * z / n
    centre = (p + z * z / (2 * n)) / d
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / d
    return (round(centre - half, 4), round(centre + half, 4))


def _crossings(c: list[dict]) -> dict:
    kept = sum(x["kept"] for x in c)
    tracked = sum(x["crossings"] - x["untracked"] for x in c)
    share = round(kept / tracked, 4) if tracked else None
    return {"kept": kept, "tracked": tracked, "share": share, "interval": wilson(kept, tracked)}


def pooled(outs: list[dict]) -> dict:
    """The figures of several seeds' runs (one mode) pooled."""
    result = {
        "seeds": [o["seed"] for o in outs],
        "crossings": _crossings([o["crossings"] for o in outs]),
    }
    if all("oracle_association" in o for o in outs):
        result["oracle_crossings"] = _crossings(
            [o["oracle_association"]["crossings"] for o in outs]
        )
    for key in ("own", "same_track_settings"):
        pairs = [o["paired_error_mm"][key] for o in outs]
        n = sum(p["n"] for p in pairs)
        if n:
            result[f"paired_{key}_mm"] = {
                "n": n,
                "fused_mean": round(sum(p["n"] * p["fused_mean"] for p in pairs) / n, 2),
                "own_mean": round(sum(p["n"] * p["own_mean"] for p in pairs) / n, 2),
            }
    for key in ("marked_share", "ghost_share", "ghost_unmarked_share"):
        values = [o[key] for o in outs]
        result[key] = [min(values), max(values)]
    return result


if __name__ == "__main__":
    main()
