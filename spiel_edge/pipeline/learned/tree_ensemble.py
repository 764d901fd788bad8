"""An ONNX ``TreeEnsembleRegressor`` evaluated in numba (the learned ToA correction's model).

onnxruntime needs ~15-35 us per call for a few rows of a 400-tree ensemble; walking the trees
in numba takes a few. The trees are read from the ONNX file itself with a minimal protobuf
reader (ModelProto.graph.node[].attribute[]: no ``onnx`` package at run time). Only what
skl2onnx writes for a regressor is accepted (BRANCH_LEQ/LEAF nodes, SUM, no post transform,
one target); anything else raises ModelError and the caller keeps onnxruntime.
:class:`spiel_edge.pipeline.learned.toa_correction.ToaCorrection` also checks on load that both agree.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

import numpy as np

from spiel_edge import _tiers
from spiel_edge._jit import jit
from spiel_edge.errors import ModelError

# the arrays a correction's ``trees`` holds for the kernels: dense(...) and the base
DENSE = ("feature", "threshold", "value", "base")

# protobuf field numbers (onnx.proto3)
_MODEL_GRAPH, _GRAPH_NODE = 7, 1
_NODE_OP_TYPE, _NODE_ATTRIBUTE, _NODE_DOMAIN = 4, 5, 7
_ATTR_NAME, _ATTR_F, _ATTR_I, _ATTR_S, _ATTR_FLOATS, _ATTR_INTS, _ATTR_STRINGS = 1, 2, 3, 4, 7, 8, 9


@dataclass(frozen=True)
class Trees:
    """Flat arrays over all nodes; ``roots`` indexes each tree's root."""

    feature: np.ndarray  # int64
    threshold: np.ndarray  # float32
    true_next: np.ndarray  # int64 (global node index)
    false_next: np.ndarray
    leaf: np.ndarray  # bool
    value: np.ndarray  # float64: the leaf's weight
    roots: np.ndarray  # int64
    base: float

    def arrays(self) -> tuple:
        return (
            self.feature,
            self.threshold,
            self.true_next,
            self.false_next,
            self.leaf,
            self.value,
            self.roots,
        )

    @property
    def n_features(self) -> int:
        return int(self.feature.max()) + 1 if self.feature.size else 0


def protobuf_fields(buf: bytes):
    """Yield (field number, wire type, value) of one protobuf message."""
    i, n = 0, len(buf)
    while i < n:
        key, i = _varint(buf, i)
        field, wire = key >> 3, key & 7
        if wire == 0:
            value, i = _varint(buf, i)
        elif wire == 1:
            value, i = buf[i : i + 8], i + 8
        elif wire == 2:
            size, i = _varint(buf, i)
            value, i = buf[i : i + size], i + size
        elif wire == 5:
            value, i = buf[i : i + 4], i + 4
        else:
            raise ModelError(f"unsupported protobuf wire type {wire}")
        if i > n:
            raise ModelError("truncated protobuf message")
        yield field, wire, value


def _varint(buf: bytes, i: int) -> tuple[int, int]:
    out = shift = 0
    while True:
        if i >= len(buf) or shift > 63:
            raise ModelError("truncated protobuf varint")
        b = buf[i]
        out |= (b & 0x7F) << shift
        i, shift = i + 1, shift + 7
        if not b & 0x80:
            return out, i


def _packed_varints(buf: bytes) -> list[int]:
    out, i = [], 0
    while i < len(buf):
        v, i = _varint(buf, i)
        out.append(v - (1 << 64) if v >= 1 << 63 else v)
    return out


def _attribute(buf: bytes) -> tuple[str, object]:
    name, floats, ints, strings, scalar = "", [], [], [], None
    for field, wire, value in protobuf_fields(buf):
        if field == _ATTR_NAME:
            name = value.decode()
        elif field == _ATTR_F:
            scalar = struct.unpack("<f", value)[0]
        elif field == _ATTR_I:
            scalar = value
        elif field == _ATTR_S:
            scalar = value.decode()
        elif field == _ATTR_FLOATS:
            floats.extend(
                struct.unpack(f"<{len(value) // 4}f", value)
                if wire == 2
                else struct.unpack("<f", value)
            )
        elif field == _ATTR_INTS:
            ints.extend(_packed_varints(value) if wire == 2 else [value])
        elif field == _ATTR_STRINGS:
            strings.append(value.decode())
    return name, floats or ints or strings or scalar


