"""Ablation of the echo association on the validation split (the paper's Table II and more).

    python -m tools.train.ablation_association            # after python -m tools.train.train_association

Methods, each giving one matched echo per channel (or none):
- ``alpha+munkres``: reference = the echo with the largest MEMG amplitude alpha; every other
  channel's echoes are matched to the reference channel's by the Hungarian algorithm on the
  Euclidean distance of standardised MEMG features; the echo paired with the reference wins.
- ``mlp+munkres``: the same with the MLP's highest score as the reference.
- ``toa_amp+mlp+contrastive``: a second net trained on [ToA, alpha] only; reference = highest
  score, per channel the echo nearest the reference in embedding space (paper eq. 19).
- ``mlp+contrastive``: the paper's method with the 8 MEMG features (no geometry).
- ``geometric``: the project's geometric associator alone.
- ``combined``: the runtime (``OnnxAssociator``): embedding-distance candidates, geometric guard.
Scores as defined in ``spiel_edge.measure.echo_labels``; 3-D error = |located - truth| over
acquisitions the method's matches can be located from (>= 3 channels, solve ok).
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
from scipy.optimize import linear_sum_assignment

from spiel_edge.measure.echo_labels import AssociationScore, score_association  # noqa: E402
from spiel_edge.pipeline.learned.associate_onnx import (  # noqa: E402
    OnnxAssociator,
    bench_scoring,
    candidate_mask,
    guarded_match,
    score_bonus,
)
from spiel_edge.pipeline.stages.associate import GeometricAssociator  # noqa: E402
from spiel_edge.pipeline.stages.features import FEATURE_NAMES, TOA_COLUMN  # noqa: E402
from spiel_edge.profile.schema import Profile, load_profile  # noqa: E402
from tools.train import association_model as ta

ALPHA_COLUMN = FEATURE_NAMES.index("alpha")
TOA_AMP_COLUMNS = (TOA_COLUMN, ALPHA_COLUMN)


def munkres_match(
    s: ta.Sample, ref: tuple[int, int], mean: np.ndarray, std: np.ndarray
) -> np.ndarray:
    z = (s.features - mean) / std
    rc, rk = ref
    matched = np.full(len(s.counts), -1, dtype=np.int64)
    matched[rc] = rk
    for c in range(len(s.counts)):
        if c == rc or s.counts[c] == 0:
            continue
        a, b = z[rc, : s.counts[rc]], z[c, : s.counts[c]]
        cost = np.linalg.norm(a[:, None, :] - b[None, :, :], axis=2)
        rows, cols = linear_sum_assignment(cost)
        hit = cols[rows == rk]
        matched[c] = int(hit[0]) if hit.size else -1
    return matched


def contrastive_match(s: ta.Sample, rows, score: np.ndarray, emb: np.ndarray) -> np.ndarray:
    matched = np.full(len(s.counts), -1, dtype=np.int64)
    if score.size == 0:
        return matched
    d = np.linalg.norm(emb - emb[int(np.argmax(score))], axis=1)
    for c in range(len(s.counts)):
        on_c = rows[0] == c
        if on_c.any():
            matched[c] = rows[1][on_c][np.argmin(d[on_c])]
    return matched


def alpha_reference(s: ta.Sample) -> tuple[int, int]:
    rows = s.rows()
    i = int(np.argmax(s.features[rows[2], rows[3], ALPHA_COLUMN]))
    return int(rows[2][i]), int(rows[3][i])


def method_matches(
    profile: Profile, s: ta.Sample, nets: dict, stats, guard: tuple[float, float, float], geometric
) -> dict:
    mean, std = stats
    rows, score, emb = ta.net_outputs(nets["mlp"], s)
    rows2, score2, emb2 = ta.net_outputs(nets["toa_amp"], s)
    mlp_ref = (
        (int(rows[0][np.argmax(score)]), int(rows[1][np.argmax(score)])) if score.size else (0, 0)
    )
    allowed = candidate_mask(s.features.shape[:2], rows, score, emb, guard[0])
    empty = np.full(len(s.counts), -1, dtype=np.int64)
    has_echo = score.size > 0
    return {
        "alpha+munkres": munkres_match(s, alpha_reference(s), mean, std) if has_echo else empty,
        "mlp+munkres": munkres_match(s, mlp_ref, mean, std) if has_echo else empty,
        "toa_amp+mlp+contrastive": contrastive_match(s, rows2, score2, emb2),
        "mlp+contrastive": contrastive_match(s, rows, score, emb),
        "geometric": s.geometric,
        "combined reference (paper's reference + guard)": guarded_match(
            geometric, s.features, s.counts, allowed, guard[1]
        ),
        "combined prior (geometric + score prior, the default)": geometric.candidates(
            s.features, s.counts, bonus_mm=score_bonus(s.features.shape[:2], rows, score, guard[2])
        )[0],
    }


def evaluate(
    profile: Profile, samples: list[ta.Sample], nets: dict, stats, guard: tuple[float, float, float]
) -> dict:
    """Per method: accuracy, F1, mean/median 3-D error and how many acquisitions were located."""
    geometric = GeometricAssociator(profile)
    per_method: dict[str, list[np.ndarray]] = {}
    for s in samples:
        for name, matched in method_matches(profile, s, nets, stats, guard, geometric).items():
            per_method.setdefault(name, []).append(matched)
    return {name: summarise(profile, samples, m) for name, m in per_method.items()}


def summarise(profile: Profile, samples: list[ta.Sample], matches: list[np.ndarray]) -> dict:
    listening = profile.geometry.listening_mask()
    sc = AssociationScore()
    for s, m in zip(samples, matches, strict=True):
        sc = sc + score_association(m, s.labels, listening)
    e = np.array([ta.position_error(profile, s, m) for s, m in zip(samples, matches, strict=True)])
    ok = np.isfinite(e)
    return {
        "accuracy": sc.accuracy,
        "f1": sc.f1,
        "channels": sc.channels,
        "mean_error_mm": float(e[ok].mean()) if ok.any() else float("nan"),
        "median_error_mm": float(np.median(e[ok])) if ok.any() else float("nan"),
        "located": int(ok.sum()),
        "acquisitions": len(e),
    }


def evaluate_runtime(profile: Profile, samples: list[ta.Sample], model_path: Path) -> dict:
    """The shipped artefact: ``OnnxAssociator`` (onnxruntime) on the same features."""
    assoc = OnnxAssociator(profile, model_path)
    return summarise(profile, samples, [assoc(s.features, s.counts) for s in samples])


def markdown_table(results: dict) -> str:
    lines = [
        "| method | accuracy | F1 | mean 3-D error (mm) | median (mm) | located |",
        "|---|---|---|---|---|---|",
    ]
    for name, r in results.items():
        lines.append(
            f"| {name} | {r['accuracy']:.4f} | {r['f1']:.4f} | {r['mean_error_mm']:.1f} | "
            f"{r['median_error_mm']:.1f} | {r['located']}/{r['acquisitions']} |"
        )
    return "\n".join(lines)


def run(
    profile: Profile,
    train_set,
    val_set,
    main_net: ta.EchoNet,
    seed: int,
    threshold: float,
    slack: float,
    weight: float,
) -> dict:
    """Train the [ToA, alpha] net and evaluate every method on ``val_set``."""
    toa_amp_net, _ = ta.train(train_set, val_set, columns=TOA_AMP_COLUMNS, seed=seed)
    x = np.concatenate([s.rows()[0] for s in train_set]).astype(np.float64)
    stats = (x.mean(0), np.where(x.std(0) > 1e-9, x.std(0), 1.0))
    return evaluate(
        profile,
        val_set,
        {"mlp": main_net, "toa_amp": toa_amp_net},
        stats,
        (threshold, slack, weight),
    )


def write_card(path: Path, profile: Profile, results: dict, info: dict) -> None:
    """The model card from the template beside this file, filled with this run's numbers."""
    bench = bench_scoring(n=3000, profile=profile, model_path=path.with_suffix(".onnx"))
    best = min(v for _, v in info["history"])
    text = CARD_TEMPLATE.format(
        profile=profile.name,
        toa_estimator=profile.memg.toa,
        delays=", ".join(f"{d:g}" for d in profile.geometry.delays()),
        val_xy=", ".join(f"({x:g}, {y:g})" for x, y in info["val_xy"]),
        best_loss=best,
        table=markdown_table(results),
        scoring=bench["scoring_us"]["median"],
        scoring_p99=bench["scoring_us"]["p99"],
        associate=bench["associate_us"]["median"],
        echoes=bench["echoes_per_acquisition"],
        **{k: v for k, v in info.items() if k not in ("val_xy", "history")},
    )
    path.write_text(text)


CARD_TEMPLATE = (Path(__file__).resolve().parent / "association_card.md.in").read_text()


def main(argv: list[str] | None = None) -> int:
    """Retrain (deterministically, same seed) and print the table: the card's numbers."""
    import argparse

    ap = argparse.ArgumentParser(description="association ablation on the validation split")
    ap.add_argument("--data", type=Path, default=ta.DEFAULT_DATA)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--split-salt", default=ta.SPLIT_SALT)
    args = ap.parse_args(argv)
    profile = load_profile("spiel-icra23")
    train_set, val_set = ta.split_by_position(
        ta.load_samples(args.data, profile), salt=args.split_salt
    )
    net, _ = ta.train(train_set, val_set, seed=args.seed)
    results = run(
        profile,
        train_set,
        val_set,
        net,
        args.seed,
        *ta.pick_guard(profile, net, train_set),
        ta.pick_score_weight(profile, net, train_set),
    )
    print(markdown_table(results))
    print(json.dumps(results, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
