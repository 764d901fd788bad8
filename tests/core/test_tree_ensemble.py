"""Trees read from ONNX and walked in numba agree with onnxruntime."""

import numpy as np
import onnxruntime as ort
import pytest
from onnx import TensorProto, helper

from spiel_edge.errors import ModelError
from spiel_edge.pipeline.learned import tree_ensemble
from spiel_edge.pipeline.learned.toa_correction import default_model_path, load_correction
from spiel_edge.pipeline.stages.echo_timing import n_toa_features


def _uneven_model(mode="BRANCH_LEQ") -> bytes:
    """Tree 0: x0 <= 0.5 ? 1.0 : (x1 <= 0.2 ? 2.0 : 3.0); tree 1: a single leaf 0.25; base 0.1."""
    node = helper.make_node(
        "TreeEnsembleRegressor",
        ["x"],
        ["y"],
        domain="ai.onnx.ml",
        n_targets=1,
        base_values=[0.1],
        nodes_treeids=[0, 0, 0, 0, 0, 1],
        nodes_nodeids=[0, 1, 2, 3, 4, 0],
        nodes_featureids=[0, 0, 1, 0, 0, 0],
        nodes_values=[0.5, 0.0, 0.2, 0.0, 0.0, 0.0],
        nodes_modes=[mode, "LEAF", "BRANCH_LEQ", "LEAF", "LEAF", "LEAF"],
        nodes_truenodeids=[1, 0, 3, 0, 0, 0],
        nodes_falsenodeids=[2, 0, 4, 0, 0, 0],
        target_treeids=[0, 0, 0, 1],
        target_nodeids=[1, 3, 4, 0],
        target_ids=[0, 0, 0, 0],
        target_weights=[1.0, 2.0, 3.0, 0.25],
        post_transform="NONE",
    )
    graph = helper.make_graph(
        [node],
        "g",
        [helper.make_tensor_value_info("x", TensorProto.FLOAT, [None, 2])],
        [helper.make_tensor_value_info("y", TensorProto.FLOAT, [None, 1])],
    )
    model = helper.make_model(
        graph, opset_imports=[helper.make_opsetid("", 17), helper.make_opsetid("ai.onnx.ml", 3)]
    )
    model.ir_version = 8
    return model.SerializeToString()


def _onnxruntime(blob, x, output="y", name="x"):
    sess = ort.InferenceSession(blob, providers=["CPUExecutionProvider"])
    return sess.run([output], {name: x.astype(np.float32)})[0].reshape(-1)


def test_uneven_trees_match_onnxruntime_exactly(rng):
    blob = _uneven_model()
    x = rng.uniform(-1, 1, (200, 2))
    x[0] = [0.5, 0.2]  # on the thresholds: <= goes to the true branch
    got = tree_ensemble.predict(tree_ensemble.read_trees(blob), x)
    np.testing.assert_allclose(got, _onnxruntime(blob, x), atol=1e-6)
    assert got[0] == pytest.approx(1.35)


def test_shipped_model_in_numba_matches_onnxruntime(rng):
    blob = default_model_path().read_bytes()
    corr = load_correction(4)
    assert corr.engine == "numba"
    x = rng.normal(0.5, 1.0, (500, n_toa_features(4)))
    np.testing.assert_allclose(
        tree_ensemble.predict(tree_ensemble.read_trees(blob), x),
        _onnxruntime(blob, x, "correction", "features"),
        atol=1e-5,
    )
    x[3, 5] = np.nan
    toa = np.full(500, 20.0)
    np.testing.assert_allclose(corr(x, toa), toa - corr.predict(x), atol=1e-9)
    assert corr(x, toa)[3] == 20.0


def test_unsupported_or_broken_trees_are_refused():
    with pytest.raises(ModelError, match="node modes"):
        tree_ensemble.read_trees(_uneven_model("BRANCH_LT"))
    with pytest.raises(ModelError):
        tree_ensemble.read_trees(b"\x3a\x05\x0a\x03abc")  # a graph holding a truncated node
    with pytest.raises(ModelError, match="found 0"):
        tree_ensemble.read_trees(b"")


def _random_trees(rng, n_trees: int, max_depth: int, n_features: int) -> tree_ensemble.Trees:
    """Uneven random trees (a leaf may stop a branch early) as read_trees builds them."""
    feature, threshold, true_next, false_next, leaf, value, roots = [], [], [], [], [], [], []

    def grow(depth: int) -> int:
        i = len(leaf)
        for column in (feature, threshold, true_next, false_next, leaf, value):
            column.append(0)
        if depth == max_depth or (depth > 0 and rng.random() < 0.2):
            leaf[i], value[i] = True, rng.normal()
            true_next[i] = false_next[i] = -1
        else:
            feature[i], threshold[i] = rng.integers(n_features), rng.normal()
            true_next[i] = grow(depth + 1)
            false_next[i] = grow(depth + 1)
        return i

    for _ in range(n_trees):
        roots.append(grow(0))
    return tree_ensemble.Trees(
        np.array(feature, dtype=np.int64),
        np.array(threshold, dtype=np.float32),
        np.array(true_next, dtype=np.int64),
        np.array(false_next, dtype=np.int64),
        np.array(leaf),
        np.array(value),
        np.array(roots, dtype=np.int64),
        float(rng.normal()),
    )


def _reference_predict(trees: tree_ensemble.Trees, x: np.ndarray) -> np.ndarray:
    """Plain numpy: walk each tree's nodes, float32 compares and float32 sums in tree order."""
    out = np.full(x.shape[0], np.nan)
    for r, row in enumerate(np.asarray(x, dtype=np.float32)):
        if not np.all(np.isfinite(row)):
            continue
        total = np.float32(trees.base)
        for node in trees.roots:
            while not trees.leaf[node]:
                go_true = row[trees.feature[node]] <= trees.threshold[node]
                node = trees.true_next[node] if go_true else trees.false_next[node]
            total = np.float32(total + np.float32(trees.value[node]))
        out[r] = total
    return out


@pytest.mark.parametrize("depth", [1, 2, 3, 4, 6])
def test_kernel_equals_numpy_walk_bit_for_bit(rng, depth):
    """Depth 3 takes the unrolled walk, the others the loop over levels."""
    trees = _random_trees(rng, 57, depth, 5)
    x = rng.normal(size=(40, 5))
    x[3, 2] = np.nan
    x[4, 0] = trees.threshold[trees.roots[0]]  # on a threshold: <= goes the true way
    got = tree_ensemble.predict(trees, x)
    np.testing.assert_array_equal(got, _reference_predict(trees, x))
    assert np.isnan(got[3])


def test_shipped_trees_equal_numpy_walk_bit_for_bit(rng):
    trees = tree_ensemble.read_trees(default_model_path().read_bytes())
    x = rng.normal(0.5, 1.0, (300, n_toa_features(4)))
    assert tree_ensemble.dense(trees)[0].shape[1] == 7  # depth 3: the unrolled walk
    np.testing.assert_array_equal(tree_ensemble.predict(trees, x), _reference_predict(trees, x))
