"""The learned ToA correction: the shipped model, and bad models falling back with a warning."""

import hashlib
import logging
import re

import numpy as np
import pytest
from onnx import TensorProto, helper

from spiel_edge.errors import ModelError
from spiel_edge.pipeline.factory import build_pipeline
from spiel_edge.pipeline.learned.toa_correction import (
    MAX_CORRECTION,
    build_correction,
    default_model_path,
    load_correction,
)
from spiel_edge.pipeline.stages.echo_timing import EchoTiming, n_toa_features


def _model(path, n_features=None, opset=17, output="correction"):
    n_features = n_features or n_toa_features(4)
    x = helper.make_tensor_value_info("features", TensorProto.FLOAT, [None, n_features])
    y = helper.make_tensor_value_info(output, TensorProto.FLOAT, [None, 1])
    w = helper.make_tensor("w", TensorProto.FLOAT, [n_features, 1], [0.01] * n_features)
    graph = helper.make_graph(
        [helper.make_node("MatMul", ["features", "w"], [output])], "g", [x], [y], [w]
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", opset)])
    model.ir_version = 8
    path.write_bytes(model.SerializeToString())
    return path


def test_shipped_model_loads_matches_its_card_and_predicts_within_bounds():
    blob = default_model_path().read_bytes()
    card = default_model_path().with_suffix(".md").read_text()
    assert hashlib.sha256(blob).hexdigest() in card
    corr = load_correction(4)
    x = np.random.default_rng(0).random((4, n_toa_features(4)))
    x[2] = np.nan
    pred = corr.predict(x)
    assert pred[2] == 0 and np.all(np.abs(pred) <= MAX_CORRECTION)


def test_a_good_small_model_loads(tmp_path):
    corr = load_correction(4, _model(tmp_path / "m.onnx"))
    np.testing.assert_allclose(
        corr(np.ones((4, n_toa_features(4))), np.full(4, 20.0)),
        20 - 0.01 * n_toa_features(4),
        rtol=1e-5,
    )


@pytest.mark.parametrize(
    "make, message",
    [
        (lambda p: p, "not found"),
        (lambda p: (p.write_bytes(b"\x08\x07garbage"), p)[1], "cannot be loaded"),
        (lambda p: _model(p, n_features=10), re.escape(f"(batch, {n_toa_features(4)})")),
        (lambda p: _model(p, opset=999), "cannot be loaded"),
        (lambda p: _model(p, output="other"), "expected input"),
    ],
    ids=["missing", "corrupt", "input size", "opset", "output name"],
)
def test_bad_models_are_refused_and_fall_back_with_one_warning(tmp_path, caplog, make, message):
    path = make(tmp_path / "bad.onnx")
    with pytest.raises(ModelError, match=message):
        load_correction(4, path)
    with caplog.at_level(logging.WARNING):
        assert build_correction("onnx", 4, path) is None
    assert len([r for r in caplog.records if "uncorrected ToA" in r.message]) == 1
    assert build_correction("none", 4, path) is None


def test_nan_from_the_correction_keeps_the_refined_toa(subset):
    def broken(features, toa):
        return np.full_like(toa, np.nan)

    f, b = subset.frames[0], subset.backgrounds[0]
    plain = EchoTiming("log_parabola", 2, 9)
    toa = np.array([20.0, 21.0, 22.0, np.nan])
    np.testing.assert_array_equal(
        EchoTiming("log_parabola", 2, 9, broken)(f, b, toa), plain(f, b, toa)
    )


def test_pipeline_with_a_bad_model_warns_and_still_locates(
    profile, subset, tmp_path, monkeypatch, caplog
):
    monkeypatch.setattr(
        "spiel_edge.pipeline.learned.toa_correction.default_model_path",
        lambda: tmp_path / "none.onnx",
    )
    with caplog.at_level(logging.WARNING):
        pipe = build_pipeline(profile, "geometric", "auto")
    assert pipe.echo_timing.correction is None and "uncorrected ToA" in caplog.text
    r = pipe.process(subset.frames[0], subset.backgrounds[0])
    assert r.position_mm is not None and np.all(np.isfinite(r.position_mm))


@pytest.mark.parametrize("with_background", [True, False])
def test_fused_step_equals_the_separate_wrappers(subset, with_background):
    from spiel_edge.pipeline.stages.echo_timing import clean_envelope, refine_toa, toa_features

    corr = load_correction(4)
    assert corr.trees is not None
    step = EchoTiming("log_parabola", 2, 9, corr)
    for i in range(0, len(subset), 40):
        f = subset.frames[i]
        b = subset.backgrounds[i] if with_background else None
        toa = np.array([15.2, 18.7, np.nan, 62.9])
        clean = clean_envelope(f, b, 9)
        refined = refine_toa(clean, toa, 2)
        expect = corr(toa_features(f, b, clean, refined), refined)
        np.testing.assert_allclose(step(f, b, toa), expect, atol=1e-9)
        assert np.isnan(step(f, b, toa)[2]) and np.isfinite(step(f, b, toa)[[0, 1, 3]]).all()
