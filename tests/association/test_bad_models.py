"""Missing or unusable model files: ModelError, and the factory falls back to geometric."""

from __future__ import annotations

import logging

import onnx
import pytest
from onnx import TensorProto, helper

from spiel_edge.errors import ModelError
from spiel_edge.pipeline import factory
from spiel_edge.pipeline.learned.associate_onnx import OnnxAssociator, default_model_path
from spiel_edge.pipeline.stages.associate import GeometricAssociator


def _wrong_shape_model(path, n_features=5):
    x = helper.make_tensor_value_info("features", TensorProto.FLOAT, ["batch", n_features])
    score = helper.make_tensor_value_info("score", TensorProto.FLOAT, ["batch", n_features])
    emb = helper.make_tensor_value_info("embedding", TensorProto.FLOAT, ["batch", n_features])
    graph = helper.make_graph(
        [
            helper.make_node("Sigmoid", ["features"], ["score"]),
            helper.make_node("Relu", ["features"], ["embedding"]),
        ],
        "wrong",
        [x],
        [score, emb],
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)], ir_version=8)
    onnx.checker.check_model(model)
    onnx.save(model, path)


def _bad_files(tmp_path):
    garbage = tmp_path / "garbage.onnx"
    garbage.write_bytes(b"\x00\xffnot an onnx model" * 10)
    truncated = tmp_path / "truncated.onnx"
    blob = default_model_path().read_bytes()
    truncated.write_bytes(blob[: len(blob) // 2])
    wrong = tmp_path / "wrong.onnx"
    _wrong_shape_model(wrong)
    return {
        "missing": tmp_path / "missing.onnx",
        "garbage": garbage,
        "truncated": truncated,
        "wrong shape": wrong,
    }


@pytest.mark.parametrize("kind", ["missing", "garbage", "truncated", "wrong shape"])
def test_bad_model_raises_model_error(profile, tmp_path, kind):
    path = _bad_files(tmp_path)[kind]
    with pytest.raises(ModelError, match="association model") as info:
        OnnxAssociator(profile, path)
    assert str(path) in str(info.value)


def test_wrong_shape_message_names_the_expected_shape(profile, tmp_path):
    path = tmp_path / "wrong.onnx"
    _wrong_shape_model(path)
    with pytest.raises(ModelError, match=r"\(batch, 8\)"):
        OnnxAssociator(profile, path)


@pytest.mark.parametrize("kind", ["missing", "garbage", "truncated", "wrong shape"])
def test_factory_warns_and_uses_geometric(profile, tmp_path, monkeypatch, caplog, kind):
    path = _bad_files(tmp_path)[kind]
    monkeypatch.setattr(
        "spiel_edge.pipeline.learned.associate_onnx.default_model_path", lambda: path
    )
    with caplog.at_level(logging.WARNING, logger=factory.__name__):
        assoc = factory.build_associator(profile, "onnx")
    assert isinstance(assoc, GeometricAssociator)
    assert any(
        "geometric" in r.getMessage() and r.levelno == logging.WARNING for r in caplog.records
    )


def test_factory_uses_the_shipped_model(profile):
    assert isinstance(factory.build_associator(profile, "auto"), OnnxAssociator)
    assert isinstance(factory.build_associator(profile, "geometric"), GeometricAssociator)
