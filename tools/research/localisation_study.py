"""Where the per-target localisation error comes from, and what generalises (docs/localisation.md).

    python -m tools.research.localisation_study [--data DIR] [--cache FILE] [--trees] [--recipe]

Workstation tool (needs the ``train`` extra: scipy, and scikit-learn for ``--trees``).
Collects the shipped pipeline's per-channel ToAs (``tools.research.localisation_data``), then prints
markdown tables: the ToA error against the labelled position's ideal ToA (bias, noise,
outliers, by height; between- and within-pose parts), the 3-D error by echo category, the
geometry's dilution, and every variant's 3-D error **out of fold** on the training positions
(3 folds by (x, y) position: everything fitted on two, scored on the third) and on the
validation positions (fitted on all training positions). ``--trees`` also retrains the
learned ToA correction per fold (slow: minutes), which is what shows whether it overfits;
``--recipe`` retrains it as shipped (its own rows, ``tools.train.toa_correction_data``) on all
training positions, without and with a path scale, and scores it on the same rows.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from spiel_edge.profile.schema import load_profile
from tools.research.localisation_data import load_or_collect, solve_all
from tools.research.localisation_fits import (
    bias_and_noise,
    fit_delays_and_scale,
    position_folds,
    position_sd_mm,
)

DEFAULT_DATA = Path("/work/shared/datasets/spiel-icra23")
INLIER = 1.5  # samples: a matched echo further than this from the ideal ToA is a wrong echo
# the shipped correction's settings (tools.train.train_toa_correction.TREES; that module needs torch)
TREES = {"max_depth": 3, "n_estimators": 400, "learning_rate": 0.05, "random_state": 0}
SETS = [(True, False), (True, True), (False, False), (False, True)]  # (background, validation)


def metrics(c, pos) -> list[str]:
    """Per set: z <= 180 mean / median (mm), within 30 mm (all heights), z = 220 mean."""
    err = np.linalg.norm(pos - c["truth"], axis=1)
    z = c["truth"][:, 2]
    out = []
    for bg, val in SETS:
        s = (c["bg"] == bg) & (c["is_val"] == val)
        near = s & (z <= 180) & np.isfinite(err)
        far = s & (z == 220) & np.isfinite(err)
        w30 = np.mean(np.where(np.isfinite(err[s]), err[s], np.inf) < 30)
        out.append(
            f"{err[near].mean():.2f} / {np.median(err[near]):.2f}, {100 * w30:.1f} %, {err[far].mean():.1f}"
        )
    return out


def table_row(name: str, cells: list[str]) -> str:
    return f"| {name} | " + " | ".join(cells) + " |"


HEADER = (
    "| variant | bg, train OOF | bg, val | no bg, train OOF | no bg, val |\n|---|---|---|---|---|"
)


def out_of_fold(c, fit_and_predict) -> np.ndarray:
    """ToA minus delay (ideal-equivalent samples) for every row: training rows from the fold
    models, validation rows from the model fitted on all training rows."""
    train = ~c["is_val"]
    folds = np.where(train, position_folds(c["xy"]), -1)
    out = np.full(c["refined"].shape, np.nan)
    for f in (0, 1, 2, -1):
        fit = train & (folds != f) if f >= 0 else train
        pred = folds == f if f >= 0 else c["is_val"]
        out[pred] = fit_and_predict(fit, pred)
    return out


def delays_variant(c, toa_key: str, scale: bool):
    def fp(fit, pred):
        inl = np.abs(c[toa_key][fit] - c["delays"] - c["ideal"][fit]) < INLIER
        a, k = fit_delays_and_scale(c[toa_key][fit], c["ideal"][fit], inl, scale=scale)
        return (c[toa_key][pred] - a) / k

    return fp


def trees_variant(c, scale: bool):
    from sklearn.ensemble import GradientBoostingRegressor

    def fp(fit, pred):
        ref, ideal, feats = c["refined"], c["ideal"], c["feats"]
        inl = np.abs(ref[fit] - c["delays"] - ideal[fit]) < INLIER
        a, k = fit_delays_and_scale(ref[fit], ideal[fit], inl, scale=scale)
        target = ref[fit] - (a + k * ideal[fit])
        ok = np.isfinite(target) & (np.abs(target) < INLIER) & np.all(np.isfinite(feats[fit]), 2)
        model = GradientBoostingRegressor(**TREES).fit(feats[fit][ok], target[ok])
        rows = np.all(np.isfinite(feats[pred]), 2)
        corr = np.zeros(rows.shape)
        corr[rows] = np.clip(model.predict(feats[pred][rows]), -1.5, 1.5)
        return (ref[pred] - corr - a) / k

    return fp


def toa_section(c) -> None:
    z = c["truth"][:, 2]
    print("\n### ToA error against the labelled position (samples; inliers |e| < 1.5)\n")
    print("| ToA | set | z | bias per channel | sd per channel | wrong echo | no echo |")
    print("|---|---|---|---|---|---|---|")
    for key in ("refined", "corrected"):
        res = c[key] - c["delays"] - c["ideal"]
        for bg, val in SETS:
            for zz in (100, 180, 220):
                s = (c["bg"] == bg) & (c["is_val"] == val) & (z == zz)
                r = res[s]
                inl = np.where(np.abs(r) < INLIER, r, np.nan)
                wrong = np.mean(np.isfinite(r) & (np.abs(r) >= INLIER))
                name = _set_name(bg, val)
                print(
                    f"| {key} | {name} | {zz} | {np.round(np.nanmean(inl, 0), 2)} | "
                    f"{np.round(np.nanstd(inl, 0), 2)} | {100 * wrong:.1f} % | "
                    f"{100 * np.mean(np.isnan(r)):.1f} % |"
                )
    print("\n### Bias against noise: inlier ToA error split by pose (samples)\n")
    print("| ToA | set | total sd | between poses | within a pose |")
    print("|---|---|---|---|---|")
    pose = np.array([f"{x[0]:g},{x[1]:g},{zz:g}" for x, zz in zip(c["xy"], z, strict=True)])
    for key in ("refined", "corrected"):
        res = c[key] - c["delays"] - c["ideal"]
        res = np.where(np.abs(res) < INLIER, res, np.nan)
        for bg, val in SETS:
            s = (c["bg"] == bg) & (c["is_val"] == val)
            tot, between, within = bias_and_noise(res[s], pose[s])
            print(f"| {key} | {_set_name(bg, val)} | {tot:.3f} | {between:.3f} | {within:.3f} |")


def category_section(c) -> None:
    z = c["truth"][:, 2]
    res = c["corrected"] - c["delays"] - c["ideal"]
    err = np.linalg.norm(c["pos"] - c["truth"], axis=1)
    wrong = (np.isfinite(res) & (np.abs(res) >= INLIER)).any(1)
    three = np.isnan(res).any(1) & ~wrong
    print("\n### Shipped pipeline by echo category (n, mean mm, within 30 mm)\n")
    print("| set | z | 4 right echoes | 3 right, one missing | a wrong echo |")
    print("|---|---|---|---|---|")
    for bg, val in SETS:
        for zz in (100, 180, 220):
            s = (c["bg"] == bg) & (c["is_val"] == val) & (z == zz) & np.isfinite(err)
            cells = []
            for cat in (~wrong & ~three, three, wrong):
                t = s & cat
                cells.append(
                    f"{t.sum()}, {np.mean(err[t]):.1f}, {100 * np.mean(err[t] < 30):.0f} %"
                    if t.any()
                    else "0"
                )
            print(f"| {_set_name(bg, val)} | {zz} | " + " | ".join(cells) + " |")


def dilution_section(profile) -> None:
    g = profile.geometry
    print("\n### Geometry: position sd (x, y, z mm) for independent ToA errors of sd s\n")
    print("| position (mm) | s = 0.25 | s = 0.35 | s = 0.45 samples |")
    print("|---|---|---|---|")
    for p in ((0, 0, 100), (0, 0, 220), (80, 0, 180), (80, 80, 220)):
        cells = [
            str(
                np.round(
                    position_sd_mm(
                        np.array(p, float), g.channels_mm, g.emitter_mm, s * profile.mm_per_sample
                    ),
                    1,
                )
            )
            for s in (0.25, 0.35, 0.45)
        ]
        print(f"| {p} | " + " | ".join(cells) + " |")


def _set_name(bg: bool, val: bool) -> str:
    return ("bg" if bg else "no bg") + (", val" if val else ", train")


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=DEFAULT_DATA)
    ap.add_argument("--cache", type=Path, default=Path("localisation_cases.npz"))
    ap.add_argument("--trees", action="store_true", help="retrain the ToA correction per fold")
    ap.add_argument(
        "--recipe", action="store_true", help="retrain it as shipped, without and with a path scale"
    )
    args = ap.parse_args(argv)
    profile = load_profile("spiel-icra23")
    c = load_or_collect(args.data, profile, args.cache)
    toa_section(c)
    category_section(c)
    dilution_section(profile)
    from tools.research import localisation_variants as lv

    print("\n### Variants: z <= 180 mean / median, within 30 mm (all heights), z = 220 mean\n")
    print(HEADER)
    print(table_row("shipped pipeline (training: in sample)", metrics(c, c["pos"])))
    w = c["weights"]
    memg = out_of_fold(c, delays_variant(c, "memg", False))
    print(
        table_row(
            "MEMG mode (no echo timing, no echo-quality shift), delays refitted",
            metrics(c, solve_all(profile, memg, w)),
        )
    )
    base = out_of_fold(c, delays_variant(c, "refined", False))
    print(table_row("estimator, delays refitted", metrics(c, solve_all(profile, base, w))))
    scaled = out_of_fold(c, delays_variant(c, "refined", True))
    print(table_row("estimator, delays + path scale", metrics(c, solve_all(profile, scaled, w))))
    for name, fp in lv.geometry_variants(c, profile):
        print(table_row(name, metrics(c, fp())))
    if args.trees:
        base = out_of_fold(c, trees_variant(c, False))
        print(
            table_row(
                "estimator + trees (retrained per fold)", metrics(c, solve_all(profile, base, w))
            )
        )
        both = out_of_fold(c, trees_variant(c, True))
        print(table_row("estimator + path scale + trees", metrics(c, solve_all(profile, both, w))))
    for name, pos in lv.solve_variants(c, profile, base):
        print(table_row(name, metrics(c, pos)))
    if args.recipe:
        for name, pos in lv.shipped_recipe(c, profile, args.data, TREES):
            print(table_row(name, metrics(c, pos)))


if __name__ == "__main__":
    main()