def read_trees(blob: bytes) -> Trees:
    """The single TreeEnsembleRegressor of an ONNX model, as flat arrays."""
    graphs = [v for f, w, v in protobuf_fields(blob) if f == _MODEL_GRAPH and w == 2]
    nodes = [v for g in graphs for f, w, v in protobuf_fields(g) if f == _GRAPH_NODE and w == 2]
    found = []
    for node in nodes:
        fields = {f: v for f, w, v in protobuf_fields(node) if f in (_NODE_OP_TYPE, _NODE_DOMAIN)}
        if fields.get(_NODE_OP_TYPE) == b"TreeEnsembleRegressor":
            found.append(
                dict(_attribute(v) for f, w, v in protobuf_fields(node) if f == _NODE_ATTRIBUTE)
            )
    if len(found) != 1:
        raise ModelError(f"expected one TreeEnsembleRegressor, found {len(found)}")
    return _flatten(found[0])


def _flatten(a: dict) -> Trees:
    if a.get("post_transform", "NONE") != "NONE" or a.get("aggregate_function", "SUM") != "SUM":
        raise ModelError("only post_transform NONE and aggregate SUM are supported")
    if a.get("n_targets", 1) != 1 or any(t != 0 for t in a.get("target_ids", [])):
        raise ModelError("only one target is supported")
    modes = a["nodes_modes"]
    if any(m not in ("BRANCH_LEQ", "LEAF") for m in modes):
        raise ModelError(f"unsupported node modes {sorted(set(modes))}")
    tree, node = np.asarray(a["nodes_treeids"]), np.asarray(a["nodes_nodeids"])
    index = {(int(t), int(n)): i for i, (t, n) in enumerate(zip(tree, node, strict=True))}
    try:
        true_next = np.array(
            [
                index[(int(t), int(n))] if m != "LEAF" else -1
                for t, n, m in zip(tree, a["nodes_truenodeids"], modes, strict=True)
            ]
        )
        false_next = np.array(
            [
                index[(int(t), int(n))] if m != "LEAF" else -1
                for t, n, m in zip(tree, a["nodes_falsenodeids"], modes, strict=True)
            ]
        )
        value = np.zeros(len(modes))
        for t, n, w in zip(
            a["target_treeids"], a["target_nodeids"], a["target_weights"], strict=True
        ):
            value[index[(int(t), int(n))]] += w
        roots = np.array([index[(int(t), 0)] for t in np.unique(tree)], dtype=np.int64)
    except (KeyError, ValueError) as exc:
        raise ModelError(f"inconsistent tree ensemble: {exc}") from exc
    base = a.get("base_values", [0.0])
    return Trees(
        np.asarray(a["nodes_featureids"], dtype=np.int64),
        np.asarray(a["nodes_values"], dtype=np.float32),
        true_next.astype(np.int64),
        false_next.astype(np.int64),
        np.array([m == "LEAF" for m in modes]),
        value,
        roots,
        float(base[0]) if base else 0.0,
    )


