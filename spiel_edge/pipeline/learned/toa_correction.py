"""The learned ToA correction (gradient-boosted trees in ONNX), run in numba or onnxruntime.

Input ``features`` (batch, n_toa_features) float32 from
:func:`spiel_edge.pipeline.stages.echo_timing.toa_features`; output ``correction`` (batch, 1): the
ToA error in samples (refined ToA minus delay minus the true ToA) to subtract; the trees are
evaluated in numba (:mod:`spiel_edge.pipeline.learned.tree_ensemble`, checked against onnxruntime
once per model file and then stored by its hash, :mod:`spiel_edge.pipeline.learned.verified_models`, so
later loads do not import onnxruntime), else by onnxruntime. Model card:
``spiel_edge/models/toa_correction.md``; trained by ``python -m tools.train.train_toa_correction``.

A missing, corrupt or mismatched model raises ModelError in :func:`load_correction`, which
:func:`build_correction` turns into one warning and no correction. Rows with NaN features
(no echo, window past the frame's edge) and non-finite predictions are left uncorrected.
"""

from __future__ import annotations

import logging
from importlib import resources
from pathlib import Path

import numpy as np

from spiel_edge._jit import jit
from spiel_edge.errors import ModelError
from spiel_edge.pipeline.learned import tree_ensemble, verified_models
from spiel_edge.pipeline.learned.mlp import read_metadata
from spiel_edge.pipeline.stages.echo_timing import EchoTiming, n_toa_features

log = logging.getLogger(__name__)

INPUT_NAME = "features"
OUTPUT_NAME = "correction"
MAX_CORRECTION = 1.5  # samples: the model was trained on residuals within this bound
CHOICES = ("auto", "onnx", "none")
AGREEMENT = 1e-4  # samples: numba and onnxruntime must agree this well on the probe rows
VERIFIED_NAMES = ("feature", "threshold", "value", "base", "n_inputs")  # verified_models


def default_model_path() -> Path:
    return Path(str(resources.files("spiel_edge") / "models" / "toa_correction.onnx"))


class ToaCorrection:
    """Callable: (features (channels, n), toa (channels,)) -> corrected toa (channels,).

    The trees run in numba when they can be read from the file and agree with onnxruntime on
    probe rows (``engine`` = "numba"), else in onnxruntime ("onnxruntime")."""

    name = "onnx"
    max_correction = MAX_CORRECTION

    @property
    def trees(self) -> tuple | None:
        """The dense trees for numba (see tree_ensemble.dense) plus the base, or None."""
        return self._dense

    def __init__(self, session, path: Path, blob: bytes):
        self._session = session
        self.path = path
        self.metadata = dict(session.get_modelmeta().custom_metadata_map)
        self._dense = None
        self.engine = "onnxruntime"
        try:
            trees = tree_ensemble.read_trees(blob)
            dense = (*tree_ensemble.dense(trees), trees.base)
        except (ModelError, ValueError, IndexError) as exc:
            log.info("ToA correction runs in onnxruntime (%s)", exc)
            return
        probe = np.random.default_rng(0).normal(0.5, 1.0, (64, session.get_inputs()[0].shape[1]))
        self._dense = dense
        if np.max(np.abs(self._numba(probe) - self._onnxruntime(probe))) <= AGREEMENT:
            self.engine = "numba"
        else:
            self._dense = None
            log.info("ToA correction runs in onnxruntime (numba trees disagree)")

    @classmethod
    def verified(cls, path: Path, blob: bytes, dense: tuple) -> ToaCorrection:
        """The numba trees stored after an earlier check (verified_models): no onnxruntime."""
        self = cls.__new__(cls)
        self._session, self.path, self.engine = None, path, "numba"
        self.metadata = read_metadata(blob)
        self._dense = dense
        return self

    def _onnxruntime(self, features: np.ndarray) -> np.ndarray:
        x = np.ascontiguousarray(features, dtype=np.float32)
        return self._session.run([OUTPUT_NAME], {INPUT_NAME: x})[0].reshape(-1).astype(np.float64)

    def _numba(self, features: np.ndarray) -> np.ndarray:
        out = np.empty(features.shape[0])
        tree_ensemble.predict_kernel(
            *self._dense, np.ascontiguousarray(features, dtype=np.float64), out
        )
        return out

    def predict(self, features: np.ndarray) -> np.ndarray:
        """Correction (samples) per row, clipped; 0 for rows with non-finite features or output."""
        ok = np.all(np.isfinite(features), axis=1)
        out = np.zeros(features.shape[0])
        if ok.any():
            pred = self._numba(features[ok]) if self._dense else self._onnxruntime(features[ok])
            out[ok] = np.where(np.isfinite(pred), np.clip(pred, -MAX_CORRECTION, MAX_CORRECTION), 0)
        return out

    def __call__(self, features: np.ndarray, toa: np.ndarray) -> np.ndarray:
        if self._dense is None:
            return toa - self.predict(features)
        out = np.empty(features.shape[0])
        _correct_kernel(
            *self._dense,
            np.ascontiguousarray(features, dtype=np.float64),
            np.ascontiguousarray(toa, dtype=np.float64),
            MAX_CORRECTION,
            out,
        )
        return out


