"""Learned echo association (PaCE paper, section IV) with a geometric guard.

The model (``spiel_edge/models/association.onnx``, card beside it) maps each echo's 8 features
to a target score and a 4-D embedding; one call per acquisition scores every echo. The MLP
runs in numba (:mod:`spiel_edge.pipeline.learned.mlp`) when its graph has the known shape and agreed
with onnxruntime on a probe batch (checked once per model file, then stored by its hash:
:mod:`spiel_edge.pipeline.learned.verified_models`; such a load never imports onnxruntime), else in
onnxruntime (``engine``).
Two ways to use it (``mode``):

- ``prior`` (default): the geometric search over all combinations, with each echo's score as a
  soft prior: a combination's cost falls by ``score_weight_mm`` times the mean logit of its
  echoes' scores. Geometry still decides what is consistent; the net breaks ties between
  consistent combinations (target vs. multipath or clutter). Weight 0 is the geometric
  associator, so the weight chosen on the training split cannot do worse there by design.
- ``reference`` (the paper's): the highest-scoring echo is the reference; echoes within the
  model's embedding-distance threshold of it (eq. 19) are the candidates, and the geometric
  search picks the consistent combination among them; without one, or when the unrestricted
  search is cheaper by more than the model's cost slack, the unrestricted search decides.

Threshold, slack and weight travel in the model's metadata (chosen on the training split).
Built by :func:`spiel_edge.pipeline.factory.build_associator`; a missing or unusable model
raises ModelError there, which becomes a warning and geometric association.
"""

from __future__ import annotations

import logging
import math
import time
from importlib import resources
from pathlib import Path

import numpy as np

from spiel_edge.errors import InputError, ModelError
from spiel_edge.pipeline.learned import mlp, verified_models
from spiel_edge.pipeline.stages.associate import GeometricAssociator
from spiel_edge.pipeline.stages.features import N_FEATURES, TOA_COLUMN
from spiel_edge.profile.schema import Profile

log = logging.getLogger(__name__)

INPUT_NAME = "features"
OUTPUTS = ("score", "embedding")
# used when the model's metadata lacks "spiel.distance_threshold" / "spiel.cost_slack_mm"
DEFAULT_DISTANCE_THRESHOLD = 1.0
DEFAULT_COST_SLACK_MM = math.inf
DEFAULT_SCORE_WEIGHT_MM = 1.0  # the shipped model carries its own (spiel.score_weight_mm)
MODES = ("prior", "reference")


def default_model_path() -> Path:
    return Path(str(resources.files("spiel_edge") / "models" / "association.onnx"))


def load_session(path: str | Path):
    """An onnxruntime session for one small core, checked for the association interface."""
    import onnxruntime as ort

    path = Path(path)
    if not path.is_file():
        raise ModelError(f"association model {path} not found")
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = 1
    opts.inter_op_num_threads = 1
    opts.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    opts.log_severity_level = 3  # errors only: a bad file is reported through ModelError
    # a few-kB model scored on a handful of rows: onnxruntime's arena and memory-pattern
    # planner would reserve far more than the model ever uses (docs/performance.md)
    opts.enable_cpu_mem_arena = False
    opts.enable_mem_pattern = False
    try:
        session = ort.InferenceSession(
            path.read_bytes(), sess_options=opts, providers=["CPUExecutionProvider"]
        )
    except Exception as exc:  # onnxruntime raises its own untyped errors for corrupt files
        raise ModelError(f"association model {path} cannot be loaded: {exc}") from exc
    _check_interface(session, path)
    return session


def load_model(path: Path) -> tuple:
    """``(session or None, MLP weights or None, metadata)``: the weights verified earlier for
    this file's hash without onnxruntime; else a session, and the weights when the graph has
    the known shape and agrees with onnxruntime on a probe batch (then stored for next time)."""
    if not path.is_file():
        raise ModelError(f"association model {path} not found")
    blob = path.read_bytes()
    sha256 = verified_models.digest(blob)
    stored = verified_models.load(path, sha256, mlp.WEIGHT_NAMES)
    if stored is not None:
        return None, stored[0], stored[1]
    session = load_session(path)
    metadata = dict(session.get_modelmeta().custom_metadata_map)
    weights = verify_mlp(session, blob, path)
    if weights is not None:
        verified_models.store(path, sha256, mlp.WEIGHT_NAMES, weights, metadata)
    return session, weights, metadata


