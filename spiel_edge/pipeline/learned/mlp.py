"""The association model's Siamese MLP evaluated in numba (no onnxruntime in the hot path).

The shipped graph (``tools/train/train_association.py``, exported by torch) is

    Sub(mean) -> Div(std) -> Gemm -> Relu -> Gemm -> Relu -> Gemm -> Relu (embedding)
    -> Gemm -> Sigmoid (score)

with every Gemm ``alpha = beta = 1, transB = 1``. :func:`read_mlp` reads the weights from the
ONNX file with the tree reader's minimal protobuf parser (no ``onnx`` package at run time) and
accepts only that shape; anything else raises ModelError and the caller keeps onnxruntime.
The standardisation is done in float32 as onnxruntime does; the layers accumulate in float64
(onnxruntime accumulates in float32): the two agree within about 1e-7 on realistic rows,
and :mod:`spiel_edge.pipeline.learned.verified_models` stores the weights only after a probe batch
agreed within AGREEMENT.
"""

from __future__ import annotations

import math
import struct

import numpy as np

from spiel_edge import _tiers
from spiel_edge._jit import jit
from spiel_edge.errors import ModelError
from spiel_edge.pipeline.learned.tree_ensemble import protobuf_fields

WEIGHTS = ("mean", "std", "w0", "b0", "w1", "b1", "w2", "b2", "wh", "bh")  # the tuple's order

AGREEMENT = 1e-5  # max |numba - onnxruntime| on the probe batch (score and embedding)
N_INPUT = 8
KNOWN_OPS = ("Sub", "Div", "Gemm", "Relu", "Gemm", "Relu", "Gemm", "Relu", "Gemm", "Sigmoid")
# weight names in the order of the kernel's arguments, with their shapes given the hidden size
WEIGHT_NAMES = ("mean", "std", "w0", "b0", "w1", "b1", "w2", "b2", "wh", "bh")

# protobuf field numbers (onnx.proto3)
_MODEL_GRAPH, _MODEL_METADATA = 7, 14
_GRAPH_NODE, _GRAPH_INITIALIZER = 1, 5
_NODE_INPUT, _NODE_OP_TYPE, _NODE_ATTRIBUTE = 1, 4, 5
_TENSOR_DIMS, _TENSOR_TYPE, _TENSOR_FLOATS, _TENSOR_NAME, _TENSOR_RAW = 1, 2, 4, 8, 9
_ATTR_NAME, _ATTR_F, _ATTR_I = 1, 2, 3
_FLOAT = 1


def read_metadata(blob: bytes) -> dict[str, str]:
    """The model's ``metadata_props`` (key -> value)."""
    out = {}
    for field, _, value in protobuf_fields(blob):
        if field == _MODEL_METADATA:
            entry = {f: v.decode() for f, _, v in protobuf_fields(value)}
            out[entry.get(1, "")] = entry.get(2, "")
    return out


def read_mlp(blob: bytes) -> tuple[np.ndarray, ...]:
    """The weights (float32, in WEIGHT_NAMES order) of an association graph of the known
    shape; ModelError for anything else."""
    nodes, tensors = [], {}
    for field, _, value in protobuf_fields(blob):
        if field != _MODEL_GRAPH:
            continue
        for g_field, _, g_value in protobuf_fields(value):
            if g_field == _GRAPH_NODE:
                nodes.append(_node(g_value))
            elif g_field == _GRAPH_INITIALIZER:
                name, array = _tensor(g_value)
                tensors[name] = array
    ops = tuple(op for op, _, _ in nodes)
    if ops != KNOWN_OPS:
        raise ModelError(f"graph {ops} is not the known MLP {KNOWN_OPS}")
    for op, _, attrs in nodes:
        if op == "Gemm" and attrs != {"alpha": 1.0, "beta": 1.0, "transB": 1}:
            raise ModelError(f"Gemm with attributes {attrs}: only alpha=beta=1, transB=1")
    try:
        weights = [tensors[nodes[0][1][1]], tensors[nodes[1][1][1]]]
        for i in (2, 4, 6, 8):
            weights += [tensors[nodes[i][1][1]], tensors[nodes[i][1][2]]]
    except (KeyError, IndexError) as exc:
        raise ModelError(f"MLP weight {exc} is not an initializer") from exc
    _check_shapes(weights)
    return tuple(np.ascontiguousarray(w, dtype=np.float32) for w in weights)


