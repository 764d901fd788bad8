"""Train the learned echo association (PaCE paper, section IV) and export it to ONNX.

    python -m tools.train.train_association [--data DIR] [--seed 0] [--out spiel_edge/models]

writes association.onnx, association_reference.json and the model card association.md
(with the ablation of ``tools.train.ablation_association``) into ``--out``. The data, network and
training steps are in ``tools.train.association_model`` (its docstring: data, split, network, loss).
The dataset defaults to ``../shared/datasets/spiel-icra23`` beside the checkout, or
``$SPIEL_DATASET``.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import logging
import sys
import time
from pathlib import Path

from spiel_edge.pipeline.stages.features import FEATURE_NAMES
from spiel_edge.profile.schema import load_profile
from tools.train import ablation_association as ablation
from tools.train.association_model import (
    DEFAULT_DATA,
    DEFAULT_OUT,
    SPLIT_SALT,
    export_onnx,
    load_samples,
    pick_guard,
    pick_score_weight,
    reference_inputs,
    reference_outputs,
    split_by_position,
    train,
)

log = logging.getLogger("train_association")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=DEFAULT_DATA)
    ap.add_argument("--profile", default="spiel-icra23")
    ap.add_argument("--seed", type=int, default=0, help="torch initialisation and shuffling")
    ap.add_argument(
        "--split-salt", default=SPLIT_SALT, help="which (x, y) positions go to validation"
    )
    ap.add_argument("--val-fraction", type=float, default=0.3)
    ap.add_argument("--out", type=Path, default=DEFAULT_OUT)
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    t0 = time.time()
    profile = load_profile(args.profile)
    samples = load_samples(args.data, profile)
    train_set, val_set = split_by_position(samples, args.val_fraction, args.split_salt)
    log.info("%d acquisitions: %d train, %d validation", len(samples), len(train_set), len(val_set))
    net, history = train(train_set, val_set, seed=args.seed)
    threshold, slack = pick_guard(profile, net, train_set)
    weight = pick_score_weight(profile, net, train_set)
    metadata = {
        "spiel.score_weight_mm": f"{weight:.6g}",
        "spiel.feature_names": ",".join(FEATURE_NAMES),
        "spiel.distance_threshold": f"{threshold:.6g}",
        "spiel.cost_slack_mm": f"{slack:.6g}",
        "spiel.profile": profile.name,
        "spiel.seed": str(args.seed),
        "spiel.epochs": str(len(history)),
    }
    blob = export_onnx(net, metadata)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "association.onnx").write_bytes(blob)
    ref = reference_outputs(net, reference_inputs(train_set, seed=args.seed))
    ref["onnx_sha256"] = hashlib.sha256(blob).hexdigest()
    (args.out / "association_reference.json").write_text(json.dumps(ref, indent=1) + "\n")
    results = ablation.run(profile, train_set, val_set, net, args.seed, threshold, slack, weight)
    results["onnx prior (onnxruntime, shipped)"] = ablation.evaluate_runtime(
        profile, val_set, args.out / "association.onnx"
    )
    ablation.write_card(
        args.out / "association.md",
        profile,
        results,
        {
            "train": len(train_set),
            "val": len(val_set),
            "val_xy": sorted({s.xy for s in val_set}),
            "epochs": len(history),
            "threshold": threshold,
            "slack": slack,
            "weight": weight,
            "seed": args.seed,
            "salt": args.split_salt,
            "sha256": ref["onnx_sha256"],
            "history": history,
        },
    )
    summary = {
        "epochs": len(history),
        "best_val_loss": min(v for _, v in history),
        "distance_threshold": threshold,
        "cost_slack_mm": slack,
        "score_weight_mm": weight,
        "sha256": ref["onnx_sha256"],
        "seconds": round(time.time() - t0, 1),
    }
    print(json.dumps(summary, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
