"""The interpreted tier's numpy forms of its hottest kernels (issue 39: the interpreted tier
keeps up with a board at 20/s): the same results, bit for bit, as the kernels' Python
functions (the twins they replace) and as the compiled kernels."""

from __future__ import annotations

import numpy as np
import pytest

from spiel_edge import _tiers
from spiel_edge.pipeline.learned import mlp, tree_ensemble


def _same(a, b) -> None:
    a, b = np.asarray(a), np.asarray(b)
    assert a.dtype == b.dtype and a.shape == b.shape
    assert a.tobytes() == b.tobytes()  # bit for bit (NaN and -0.0 included)


@pytest.mark.parametrize("seed", range(5))
def test_the_trees_numpy_form_sums_as_the_kernel(seed) -> None:
    rng = np.random.default_rng(seed)
    n_trees = int(rng.integers(1, 500))
    feature = rng.integers(0, 6, (n_trees, 7)).astype(np.int64)
    threshold = rng.normal(size=(n_trees, 7)).astype(np.float32)
    value = (rng.normal(size=(n_trees, 8)) * 10.0 ** rng.integers(-3, 3)).astype(np.float32)
    for _ in range(20):
        xf = rng.normal(size=6).astype(np.float32)
        xf[rng.integers(0, 6)] = threshold[0, 0]  # a value on a threshold: x <= t goes left
        total = np.float32(rng.normal())
        args = (xf, feature, threshold, value, total)
        want = tree_ensemble._sum_depth3.py_func(*args)
        _same(tree_ensemble._sum_depth3_numpy(*args), want)
        _same(np.float32(tree_ensemble._sum_depth3(*args)), want)  # boxed as a Python float


@pytest.mark.parametrize("seed", range(5))
def test_the_layers_numpy_form_sums_as_the_kernel(seed) -> None:
    rng = np.random.default_rng(seed)
    n_out, n_in, n = (int(v) for v in rng.integers(1, 40, 3))
    x = rng.normal(size=(n_in, n)) * 10.0 ** rng.integers(-2, 3)
    x[0, 0] = np.nan if seed % 2 else -0.0
    w = rng.normal(size=(n_out, n_in)).astype(np.float32)
    b = rng.normal(size=n_out).astype(np.float32)
    b[0] = -1e9  # a unit that is cut to 0 by the ReLU (or -0.0/NaN through it)
    outs = [np.full((n_out, n), 7.0) for _ in range(3)]
    mlp._layer_rows.py_func(x, w, b, outs[0])
    mlp._layer_rows_numpy(x, w, b, outs[1])
    mlp._layer_rows(x, w, b, outs[2])
    _same(outs[1], outs[0])
    _same(outs[2][~np.isnan(outs[0])], outs[0][~np.isnan(outs[0])])  # compiled: NaN aside


def test_the_interpreted_tier_runs_the_numpy_forms() -> None:
    tier = _tiers.Interpreted()
    assert tier.twins[id(tree_ensemble._sum_depth3)] is tree_ensemble._sum_depth3_numpy
    assert tier.twins[id(mlp._layer_rows)] is mlp._layer_rows_numpy
    # the twins of their callers call them
    caller = tier.twins[id(tree_ensemble.predict_kernel)]
    assert caller.__globals__["_sum_depth3"] is tree_ensemble._sum_depth3_numpy
    assert tier.twins[id(mlp.mlp_scores)].__globals__["_layer_rows"] is mlp._layer_rows_numpy