def _check_shapes(weights: list[np.ndarray]) -> None:
    mean, std, w0, b0, w1, b1, w2, b2, wh, bh = weights
    hidden, embed = w0.shape[0], w2.shape[0]
    want = (
        (N_INPUT,),
        (N_INPUT,),
        (hidden, N_INPUT),
        (hidden,),
        (hidden, hidden),
        (hidden,),
        (embed, hidden),
        (embed,),
        (1, embed),
        (1,),
    )
    got = tuple(w.shape for w in weights)
    if got != want:
        raise ModelError(f"MLP weight shapes {got} are not {want}")


def _node(buf: bytes) -> tuple[str, list[str], dict]:
    op, inputs, attrs = "", [], {}
    for field, _, value in protobuf_fields(buf):
        if field == _NODE_OP_TYPE:
            op = value.decode()
        elif field == _NODE_INPUT:
            inputs.append(value.decode())
        elif field == _NODE_ATTRIBUTE:
            name, scalar = "", None
            for a_field, _, a_value in protobuf_fields(value):
                if a_field == _ATTR_NAME:
                    name = a_value.decode()
                elif a_field == _ATTR_F:
                    scalar = struct.unpack("<f", a_value)[0]
                elif a_field == _ATTR_I:
                    scalar = a_value
            attrs[name] = scalar
    return op, inputs, attrs


def _tensor(buf: bytes) -> tuple[str, np.ndarray]:
    name, dims, dtype, raw, floats = "", [], None, None, []
    for field, wire, value in protobuf_fields(buf):
        if field == _TENSOR_NAME:
            name = value.decode()
        elif field == _TENSOR_DIMS:
            dims.append(value)
        elif field == _TENSOR_TYPE:
            dtype = value
        elif field == _TENSOR_RAW:
            raw = value
        elif field == _TENSOR_FLOATS:
            floats.extend(
                struct.unpack(f"<{len(value) // 4}f", value)
                if wire == 2
                else struct.unpack("<f", value)
            )
    if dtype != _FLOAT:
        raise ModelError(f"initializer {name!r} is not float32")
    data = np.frombuffer(raw, dtype="<f4") if raw is not None else np.array(floats, np.float32)
    if data.size != math.prod(dims):
        raise ModelError(f"initializer {name!r} holds {data.size} values for dims {dims}")
    return name, data.reshape(dims)


def evaluate(x: np.ndarray, weights: tuple[np.ndarray, ...]) -> tuple[np.ndarray, np.ndarray]:
    """``(score (n,), embedding (n, embed))`` float32 for rows ``x`` (n, 8)."""
    x = np.ascontiguousarray(x, dtype=np.float32)
    if x.ndim != 2 or x.shape[1] != N_INPUT:
        raise ModelError(f"MLP input must be (n, {N_INPUT}), got {x.shape}")
    score = np.empty(x.shape[0], dtype=np.float32)
    embedding = np.empty((x.shape[0], weights[6].shape[0]), dtype=np.float32)
    _mlp_kernel(x, *weights, score, embedding)
    return score, embedding