def verify_mlp(session, blob: bytes, path: Path) -> tuple | None:
    """The MLP weights when the graph has the known shape and numba agrees with onnxruntime
    within mlp.AGREEMENT on a probe batch around the training statistics; else None."""
    try:
        weights = mlp.read_mlp(blob)
    except (ModelError, ValueError, IndexError) as exc:
        log.info("association model %s runs in onnxruntime (%s)", path, exc)
        return None
    mean, std = weights[0].astype(np.float64), np.abs(weights[1].astype(np.float64))
    probe = mean + std * np.random.default_rng(0).normal(0.0, 1.5, (256, N_FEATURES))
    x = np.ascontiguousarray(probe, dtype=np.float32)
    score, embedding = mlp.evaluate(x, weights)
    ref_score, ref_embedding = session.run(list(OUTPUTS), {INPUT_NAME: x})
    gap = max(
        float(np.max(np.abs(score - ref_score[:, 0]))),
        float(np.max(np.abs(embedding - ref_embedding))),
    )
    if not gap <= mlp.AGREEMENT:
        log.info("association model %s runs in onnxruntime (numba differs by %.2g)", path, gap)
        return None
    return weights


def _check_interface(session, path: Path) -> None:
    inputs = session.get_inputs()
    if len(inputs) != 1 or inputs[0].name != INPUT_NAME:
        raise ModelError(
            f"association model {path}: expected one input {INPUT_NAME!r}, got {[i.name for i in inputs]}"
        )
    shape = inputs[0].shape
    if len(shape) != 2 or shape[1] != N_FEATURES or isinstance(shape[0], int) and shape[0] != -1:
        raise ModelError(
            f"association model {path}: input {INPUT_NAME!r} must be (batch, {N_FEATURES}) "
            f"with a dynamic batch axis, got {shape}"
        )
    if inputs[0].type != "tensor(float)":
        raise ModelError(f"association model {path}: input must be float32, got {inputs[0].type}")
    names = {o.name for o in session.get_outputs()}
    if not set(OUTPUTS) <= names:
        raise ModelError(
            f"association model {path}: outputs {sorted(names)} lack {sorted(set(OUTPUTS) - names)}"
        )


