"""Check the shipped models' numba evaluation against onnxruntime and store the verified
weights next to them (build time), so an install never imports onnxruntime for them.

    python -m tools.release.verify_models [--folder spiel_edge/models]

Writes ``<model>-<hash16>.verified.npz`` for the association MLP and the ToA correction trees
(:mod:`spiel_edge.pipeline.learned.verified_models`); exits 1 when a model does not verify. Rerun it
after retraining a model (a stale file is ignored: its hash no longer matches).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from spiel_edge.pipeline.learned import associate_onnx, mlp, toa_correction, verified_models
from spiel_edge.pipeline.stages.echo_timing import N_SCALARS, N_WINDOW


def verify_association(path: Path, folder: Path) -> Path | None:
    blob = path.read_bytes()
    session = associate_onnx.load_session(path)
    weights = associate_onnx.verify_mlp(session, blob, path)
    if weights is None:
        return None
    meta = dict(session.get_modelmeta().custom_metadata_map)
    sha = verified_models.digest(blob)
    return verified_models.store(path, sha, mlp.WEIGHT_NAMES, weights, meta, folder)


def verify_toa_correction(path: Path, folder: Path) -> Path | None:
    blob = path.read_bytes()
    import onnxruntime as ort

    width = ort.InferenceSession(blob, providers=["CPUExecutionProvider"]).get_inputs()[0].shape[1]
    corr = toa_correction._load_with_onnxruntime(width - 3 * N_WINDOW - N_SCALARS, path, blob)
    if corr.trees is None:
        return None
    arrays = (*corr.trees[:3], np.float64(corr.trees[3]), np.int64(width))
    sha = verified_models.digest(blob)
    return verified_models.store(
        path, sha, toa_correction.VERIFIED_NAMES, arrays, corr.metadata, folder
    )


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--folder", type=Path, default=None, help="default: next to each model")
    args = ap.parse_args(argv)
    failed = 0
    for verify, path in (
        (verify_association, associate_onnx.default_model_path()),
        (verify_toa_correction, toa_correction.default_model_path()),
    ):
        for stale in path.parent.glob(f"{path.stem}-*{verified_models.SUFFIX}"):
            stale.unlink()
        written = verify(path, args.folder or path.parent)
        print(f"{path.name}: {written or 'does not verify (stays on onnxruntime)'}")
        failed += written is None
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
