"""The geometry and solve variants of ``tools.research.localisation_study`` (docs/localisation.md).

Geometry: the emitter's position, or the receivers' x and y, refitted with the delays on the
labelled training positions (robust least squares, a Gaussian prior of ``prior_mm`` towards
the profile's values: few positions, so regularised). Solve: weights, an angle-dependent ToA
bias model applied at the estimated position, and dropping the least trusted channel when four
channels disagree. Every variant is fitted out of fold as in the study.
"""

from __future__ import annotations

import numpy as np

from spiel_edge.pipeline.stages.locate import locate
from tools.research.localisation_fits import position_folds

INLIER = 1.5


def _fit_geometry(c, fit, profile, part: str, prior_mm: float):
    from scipy.optimize import least_squares

    g = profile.geometry
    ch0, em0 = np.asarray(g.channels_mm, float), np.asarray(g.emitter_mm, float)
    d0 = np.asarray(c["delays"], float)
    toa, truth = c["refined"][fit], c["truth"][fit]
    ok = np.abs(toa - d0 - c["ideal"][fit]) < INLIER
    n_geo = 3 if part == "emitter" else 2 * (len(ch0) - 1)

    def unpack(theta):
        ch, em = ch0.copy(), em0.copy()
        if part == "emitter":
            em = em0 + theta[len(d0) :]
        else:
            ch[1:, :2] += theta[len(d0) :].reshape(-1, 2)
        return theta[: len(d0)], em, ch

    def residual(theta):
        d, em, ch = unpack(theta)
        paths = np.linalg.norm(truth - em, axis=1)[:, None] + np.linalg.norm(
            truth[:, None, :] - ch[None], axis=2
        )
        r = (toa - d - paths / profile.mm_per_sample)[ok]
        # prior: prior_mm of offset costs as much as one echo off by 0.3 samples, times sqrt(n)
        prior = theta[len(d0) :] / prior_mm * 0.3 * np.sqrt(ok.sum()) / 20.0
        return np.r_[r, prior]

    theta = least_squares(residual, np.r_[d0, np.zeros(n_geo)], loss="huber", f_scale=0.5).x
    return unpack(theta)


def _solve_with(c, rows, profile, d, em, ch):
    out = np.full((rows.size, 3), np.nan)
    fa = np.asarray(profile.geometry.facing, float)
    for j, i in enumerate(rows):
        paths = (c["refined"][i] - d) * profile.mm_per_sample
        use = np.isfinite(paths)
        if use.sum() >= 3:
            p, _, ok = locate(paths, ch, em, fa, use, weights=c["weights"][i])
            if ok:
                out[j] = p
    return out


def geometry_variants(c, profile):
    def run(part, prior_mm):
        pos = np.full((len(c["refined"]), 3), np.nan)
        train = ~c["is_val"]
        folds = np.where(train, position_folds(c["xy"]), -1)
        for f in (0, 1, 2, -1):
            fit = train & (folds != f) if f >= 0 else train
            pred = np.flatnonzero(folds == f if f >= 0 else c["is_val"])
            d, em, ch = _fit_geometry(c, fit, profile, part, prior_mm)
            pos[pred] = _solve_with(c, pred, profile, d, em, ch)
        return pos

    for part in ("emitter", "receivers x, y"):
        for prior in (1.0, 3.0):
            yield (
                f"estimator, delays + {part} (prior {prior:g} mm)",
                lambda p=part, q=prior: run(p, q),
            )


def _angle_features(pos, ch, em, n):
    to_e, to_r = pos - em, pos - ch[n]
    cos_e = to_e[:, 2] / np.linalg.norm(to_e, axis=1)
    cos_r = to_r[:, 2] / np.linalg.norm(to_r, axis=1)
    return np.c_[np.ones(len(pos)), 1 - cos_e, 1 - cos_r, (1 - cos_r) ** 2]


def angle_bias(c, profile, toa, lam: float = 1.0):
    """ToA bias per channel as a ridge-regularised function of the angles at the emitter and
    the receiver, fitted at the labelled positions, applied (twice) at the estimated one."""
    from tools.research.localisation_data import solve_all

    g = profile.geometry
    ch, em = np.asarray(g.channels_mm, float), np.asarray(g.emitter_mm, float)
    res = toa - c["ideal"]
    res = np.where(np.abs(res) < INLIER, res, np.nan)
    start = solve_all(profile, toa, c["weights"])
    out = start.copy()
    train = ~c["is_val"]
    folds = np.where(train, position_folds(c["xy"]), -1)
    for f in (0, 1, 2, -1):
        fit = train & (folds != f) if f >= 0 else train
        rows = np.flatnonzero(folds == f if f >= 0 else c["is_val"])
        coef = []
        for n in range(ch.shape[0]):
            x = _angle_features(c["truth"][fit], ch, em, n)
            y = res[fit, n]
            m = np.isfinite(y)
            reg = lam * m.sum() / 100 * np.diag([0.0, 1, 1, 1]) + 1e-8 * np.eye(4)
            coef.append(np.linalg.solve(x[m].T @ x[m] + reg, x[m].T @ y[m]))
        est = start[rows]
        for _ in range(2):
            good = np.all(np.isfinite(est), 1)
            corr = np.zeros((rows.size, ch.shape[0]))
            for n in range(ch.shape[0]):
                corr[good, n] = _angle_features(est[good], ch, em, n) @ coef[n]
            new = solve_all(profile, toa[rows] - corr, c["weights"][rows])
            est = np.where(np.isfinite(new), new, est)
        out[rows] = est
    return out


