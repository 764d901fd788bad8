"""The shipped model: ONNX reproduces the torch reference, the card names the file's hash."""

from __future__ import annotations

import hashlib
import json
import re
from pathlib import Path

import numpy as np
import onnxruntime as ort

MODELS = Path(__file__).resolve().parents[2] / "spiel_edge" / "models"
MODEL = MODELS / "association.onnx"


def test_onnx_reproduces_torch_reference_outputs():
    ref = json.loads((MODELS / "association_reference.json").read_text())
    assert ref["onnx_sha256"] == hashlib.sha256(MODEL.read_bytes()).hexdigest(), (
        "reference is from another model"
    )
    session = ort.InferenceSession(str(MODEL), providers=["CPUExecutionProvider"])
    x = np.array(ref["features"], dtype=np.float32)
    score, embedding = session.run(["score", "embedding"], {"features": x})
    assert score.shape == (len(x), 1) and embedding.shape == (len(x), 4)
    np.testing.assert_allclose(score, np.array(ref["score"]), atol=1e-5, rtol=0)
    np.testing.assert_allclose(embedding, np.array(ref["embedding"]), atol=1e-5, rtol=0)
    assert np.ptp(score) > 1e-3, "reference inputs should not all score the same"


def test_batch_axis_is_dynamic():
    session = ort.InferenceSession(str(MODEL), providers=["CPUExecutionProvider"])
    x = np.array(
        json.loads((MODELS / "association_reference.json").read_text())["features"],
        dtype=np.float32,
    )
    one = session.run(["score"], {"features": x[:1]})[0]
    many = session.run(["score"], {"features": x})[0]
    np.testing.assert_allclose(one[0], many[0], atol=1e-6)


def test_model_card_states_the_files_sha256():
    card = (MODELS / "association.md").read_text()
    m = re.search(r"SHA-256 of association\.onnx: `([0-9a-f]{64})`", card)
    assert m, "model card lacks the SHA-256 line"
    assert m.group(1) == hashlib.sha256(MODEL.read_bytes()).hexdigest()


def test_repo_root_models_link_points_at_the_packaged_model():
    root = MODELS.parents[1] / "models"
    assert (root / "association.onnx").read_bytes() == MODEL.read_bytes()
    assert (root / "association.md").is_file()