def echo_rows(
    features: np.ndarray, counts: np.ndarray, listening: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """(channel, echo) indices of the echoes to score: present, listening, finite ToA."""
    k_max = features.shape[1]
    valid = (np.arange(k_max)[None, :] < counts[:, None]) & listening[:, None]
    valid &= np.isfinite(features[:, :, TOA_COLUMN])
    return np.nonzero(valid)


def candidate_mask(
    shape: tuple[int, int],
    rows: tuple[np.ndarray, np.ndarray],
    score: np.ndarray,
    embedding: np.ndarray,
    threshold: float,
) -> np.ndarray:
    """(channels, max_echoes) bool: echoes within ``threshold`` embedding distance of the
    reference (the highest-scoring echo), which is always a candidate."""
    allowed = np.zeros(shape, dtype=np.bool_)
    if score.size == 0:
        return allowed
    ref = int(np.argmax(score))
    d = np.sqrt(((embedding - embedding[ref]) ** 2).sum(axis=1))
    allowed[rows[0], rows[1]] = d <= threshold
    return allowed


def score_bonus(
    shape: tuple[int, int], rows: tuple[np.ndarray, np.ndarray], score: np.ndarray, weight_mm: float
) -> np.ndarray:
    """(channels, max_echoes) cost bonus in mm: ``weight_mm`` times each echo's score logit."""
    bonus = np.zeros(shape)
    p = np.clip(score.astype(np.float64), 1e-4, 1.0 - 1e-4)
    bonus[rows[0], rows[1]] = weight_mm * np.log(p / (1.0 - p))
    return bonus


def guarded_match(
    geometric: GeometricAssociator,
    features: np.ndarray,
    counts: np.ndarray,
    allowed: np.ndarray,
    slack_mm: float = math.inf,
) -> np.ndarray:
    """The best geometrically consistent combination among the candidates, unless the
    unrestricted search finds one cheaper by more than ``slack_mm`` (then the net most likely
    left the target's echo out) or the candidates hold no consistent combination at all."""
    matched, cost = geometric.candidates(features, counts, allowed)
    if math.isfinite(cost) and math.isinf(slack_mm):
        return matched
    free, free_cost = geometric.candidates(features, counts)
    return matched if math.isfinite(cost) and cost <= free_cost + slack_mm else free


class OnnxAssociator:
    """``associator(features, counts) -> matched`` with the learned model and a geometric guard."""

    name = "onnx"

    def __init__(
        self,
        profile: Profile,
        model_path: str | Path | None = None,
        *,
        distance_threshold: float | None = None,
        cost_slack_mm: float | None = None,
        score_weight_mm: float | None = None,
        mode: str = "prior",
    ):
        if mode not in MODES:
            raise InputError(f"mode must be one of {MODES}, got {mode!r}")
        self.mode = mode
        self.model_path = Path(model_path) if model_path is not None else default_model_path()
        self.session, self.mlp, meta = load_model(self.model_path)
        self.engine = "onnxruntime" if self.mlp is None else "numba"
        self.geometric = GeometricAssociator(profile)
        self.listening = np.asarray(profile.geometry.listening_mask(), dtype=np.bool_)
        self.n_channels = profile.geometry.n_channels
        if distance_threshold is None:
            distance_threshold = float(
                meta.get("spiel.distance_threshold", DEFAULT_DISTANCE_THRESHOLD)
            )
        if cost_slack_mm is None:
            cost_slack_mm = float(meta.get("spiel.cost_slack_mm", DEFAULT_COST_SLACK_MM))
        if score_weight_mm is None:
            score_weight_mm = float(meta.get("spiel.score_weight_mm", DEFAULT_SCORE_WEIGHT_MM))
        self.distance_threshold, self.cost_slack_mm = distance_threshold, cost_slack_mm
        self.score_weight_mm = score_weight_mm
        log.debug(
            "association model %s loaded (%s; threshold %.3g, slack %.3g mm)",
            self.model_path,
            self.engine,
            distance_threshold,
            cost_slack_mm,
        )

    def score(self, features: np.ndarray, counts: np.ndarray):
        """One ``run`` over every echo: (rows, score (n,), embedding (n, 4))."""
        features = np.asarray(features)
        counts = np.asarray(counts, dtype=np.int64)
        if (
            features.ndim != 3
            or features.shape[0] != self.n_channels
            or features.shape[2] != N_FEATURES
        ):
            raise InputError(
                f"features must be ({self.n_channels}, max_echoes, {N_FEATURES}), got {features.shape}"
            )
        rows = echo_rows(features, counts, self.listening)
        x = np.ascontiguousarray(features[rows], dtype=np.float32)
        if x.shape[0] == 0:
            return rows, np.zeros(0, np.float32), np.zeros((0, 4), np.float32)
        if self.mlp is not None:
            score, embedding = mlp.evaluate(x, self.mlp)
            return rows, score, embedding
        score, embedding = self.session.run(list(OUTPUTS), {INPUT_NAME: x})
        return rows, score[:, 0], embedding

    def kernel_constants(self) -> dict | None:
        """The compiled path's constants (``pipeline/compiled/abi.py``): the geometric
        search's with the MLP as its score prior; None in ``reference`` mode or with the model
        in onnxruntime (then the staged path runs)."""
        if self.mode != "prior" or self.mlp is None:
            return None
        return {
            **self.geometric.kernel_constants(),
            "prior": "mlp",
            "score_weight": self.score_weight_mm,
            **dict(zip(mlp.WEIGHTS, self.mlp, strict=True)),
        }

    def bonus(self, features: np.ndarray, counts: np.ndarray) -> np.ndarray:
        """The score prior as a (channels, max_echoes) cost bonus in mm (the scene stage)."""
        rows, score, _ = self.score(features, counts)
        return score_bonus(np.shape(features)[:2], rows, score, self.score_weight_mm)

    def __call__(self, features: np.ndarray, counts: np.ndarray) -> np.ndarray:
        rows, score, embedding = self.score(features, counts)
        if self.mode == "prior":
            return self.geometric.candidates(
                features,
                counts,
                bonus_mm=score_bonus(np.shape(features)[:2], rows, score, self.score_weight_mm),
            )[0]
        allowed = candidate_mask(
            np.shape(features)[:2], rows, score, embedding, self.distance_threshold
        )
        return guarded_match(self.geometric, features, counts, allowed, self.cost_slack_mm)


def bench_scoring(
    n: int = 2000, profile: Profile | None = None, model_path: str | Path | None = None
) -> dict:
    """Median and p99 wall time (us) of scoring one acquisition (the ``run`` call with its
    input packing) and of the whole association, over the vendored recordings."""
    from spiel_edge.data import load_subset
    from spiel_edge.pipeline.staged import Pipeline
    from spiel_edge.profile.schema import load_profile

    profile = profile or load_profile("spiel-icra23")
    assoc = OnnxAssociator(profile, model_path)
    pipe = Pipeline(profile, assoc)
    data = load_subset()
    inputs = []
    for i in range(min(len(data), 64)):
        r = pipe.process(data.frames[i], data.backgrounds[i])
        inputs.append((r.features, r.counts))
    times = {"scoring_us": [], "associate_us": []}
    for i in range(n):
        f, c = inputs[i % len(inputs)]
        t0 = time.perf_counter_ns()
        assoc.score(f, c)
        t1 = time.perf_counter_ns()
        assoc(f, c)
        t2 = time.perf_counter_ns()
        times["scoring_us"].append((t1 - t0) / 1e3)
        times["associate_us"].append((t2 - t1) / 1e3)
    out: dict = {"n": n, "echoes_per_acquisition": float(np.mean([c.sum() for _, c in inputs]))}
    for key, values in times.items():
        out[key] = {"median": float(np.median(values)), "p99": float(np.percentile(values, 99))}
    return out
