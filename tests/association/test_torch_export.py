"""With torch installed (extra ``train``): the training tool's export reproduces torch, and
training is deterministic for a seed. Skipped without torch."""

from __future__ import annotations

import hashlib

import numpy as np
import pytest

torch = pytest.importorskip("torch")
ta = pytest.importorskip("tools.train.association_model")


@pytest.fixture(scope="module")
def samples(profile, subset_features):
    out = []
    for i, (f, c, labels, geo) in enumerate(subset_features[:60]):
        x = float(i % 5)  # five fake (x, y) positions so the split has both sides
        out.append(
            ta.Sample(f"{x}mm_0.0mm_100.0mm_0_{i}_frames.csv", f, c, labels, np.zeros(3), geo)
        )
    return out


def _train(samples):
    return ta.train(samples[:45], samples[45:], seed=3, max_epochs=3)[0]


def test_onnx_export_matches_torch(samples):
    import onnxruntime as ort

    net = _train(samples)
    blob = ta.export_onnx(net, {"spiel.distance_threshold": "1.5"})
    session = ort.InferenceSession(blob, providers=["CPUExecutionProvider"])
    x = ta.reference_inputs(samples)
    ref = ta.reference_outputs(net, x)
    score, emb = session.run(["score", "embedding"], {"features": x})
    np.testing.assert_allclose(score, ref["score"], atol=1e-5, rtol=0)
    np.testing.assert_allclose(emb, ref["embedding"], atol=1e-5, rtol=0)
    assert session.get_modelmeta().custom_metadata_map["spiel.distance_threshold"] == "1.5"


def test_training_is_deterministic_for_a_seed(samples):
    def digest(net):
        return hashlib.sha256(
            b"".join(v.numpy().tobytes() for v in net.state_dict().values())
        ).hexdigest()

    assert digest(_train(samples)) == digest(_train(samples))
