"""The learned echo association's data, network and training steps (PaCE paper, section IV),
used by ``tools.train.train_association`` (training, export, card) and ``tools.train.ablation_association``.

Workstation tool (extra ``train``: torch, onnx). Features come from the project's own stages
(``Pipeline.process`` with the geometric associator, whose features are the runtime's), so
training and runtime features are identical; rerun after any change to the profile or stages.

Data: ``<data>/train_val`` + ``<data>/train_val_bg`` (spiel-csv with labels). The z = 90 mm
frames are excluded (mislabelled: their echoes fit z ~ 140-150 mm). Split by position: the
distinct (x, y) positions are hashed with ``--split-salt`` (``spiel_edge.measure.evaluate``'s split, so
``spiel-edge evaluate`` validates on the same positions) and ~``val_fraction`` of them held out at
every height, so validation positions are unseen xy. Labels: ``spiel_edge.measure.echo_labels``
(the echo nearest the ground-truth echo time within 1.5 samples is the target's).

Network: 8 -> 32 -> 32 -> 4 (ReLU after each: the embedding) -> 1 (sigmoid: the score), with the
feature standardisation (training mean/std) as buffers inside the graph. Loss per frame (batch =
one frame, all its echoes): 10 * BCE(score, label) + 1 * contrastive(distance to the reference),
reference = the target echo with the highest score; contrastive is Hadsell's (targets pulled to
the reference, others pushed beyond the margin). Adam lr 5e-4, early stopping on validation loss
(patience 5, min delta 0). Deterministic for a seed: single thread, deterministic algorithms.
"""

from __future__ import annotations

import io
import logging
import math
import os
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import nn

from spiel_edge.data import EXCLUDED_Z_MM
from spiel_edge.measure import evaluate
from spiel_edge.measure.echo_labels import (
    DEFAULT_TOLERANCE,
    AssociationScore,
    expected_toa,
    label_echoes,
    score_association,
)
from spiel_edge.pipeline import Pipeline
from spiel_edge.pipeline.learned.associate_onnx import candidate_mask, guarded_match, score_bonus
from spiel_edge.pipeline.stages.associate import GeometricAssociator
from spiel_edge.pipeline.stages.features import N_FEATURES, TOA_COLUMN
from spiel_edge.pipeline.stages.locate import locate
from spiel_edge.profile.schema import Profile
from spiel_edge.recordings.spiel_csv import iter_recordings, position_key, read_truth

log = logging.getLogger("train_association")

REPO = Path(__file__).resolve().parents[2]
DEFAULT_DATA = Path(
    os.environ.get("SPIEL_DATASET", REPO.parent / "shared" / "datasets" / "spiel-icra23")
)
DEFAULT_OUT = REPO / "spiel_edge" / "models"
OPSET = 17
MARGIN = 1.0
LAMBDA_BCE, LAMBDA_CONTRASTIVE = 10.0, 1.0
SPLIT_SALT = "spiel-edge"  # spiel_edge.measure.evaluate.split_by_position's default
SLACKS_MM = (0.0, 2.0, 4.0, 8.0, math.inf)
THRESHOLDS = (0.25, 0.5, 0.75, 1.0, 1.5, 2.0, 3.0, 5.0)  # embedding distance (margin = 1)


