"""Train the learned ToA correction and export it to ONNX, with its model card.

    python -m tools.train.train_toa_correction [--data DIR] [--out spiel_edge/models]

Steps (data and targets: ``tools.train.toa_correction_data``): choose the echo-timing estimator and
half window on the training positions (lowest inlier ToA rms), refit the per-channel delay
shift on them, fit gradient-boosted trees (depth 3, 400 trees, learning rate 0.05, fixed seed:
deterministic) on the training positions' echoes with and without background, export to ONNX
(skl2onnx, the lowest opsets the trees need), check onnxruntime against scikit-learn, and write
``toa_correction.onnx`` and ``toa_correction.md`` (ablation on the validation positions).
Needs the ``train`` extra (scikit-learn, skl2onnx). The dataset defaults to
``../shared/datasets/spiel-icra23`` beside the checkout, or ``$SPIEL_DATASET``.
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import logging
import sys
import time
from pathlib import Path

import numpy as np

from spiel_edge.pipeline.stages.echo_timing import feature_names
from spiel_edge.profile.schema import load_profile
from tools.train import toa_correction_card as card
from tools.train import toa_correction_data as tcd
from tools.train.association_model import DEFAULT_DATA, DEFAULT_OUT

log = logging.getLogger("train_toa_correction")

CANDIDATES = [(e, w) for e in ("parabola", "log_parabola") for w in (1, 2, 3)]
TREES = {"max_depth": 3, "n_estimators": 400, "learning_rate": 0.05, "random_state": 0}
OPSETS = {"": 17, "ai.onnx.ml": 3}


def choose_estimator(cases, base_delays) -> tuple[str, int, dict]:
    """The (estimator, half window) with the lowest inlier ToA rms on the training cases."""
    scores = {}
    for est, hw in CANDIDATES:
        tcd.re_refine(cases, est, hw)
        shift = tcd.fit_delay_shift(cases, base_delays)
        scores[f"{est} +-{hw}"] = tcd.inlier_rms(cases, lambda c: c.refined, base_delays + shift)
    best = min(scores, key=scores.get)
    est, hw = best.split(" +-")
    return est, int(hw), scores


def fit_trees(X: np.ndarray, y: np.ndarray):
    from sklearn.ensemble import GradientBoostingRegressor

    return GradientBoostingRegressor(**TREES).fit(X, y)


def export_onnx(model, n_features: int, metadata: dict) -> bytes:
    from skl2onnx import convert_sklearn
    from skl2onnx.common.data_types import FloatTensorType

    onx = convert_sklearn(
        model,
        initial_types=[("features", FloatTensorType([None, n_features]))],
        final_types=[("correction", FloatTensorType([None, 1]))],
        target_opset=OPSETS,
    )
    for key, value in metadata.items():
        entry = onx.metadata_props.add()
        entry.key, entry.value = key, value
    onx.doc_string = "spiel-edge learned ToA correction (samples to subtract)"
    onx.graph.name = "toa_correction"  # skl2onnx names it with a random uuid: not reproducible
    return onx.SerializeToString()


def check_runtime(blob: bytes, model, X: np.ndarray) -> float:
    """Largest |onnxruntime - scikit-learn| prediction over X (samples)."""
    import onnxruntime as ort

    sess = ort.InferenceSession(blob, providers=["CPUExecutionProvider"])
    got = sess.run(["correction"], {"features": X})[0].reshape(-1)
    return float(np.max(np.abs(got - model.predict(X))))


def _opsets(blob: bytes) -> str:
    import onnx

    model = onnx.load_from_string(blob)
    return ", ".join(f"{o.domain or 'ai.onnx'} {o.version}" for o in model.opset_import)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=DEFAULT_DATA)
    ap.add_argument("--profile", default="spiel-icra23")
    ap.add_argument("--out", type=Path, default=DEFAULT_OUT)
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    t0 = time.time()
    profile = load_profile(args.profile)
    base = np.asarray(profile.geometry.delays(), dtype=np.float64)
    cases = tcd.load_cases(args.data, profile, "log_parabola", 2)
    train, val = tcd.split(cases)
    log.info(
        "%d cases (with and without background): %d train, %d val", len(cases), len(train), len(val)
    )
    est, hw, choice = choose_estimator(train, base)
    tcd.re_refine(cases, est, hw)
    shift = tcd.fit_delay_shift(train, base)
    delays = base + shift
    log.info("estimator %s +-%d, delay shift %s", est, hw, np.round(shift, 4))
    X, y, _ = tcd.training_rows(train, delays)
    model = fit_trees(X, y)
    Xb, yb, _ = tcd.training_rows([c for c in train if c.has_background], delays)
    model_bg_only = fit_trees(Xb, yb)
    names = feature_names(profile.geometry.n_channels)
    metadata = {
        "spiel.profile": profile.name,
        "spiel.feature_names": ",".join(names),
        "spiel.estimator": est,
        "spiel.half_window": str(hw),
        "spiel.delay_shift_samples": ",".join(f"{v:.4f}" for v in shift),
        "spiel.trees": json.dumps(TREES),
    }
    blob = export_onnx(model, len(names), metadata)
    max_diff = check_runtime(blob, model, X)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "toa_correction.onnx").write_bytes(blob)
    sha = hashlib.sha256(blob).hexdigest()
    timed = dataclasses.replace(
        profile.echo_timing,
        estimator=est,
        half_window=hw,
        delay_shift_samples=tuple(round(float(v), 4) for v in shift),
    )
    table = card.ablation(profile.replace(echo_timing=timed), train, val, model, model_bg_only)
    info = {
        "estimator": est,
        "half_window": hw,
        "choice": choice,
        "shift": shift,
        "rows": len(y),
        "rows_bg": len(yb),
        "train_cases": len(train),
        "val_cases": len(val),
        "val_xy": sorted({c.xy for c in val}),
        "sha256": sha,
        "size_kb": len(blob) / 1024,
        "max_diff": max_diff,
        "names": names,
        "opsets": _opsets(blob),
    }
    card.write(args.out / "toa_correction.md", profile, table, info)
    summary = {k: info[k] for k in ("estimator", "half_window", "rows", "sha256", "max_diff")}
    summary["delay_shift_samples"] = [round(float(v), 4) for v in shift]
    summary["seconds"] = round(time.time() - t0, 1)
    print(json.dumps(summary, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