def drop_least_trusted(c, profile, toa, threshold_mm: float):
    """When four channels leave an rms residual above ``threshold_mm``, solve again without
    the channel of lowest echo-quality weight."""
    g = profile.geometry
    ch, em, fa = (np.asarray(a, float) for a in (g.channels_mm, g.emitter_mm, g.facing))
    out = np.full((len(toa), 3), np.nan)
    for i, t in enumerate(toa):
        paths = t * profile.mm_per_sample
        use = np.isfinite(paths)
        if use.sum() < 3:
            continue
        p, rms, ok = locate(paths, ch, em, fa, use, weights=c["weights"][i])
        if use.sum() == 4 and rms > threshold_mm:
            use[np.argmin(np.where(use, c["weights"][i], np.inf))] = False
            p, _, ok = locate(paths, ch, em, fa, use, weights=c["weights"][i])
        if ok:
            out[i] = p
    return out


def solve_variants(c, profile, toa):
    """(name, positions) for the solve variants on the ToA ``toa`` (minus delays)."""
    from tools.research.localisation_data import solve_all

    yield "  same ToA, unweighted solve", solve_all(profile, toa, None)
    loc = profile.locate
    alpha = np.maximum(np.nan_to_num(c["alpha"], nan=1.0), 1.0)
    ratio = np.clip(
        (1 / c["weights"] - loc.toa_sigma_samples - loc.toa_sigma_alpha_counts / alpha)
        / loc.toa_sigma_per_background,
        0,
        None,
    )
    for s0, s1, s2 in ((0.2, 0.25, 8.4), (0.4, 1.0, 8.4), (0.3, 0.0, 20.0)):
        w = 1 / (s0 + s1 * ratio + s2 / alpha)
        yield f"  same ToA, echo-quality sigmas ({s0}, {s1}, {s2})", solve_all(profile, toa, w)
    for lam in (0.3, 3.0):
        yield f"  same ToA, angle bias model (ridge {lam:g})", angle_bias(c, profile, toa, lam)
    for thr in (5.0, 8.0):
        yield (
            f"  same ToA, drop least trusted channel above {thr:g} mm",
            drop_least_trusted(c, profile, toa, thr),
        )


def shipped_recipe(c, profile, data, trees: dict):
    """The shipped correction's own recipe (``tools.train.toa_correction_data``: rows with and
    without a true background, delays + shift) retrained on all training positions, without and
    with a path scale fitted before the trees; (name, positions) on the study's rows."""
    from pathlib import Path

    from sklearn.ensemble import GradientBoostingRegressor

    from tools.research.localisation_data import solve_all
    from tools.research.localisation_fits import fit_delays_and_scale
    from tools.train import toa_correction_data as tcd

    base = np.asarray(profile.geometry.delays(), float)
    train, _ = tcd.split(tcd.load_cases(Path(data), profile, "log_parabola", 2))
    shift = tcd.fit_delay_shift(train, base)
    with_bg = [k for k in train if k.has_background]
    ref = np.array([k.refined for k in with_bg])
    ideal = np.array([k.ideal for k in with_bg])
    inl = np.abs(ref - base - shift - ideal) < INLIER
    scaled = fit_delays_and_scale(ref, ideal, inl, scale=True)
    feats = c["feats"]
    rows = np.all(np.isfinite(feats), 2)
    for name, (delay, k) in (("", (base + shift, 1.0)), (" + path scale", scaled)):
        x, y = [], []
        for case in train:
            res = case.refined - (delay + k * case.ideal)
            ok = np.isfinite(res) & (np.abs(res) < INLIER) & np.all(np.isfinite(case.features), 1)
            x.append(case.features[ok])
            y.append(res[ok])
        model = GradientBoostingRegressor(**trees).fit(np.vstack(x), np.concatenate(y))
        corr = np.zeros(rows.shape)
        corr[rows] = np.clip(model.predict(feats[rows]), -1.5, 1.5)
        toa = (c["refined"] - corr - delay) / k
        yield (
            f"shipped recipe retrained{name} (training: in sample)",
            solve_all(profile, toa, c["weights"]),
        )