@dataclass
class Sample:
    """One acquisition: the pipeline's features, its labels and the truth."""

    name: str
    features: np.ndarray  # (channels, max_echoes, 8)
    counts: np.ndarray
    labels: np.ndarray  # (channels,) target echo index or -1
    truth_mm: np.ndarray
    geometric: np.ndarray  # the geometric associator's matched (channels,)
    frames: np.ndarray | None = None  # the raw acquisition, for the final stages' 3-D error
    background: np.ndarray | None = None

    @property
    def xy(self) -> tuple[float, float]:
        key = position_key(self.name)
        return (key[0], key[1])

    def rows(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Valid echoes as (x (n, 8), y (n,), channel (n,), echo index (n,))."""
        ch, k = np.nonzero(np.arange(self.features.shape[1])[None, :] < self.counts[:, None])
        y = (self.labels[ch] == k).astype(np.float32)
        return self.features[ch, k].astype(np.float32), y, ch, k


def load_samples(
    data: Path, profile: Profile, tolerance: float = DEFAULT_TOLERANCE
) -> list[Sample]:
    """Every labelled acquisition of ``data/train_val`` (z = 90 mm excluded) through the stages."""
    pipe = Pipeline(profile)
    out = []
    for rec in iter_recordings(data / "train_val", data / "train_val_bg"):
        key = position_key(rec.source)
        if rec.error is not None or key is None or key[2] in EXCLUDED_Z_MM:
            continue
        truth = read_truth(data / "train_val" / rec.source)
        r = pipe.process(rec.frames, rec.background)
        labels = label_echoes(r.features, r.counts, expected_toa(profile, truth), tolerance)
        geo = np.array([-1 if m is None else m for m in r.matched], dtype=np.int64)
        out.append(
            Sample(rec.source, r.features, r.counts, labels, truth, geo, rec.frames, rec.background)
        )
    return out


def split_by_position(samples: list[Sample], val_fraction: float = 0.3, salt: str = SPLIT_SALT):
    """(train, validation): whole (x, y) positions, all heights, by ``spiel-edge evaluate``'s split."""
    _, val_xy = evaluate.split_by_position([s.name for s in samples], val_fraction, salt)
    return [s for s in samples if s.xy not in val_xy], [s for s in samples if s.xy in val_xy]


class EchoNet(nn.Module):
    """The paper's Siamese MLP; ``columns`` picks the features it sees (ablation)."""

    def __init__(
        self, mean: np.ndarray, std: np.ndarray, columns: tuple[int, ...] = tuple(range(N_FEATURES))
    ):
        super().__init__()
        self.register_buffer("columns", torch.tensor(columns, dtype=torch.long))
        self.register_buffer("mean", torch.tensor(mean[list(columns)], dtype=torch.float32))
        self.register_buffer("std", torch.tensor(std[list(columns)], dtype=torch.float32))
        n = len(columns)
        self.embed = nn.Sequential(
            nn.Linear(n, 32), nn.ReLU(), nn.Linear(32, 32), nn.ReLU(), nn.Linear(32, 4), nn.ReLU()
        )
        self.head = nn.Linear(4, 1)

    def forward(self, features: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        x = (
            features
            if self.columns.numel() == N_FEATURES
            else features.index_select(1, self.columns)
        )
        e = self.embed((x - self.mean) / self.std)
        return torch.sigmoid(self.head(e)), e


def frame_loss(net: EchoNet, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """10 * BCE + contrastive for one frame's echoes (sums over echoes, as in the paper)."""
    score, emb = net(x)
    score = score[:, 0].clamp(1e-7, 1 - 1e-7)
    loss = LAMBDA_BCE * nn.functional.binary_cross_entropy(score, y, reduction="sum")
    pos = y > 0.5
    if pos.any():
        with torch.no_grad():
            ref = int(torch.nonzero(pos)[torch.argmax(score[pos])])
        d = torch.linalg.vector_norm(emb - emb[ref], dim=1)
        contrastive = torch.where(pos, d**2, torch.clamp(MARGIN - d, min=0.0) ** 2) / 2
        loss = loss + LAMBDA_CONTRASTIVE * contrastive.sum()
    return loss


def to_tensors(samples: list[Sample]) -> list[tuple[torch.Tensor, torch.Tensor]]:
    out = []
    for s in samples:
        x, y, _, _ = s.rows()
        if len(y):
            out.append((torch.from_numpy(x), torch.from_numpy(y)))
    return out


def seed_everything(seed: int) -> None:
    torch.manual_seed(seed)
    torch.use_deterministic_algorithms(True)
    torch.set_num_threads(1)


def train(
    train_set: list[Sample],
    val_set: list[Sample],
    *,
    columns: tuple[int, ...] = tuple(range(N_FEATURES)),
    seed: int = 0,
    max_epochs: int = 300,
    patience: int = 5,
    lr: float = 5e-4,
) -> tuple[EchoNet, list[tuple[float, float]]]:
    """Train with early stopping on the validation loss; returns the best net and the history."""
    seed_everything(seed)
    x_all = np.concatenate([s.rows()[0] for s in train_set]).astype(np.float64)
    std = x_all.std(0)
    net = EchoNet(x_all.mean(0), np.where(std > 1e-9, std, 1.0), columns)
    opt = torch.optim.Adam(net.parameters(), lr=lr)
    tr, va = to_tensors(train_set), to_tensors(val_set)
    gen = torch.Generator().manual_seed(seed)
    best, best_state, waited, history = float("inf"), None, 0, []
    for epoch in range(max_epochs):
        net.train()
        total = 0.0
        for i in torch.randperm(len(tr), generator=gen).tolist():
            opt.zero_grad()
            loss = frame_loss(net, *tr[i])
            loss.backward()
            opt.step()
            total += loss.item()
        net.eval()
        with torch.no_grad():
            val = sum(float(frame_loss(net, *f)) for f in va) / max(len(va), 1)
        history.append((total / len(tr), val))
        log.info("epoch %3d  train %.4f  val %.4f", epoch, total / len(tr), val)
        if val < best:  # min delta 0
            best, waited = val, 0
            best_state = {k: v.clone() for k, v in net.state_dict().items()}
        else:
            waited += 1
            if waited >= patience:
                break
    net.load_state_dict(best_state)
    net.eval()
    return net, history


def export_onnx(net: EchoNet, metadata: dict[str, str]) -> bytes:
    """The net as ONNX bytes: input ``features`` (batch, 8) float32, outputs ``score`` (batch, 1)
    and ``embedding`` (batch, 4); ``metadata`` goes into the model's metadata_props."""
    import onnx

    buf = io.BytesIO()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the TorchScript exporter's deprecation notice
        torch.onnx.export(
            net,
            torch.zeros(2, N_FEATURES),
            buf,
            dynamo=False,
            opset_version=OPSET,
            input_names=["features"],
            output_names=["score", "embedding"],
            dynamic_axes={
                "features": {0: "batch"},
                "score": {0: "batch"},
                "embedding": {0: "batch"},
            },
        )
    model = onnx.load_from_string(buf.getvalue())
    model.producer_name, model.producer_version = (
        "spiel-edge tools/train/train_association.py",
        torch.__version__,
    )
    for key, value in sorted(metadata.items()):
        onnx.helper.set_model_props(
            model, {**{p.key: p.value for p in model.metadata_props}, key: value}
        )
    onnx.checker.check_model(model)
    return model.SerializeToString()


def net_outputs(net: EchoNet, s: Sample):
    """(rows (channel, echo), score (n,), embedding (n, 4)) as the runtime computes them."""
    _, _, ch, k = s.rows()
    with torch.no_grad():
        score, emb = net(torch.from_numpy(s.features[ch, k].astype(np.float32)))
    return (ch, k), score.numpy()[:, 0], emb.numpy()


def pick_guard(profile: Profile, net: EchoNet, samples: list[Sample]) -> tuple[float, float]:
    """(distance threshold, cost slack) with the best guarded accuracy on ``samples`` (the
    training split); ties go to the larger values, which leave more to the geometry."""
    geometric = GeometricAssociator(profile)
    outputs = [net_outputs(net, s) for s in samples]
    best = (-1.0, 0.0, 0.0)
    for threshold in THRESHOLDS:
        for slack in SLACKS_MM:
            total = AssociationScore()
            for s, (rows, score, emb) in zip(samples, outputs, strict=True):
                allowed = candidate_mask(s.features.shape[:2], rows, score, emb, threshold)
                matched = guarded_match(geometric, s.features, s.counts, allowed, slack)
                total = total + score_association(matched, s.labels)
            log.info(
                "threshold %.2f slack %.1f mm: training accuracy %.4f",
                threshold,
                slack,
                total.accuracy,
            )
            best = max(best, (total.accuracy, threshold, slack))
    return best[1], best[2]


def position_error(profile: Profile, s: Sample, matched: np.ndarray) -> float:
    """|located - truth| in mm, NaN when the matches cannot be located: through the runtime's
    final stages (echo timing, echo quality, locate) when the sample holds its frames."""
    g = profile.geometry
    use = matched >= 0
    if use.sum() < 3:
        return float("nan")
    if s.frames is not None:
        pipe = _final_stages(profile)
        located = pipe.locate_target(s.features, matched, 0.0, s.frames, s.background)
        return (
            float("nan")
            if located is None
            else float(np.linalg.norm(located[0].position_mm - s.truth_mm))
        )
    toa = s.features[np.arange(len(matched)), np.maximum(matched, 0), TOA_COLUMN]
    paths = (toa - g.delays()) * profile.mm_per_sample
    pos, _, ok = locate(paths, g.channels_mm, g.emitter_mm, g.facing, use)
    return float(np.linalg.norm(pos - s.truth_mm)) if ok else float("nan")


_FINAL_STAGES: dict[int, Pipeline] = {}


def _final_stages(profile: Profile) -> Pipeline:
    """One pipeline per profile object for position_error (its echo timing loads the model)."""
    if id(profile) not in _FINAL_STAGES:
        _FINAL_STAGES[id(profile)] = Pipeline(profile)
    return _FINAL_STAGES[id(profile)]


SCORE_WEIGHTS_MM = (0.0, 1.0, 2.0, 4.0, 8.0, 16.0)


def pick_score_weight(profile: Profile, net: EchoNet, samples: list[Sample]) -> float:
    """The prior weight (mm per unit of score logit) with the lowest mean 3-D error on
    ``samples`` (the training split); 0 is the geometric associator itself."""
    geometric = GeometricAssociator(profile)
    outputs = [net_outputs(net, s) for s in samples]
    best = (math.inf, 0.0)
    for weight in SCORE_WEIGHTS_MM:
        errors = []
        for s, (rows, score, _) in zip(samples, outputs, strict=True):
            bonus = score_bonus(s.features.shape[:2], rows, score, weight)
            errors.append(
                position_error(
                    profile, s, geometric.candidates(s.features, s.counts, bonus_mm=bonus)[0]
                )
            )
        mean = float(np.nanmean(errors))
        log.info("score weight %.1f mm: training mean 3-D error %.2f mm", weight, mean)
        best = min(best, (mean, weight))
    return best[1]


def reference_inputs(samples: list[Sample], n_real: int = 12, seed: int = 0) -> np.ndarray:
    """Fixed test inputs: real feature rows plus standardised-scale random ones."""
    rows = np.concatenate([s.rows()[0] for s in samples])
    rng = np.random.default_rng(seed)
    real = rows[rng.choice(len(rows), n_real, replace=False)]
    noise = rows.mean(0) + rows.std(0) * rng.standard_normal((4, rows.shape[1]))
    return np.concatenate([real, noise]).astype(np.float32)


def reference_outputs(net: EchoNet, x: np.ndarray) -> dict:
    with torch.no_grad():
        score, emb = net(torch.from_numpy(x))
    return {
        "features": x.tolist(),
        "score": score.numpy().tolist(),
        "embedding": emb.numpy().tolist(),
    }