def dense(trees: Trees) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Every tree as a full binary tree of the ensemble's depth in heap order (children of i at
    2i+1 (true: x <= threshold) and 2i+2): (feature (trees, 2^D-1), threshold float32, leaf
    value float32 (trees, 2^D), rounded once as onnxruntime adds them). A leaf above depth D
    becomes always-true splits (+inf) down to it."""
    depth = max(_depth(trees, r) for r in trees.roots)
    n_inner = 2**depth - 1
    feature = np.zeros((len(trees.roots), max(n_inner, 1)), dtype=np.int64)
    threshold = np.full((len(trees.roots), max(n_inner, 1)), np.inf, dtype=np.float32)
    value = np.zeros((len(trees.roots), 2**depth))
    for t, root in enumerate(trees.roots):
        stack = [(int(root), 0)]
        while stack:
            node, slot = stack.pop()
            if slot >= n_inner:
                value[t, slot - n_inner] = trees.value[node]
            elif trees.leaf[node]:
                stack += [(node, 2 * slot + 1), (node, 2 * slot + 2)]
            else:
                feature[t, slot], threshold[t, slot] = trees.feature[node], trees.threshold[node]
                stack += [(int(trees.true_next[node]), 2 * slot + 1)]
                stack += [(int(trees.false_next[node]), 2 * slot + 2)]
    return feature, threshold, value.astype(np.float32)


def _depth(trees: Trees, node: int) -> int:
    if trees.leaf[node]:
        return 0
    return 1 + max(_depth(trees, trees.true_next[node]), _depth(trees, trees.false_next[node]))


def predict(trees: Trees, x: np.ndarray) -> np.ndarray:
    """Sum of the trees' leaves plus the base value per row of ``x`` (compared as float32, as
    onnxruntime does); NaN for rows with a non-finite value."""
    x = np.ascontiguousarray(x, dtype=np.float64)
    if x.ndim != 2:
        raise ModelError(f"features must be (rows, columns), got shape {x.shape}")
    out = np.empty(x.shape[0])
    predict_kernel(*dense(trees), trees.base, x, out)
    return out


@jit
def predict_kernel(feature, threshold, value, base, x, out):
    n_trees, n_inner = feature.shape
    depth = 0
    while (1 << depth) - 1 < n_inner:
        depth += 1
    xf = np.empty(x.shape[1], dtype=np.float32)
    for r in range(x.shape[0]):
        finite = True
        for j in range(x.shape[1]):
            finite = finite and np.isfinite(x[r, j])
            xf[j] = x[r, j]
        if not finite:
            out[r] = np.nan
            continue
        total = np.float32(base)  # float32 sums in tree order, as onnxruntime's
        if depth == 3:
            out[r] = _sum_depth3(xf, feature, threshold, value, total)
        else:
            out[r] = _sum_trees(xf, feature, threshold, value, depth, total)


@jit(inline="always")
def _down(xf, feature, threshold, i):
    """The child of inner node ``i``: 2i+1 when x <= threshold, else 2i+2 (no branch)."""
    return 2 * i + 2 - np.int64(xf[feature[i]] <= threshold[i])


@jit
def _sum_trees(xf, feature, threshold, value, depth, total):
    n_inner = feature.shape[1]
    for t in range(feature.shape[0]):
        f, h = feature[t], threshold[t]
        i = 0
        for _ in range(depth):
            i = _down(xf, f, h, i)
        total += np.float32(value[t, i - n_inner])
    return total


@jit
def _sum_depth3(xf, feature, threshold, value, total):
    """:func:`_sum_trees` for depth 3 (the shipped model), unrolled: with the loop over
    levels (a trip count LLVM does not know) 400 trees took 1.7x as long."""
    for t in range(feature.shape[0]):
        f, h = feature[t], threshold[t]
        i = _down(xf, f, h, _down(xf, f, h, _down(xf, f, h, 0)))
        total += np.float32(value[t, i - 7])
    return total


@_tiers.numpy_form(_sum_depth3)
def _sum_depth3_numpy(xf, feature, threshold, value, total):
    """:func:`_sum_depth3` on the interpreted tier: every tree's path at once, the leaves
    summed in tree order in float32 (``np.add.accumulate`` adds one after the other)."""
    t = np.arange(feature.shape[0])

    def down(i):
        return 2 * i + 2 - (xf[feature[t, i]] <= threshold[t, i]).astype(np.int64)

    leaves = value[t, down(down(down(np.zeros(len(t), dtype=np.int64)))) - 7]
    terms = np.concatenate((np.array([total], dtype=np.float32), leaves.astype(np.float32)))
    return np.add.accumulate(terms)[-1]