@jit
def mlp_scores(x, n, mean, std, w0, b0, w1, b1, w2, b2, wh, bh, out):
    """The scores of the first ``n`` rows of ``x`` (float32, (>= n, N_INPUT)) into ``out``,
    bit for bit as :func:`mlp_row` row by row: every row's sums run in mlp_row's order, but
    the rows go through each layer side by side (independent sums the CPU overlaps: about
    1.7x faster for the ~15 echoes of an acquisition)."""
    n_in = x.shape[1]
    z = np.empty((n_in, n))
    for j in range(n_in):
        for r in range(n):
            z[j, r] = np.float32(np.float32(np.float32(x[r, j]) - mean[j]) / std[j])
    h0 = np.empty((w0.shape[0], n))
    h1 = np.empty((w1.shape[0], n))
    emb = np.empty((w2.shape[0], n))
    _layer_rows(z, w0, b0, h0)
    _layer_rows(h0, w1, b1, h1)
    _layer_rows(h1, w2, b2, emb)
    for r in range(n):
        logit = np.float64(bh[0])
        for j in range(emb.shape[0]):
            logit += np.float64(wh[0, j]) * emb[j, r]
        out[r] = np.float32(1.0 / (1.0 + math.exp(-logit)))


@jit
def _layer_rows(x, w, b, out):
    """out[:, r] = relu(w @ x[:, r] + b) for every column r, each sum in _layer's order."""
    n = x.shape[1]
    for i in range(w.shape[0]):
        bias = np.float64(b[i])
        for r in range(n):
            out[i, r] = bias
        for j in range(w.shape[1]):
            wij = np.float64(w[i, j])
            for r in range(n):
                out[i, r] += wij * x[j, r]
        for r in range(n):
            out[i, r] = max(out[i, r], 0.0)


@_tiers.numpy_form(_layer_rows)
def _layer_rows_numpy(x, w, b, out):
    """:func:`_layer_rows` on the interpreted tier: the same float64 sums in the same order
    (bias, then w[i, j] * x[j, r] for j = 0, 1, ...), all rows and columns at once."""
    acc = np.repeat(b.astype(np.float64)[:, None], x.shape[1], axis=1)
    for j in range(w.shape[1]):
        acc += w[:, j].astype(np.float64)[:, None] * x[j][None, :]
    out[:, :] = np.where(acc < 0.0, 0.0, acc)  # max(v, 0.0) keeps v when not below (NaN, -0.0)


@jit
def _layer(x, w, b, out):
    """out = relu(w @ x + b), accumulated in float64."""
    for i in range(w.shape[0]):
        acc = np.float64(b[i])
        for j in range(w.shape[1]):
            acc += np.float64(w[i, j]) * x[j]
        out[i] = max(acc, 0.0)


@jit
def mlp_row(x, mean, std, w0, b0, w1, b1, w2, b2, wh, bh, z, h0, h1, emb):
    """One row: the score (float32); the embedding into ``emb``. ``z``, ``h0``, ``h1`` are
    scratch (N_INPUT,), (hidden,), (hidden,) float64."""
    for j in range(x.shape[0]):
        z[j] = np.float32(np.float32(np.float32(x[j]) - mean[j]) / std[j])  # as onnxruntime
    _layer(z, w0, b0, h0)
    _layer(h0, w1, b1, h1)
    _layer(h1, w2, b2, emb)
    logit = np.float64(bh[0])
    for j in range(emb.shape[0]):
        logit += np.float64(wh[0, j]) * emb[j]
    return np.float32(1.0 / (1.0 + math.exp(-logit)))


@jit
def _mlp_kernel(x, mean, std, w0, b0, w1, b1, w2, b2, wh, bh, score, embedding):
    z = np.empty(x.shape[1])
    h0 = np.empty(w0.shape[0])
    h1 = np.empty(w1.shape[0])
    emb = np.empty(w2.shape[0])
    for r in range(x.shape[0]):
        score[r] = mlp_row(x[r], mean, std, w0, b0, w1, b1, w2, b2, wh, bh, z, h0, h1, emb)
        for j in range(emb.shape[0]):
            embedding[r, j] = emb[j]