@jit
def _correct_kernel(feature, threshold, value, base, x, toa, max_correction, out):
    tree_ensemble.predict_kernel(feature, threshold, value, base, x, out)
    for r in range(x.shape[0]):
        pred = out[r]
        if not np.isfinite(pred):
            pred = 0.0
        out[r] = toa[r] - min(max(pred, -max_correction), max_correction)


def load_correction(n_channels: int, path: str | Path | None = None) -> ToaCorrection:
    """Load and check the model for a board with ``n_channels`` channels: the trees stored
    for this file's hash after an earlier check (no onnxruntime import), else onnxruntime,
    and the trees stored when numba agrees with it."""
    path = Path(path) if path is not None else default_model_path()
    if not path.is_file():
        raise ModelError(f"ToA correction model {path} not found")
    blob = path.read_bytes()
    sha256 = verified_models.digest(blob)
    want = n_toa_features(n_channels)
    stored = verified_models.load(path, sha256, VERIFIED_NAMES)
    if stored is not None and int(stored[0][-1]) == want:
        feature, threshold, value, base, _ = stored[0]
        value = value.astype(np.float32, copy=False)  # stored as float64 before 2026-12
        return ToaCorrection.verified(path, blob, (feature, threshold, value, float(base)))
    corr = _load_with_onnxruntime(n_channels, path, blob)
    if corr.trees is not None:
        arrays = (*corr.trees[:3], np.float64(corr.trees[3]), np.int64(want))
        verified_models.store(path, sha256, VERIFIED_NAMES, arrays, corr.metadata)
    return corr


def _load_with_onnxruntime(n_channels: int, path: Path, blob: bytes) -> ToaCorrection:
    import onnxruntime as ort

    opts = ort.SessionOptions()
    opts.intra_op_num_threads = 1
    opts.inter_op_num_threads = 1
    opts.log_severity_level = 3
    try:
        session = ort.InferenceSession(blob, sess_options=opts, providers=["CPUExecutionProvider"])
    except Exception as exc:  # onnxruntime's own errors: corrupt file, unsupported opset
        raise ModelError(f"ToA correction model {path} cannot be loaded: {exc}") from exc
    inputs, outputs = session.get_inputs(), [o.name for o in session.get_outputs()]
    want = n_toa_features(n_channels)
    if len(inputs) != 1 or inputs[0].name != INPUT_NAME or OUTPUT_NAME not in outputs:
        raise ModelError(
            f"ToA correction model {path}: expected input {INPUT_NAME!r} and output "
            f"{OUTPUT_NAME!r}, got {[i.name for i in inputs]} -> {outputs}"
        )
    shape = inputs[0].shape
    if len(shape) != 2 or shape[1] != want or inputs[0].type != "tensor(float)":
        raise ModelError(
            f"ToA correction model {path}: input must be float32 (batch, {want}) for "
            f"{n_channels} channels, got {inputs[0].type} {shape}"
        )
    return ToaCorrection(session, path, blob)


def build_correction(
    choice: str, n_channels: int, path: str | Path | None = None
) -> ToaCorrection | None:
    """``none``: no correction; ``auto``/``onnx``: the model, or one warning and None."""
    if choice == "none":
        return None
    try:
        return load_correction(n_channels, path)
    except ImportError as exc:
        log.warning("ToA correction unavailable (%s); using the uncorrected ToA", exc)
    except ModelError as exc:
        log.warning("%s; using the uncorrected ToA", exc)
    return None


def build_echo_timing(profile, toa_correction: str | None = None) -> EchoTiming:
    """The profile's step; ``toa_correction`` (auto|onnx|none) overrides the profile's.
    RF boards keep the MEMG ToA: the step works on envelopes."""
    spec = profile.echo_timing
    estimator = spec.estimator if profile.acquisition.signal == "envelope" else "none"
    correction = None
    if estimator != "none":
        correction = build_correction(
            toa_correction or spec.toa_correction, profile.geometry.n_channels
        )
    return EchoTiming(
        estimator, spec.half_window, profile.preprocess.blind_zone_samples, correction
    )
