"""Tracking figures on the virtual board's moving targets (docs/tracking.md).

    python -m tools.bench.track_movers [--movers 3] [--seed 0] [--acquisitions 1000] [--max-targets 4]
        [--background scene|none|running]

Prints one JSON object: per true target the share of acquisitions (after the first 20) with a
confirmed track within 40 mm, id switches, tracked vs per-acquisition error.
"""

from __future__ import annotations

import argparse
import json

from spiel_edge.pipeline.factory import build_pipeline
from spiel_edge.profile.schema import load_profile
from tools.bench.track_scene import run_movers


def add_toa_correction(parser: argparse.ArgumentParser) -> None:
    """``--toa-correction``, none by default: the learned correction was fitted to the real
    board's envelope, not the echo model's (docs/virtual-board.md)."""
    parser.add_argument(
        "--toa-correction",
        choices=["auto", "onnx", "none"],
        default="none",
        help="learned ToA correction (default none: fitted to the real board's envelope)",
    )


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--movers", type=int, default=3)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--acquisitions", type=int, default=1000)
    parser.add_argument("--rate", type=float, default=50.0, help="acquisitions per second")
    parser.add_argument("--profile", default="spiel-icra23")
    add_toa_correction(parser)
    parser.add_argument("--max-targets", type=int, default=4, help="targets per acquisition")
    parser.add_argument(
        "--oracle",
        type=float,
        default=None,
        metavar="SIGMA_MM",
        help="targets = truth + noise of this std (5 %% missed): the tracker alone",
    )
    parser.add_argument(
        "--background",
        choices=["scene", "none", "running"],
        default="scene",
        help="the scene's target-free background, none (the profile's stand-in), or the "
        "running estimate",
    )
    args = parser.parse_args(argv)
    pipeline = build_pipeline(load_profile(args.profile), None, args.toa_correction)
    pipeline.set_max_targets(args.max_targets)
    url = f"sim://?scene=model&movers={args.movers}&seed={args.seed}"
    print(
        json.dumps(
            run_movers(
                pipeline,
                url,
                args.acquisitions,
                args.rate,
                oracle_sigma_mm=args.oracle,
                background=args.background,
            )
        )
    )


if __name__ == "__main__":
    main()
