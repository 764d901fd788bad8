"""Between associate and locate: each matched echo's time of arrival to a fraction of a sample.

The MEMG mode is fitted to the linearly background-subtracted envelope, which an echo sitting
on a background echo distorts (the two add as phasors, not as amplitudes). Here, per matched
echo, the background is removed in the power domain, ``sqrt(max(frame^2 - background^2, 0))``
(the expected envelope of a target echo plus an uncorrelated background), and the ToA is the
peak of a parabola through the log of the three samples around the largest sample within
``half_window`` of the matched echo (a Gaussian pulse's exact peak; the peak sample itself
where a neighbour is zero, i.e. removed with the background, as in the study of issue 11). An optional learned
correction (:mod:`spiel_edge.pipeline.learned.toa_correction`) then removes the remaining bias from
the local window of frame, background and cleaned envelope (:func:`toa_features`).

Without a background capture the cleaned envelope is the frame itself, and the features say so.
One target's matched echoes at a time (``time_echoes``), so the step applies per target.
The estimator (log parabola, +-2 samples) was chosen on the training positions of
spiel-icra23: see docs/echo-timing.md.
"""

from __future__ import annotations

import math

import numpy as np

from spiel_edge._jit import jit
from spiel_edge.errors import InputError
from spiel_edge.pipeline.learned.tree_ensemble import DENSE, predict_kernel

ESTIMATORS = {"none": 0, "parabola": 1, "log_parabola": 2}
FEATURE_HALF_WIDTH = 6  # samples either side of the echo's peak sample (chosen by grouped CV)
N_WINDOW = 2 * FEATURE_HALF_WIDTH + 1
N_SCALARS = 3  # offset of the ToA from the peak sample, log peak, background present


def n_toa_features(n_channels: int) -> int:
    """Feature count per echo: three windows, three scalars and a one-hot channel."""
    return 3 * N_WINDOW + N_SCALARS + n_channels


def feature_names(n_channels: int) -> list[str]:
    offsets = range(-FEATURE_HALF_WIDTH, FEATURE_HALF_WIDTH + 1)
    names = [f"{w}[{o:+d}]" for w in ("frame", "background", "clean") for o in offsets]
    return names + ["offset", "log_peak", "has_background"] + [f"ch{c}" for c in range(n_channels)]


def _as_2d(a: np.ndarray, what: str) -> np.ndarray:
    out = np.ascontiguousarray(a, dtype=np.float64)
    if out.ndim != 2:
        raise InputError(f"{what} must be (channels, samples), got shape {out.shape}")
    return out


def clean_envelope(
    frames: np.ndarray, background: np.ndarray | None, blind_zone: int = 0
) -> np.ndarray:
    """The power-domain background-free envelope (the frame itself without a background),
    zero in the blind zone."""
    y = _as_2d(frames, "frames")
    bg = np.zeros((0, 0)) if background is None else _as_2d(background, "background")
    if bg.size and bg.shape != y.shape:
        raise InputError(f"background shape {bg.shape} does not match frames shape {y.shape}")
    out = np.empty_like(y)
    clean_kernel(y, bg, int(max(blind_zone, 0)), out)
    return out


@jit
def clean_kernel(y, bg, blind_zone, out):
    n_ch, n_t = y.shape
    subtract = bg.shape[0] == n_ch
    for c in range(n_ch):
        for t in range(n_t):
            if t < blind_zone:
                out[c, t] = 0.0
            elif subtract:
                out[c, t] = math.sqrt(max(y[c, t] * y[c, t] - bg[c, t] * bg[c, t], 0.0))
            else:
                out[c, t] = max(y[c, t], 0.0)


def refine_toa(
    clean: np.ndarray, toa: np.ndarray, half_window: int = 2, estimator: str = "log_parabola"
) -> np.ndarray:
    """Per channel, the refined ToA of the echo matched at ``toa`` (NaN: no echo, kept NaN).
    An echo whose peak sample is at the frame's edge, or not above zero, keeps its ToA;
    ``log_parabola`` gives the peak sample where a neighbour of it is zero."""
    y = _as_2d(clean, "clean")
    t = np.ascontiguousarray(toa, dtype=np.float64)
    if t.shape != (y.shape[0],):
        raise InputError(f"toa must have one value per channel ({y.shape[0]}), got {t.shape}")
    if estimator not in ESTIMATORS:
        raise InputError(f"estimator must be one of {sorted(ESTIMATORS)}, got {estimator!r}")
    out = t.copy()
    if estimator != "none":
        refine_kernel(y, t, int(half_window), ESTIMATORS[estimator] == 2, out)
    return out


@jit
def refine_kernel(y, toa, half_window, log_domain, out):
    n_ch, n_t = y.shape
    for c in range(n_ch):
        if not math.isfinite(toa[c]):
            continue
        k = _peak_sample(y[c], toa[c], half_window)
        if k < 1 or k > n_t - 2:
            continue
        a, b, d = y[c, k - 1], y[c, k], y[c, k + 1]
        if b <= 0.0:
            continue
        if log_domain:
            if a <= 0.0 or d <= 0.0:  # a neighbour removed with the background: no shape left
                out[c] = k
                continue
            a, b, d = math.log(a), math.log(b), math.log(d)
        curvature = a - 2.0 * b + d
        step = 0.5 * (a - d) / curvature if curvature < 0.0 else 0.0
        out[c] = k + min(max(step, -0.5), 0.5)


@jit
def _peak_sample(row, toa, half_window):
    """Index of the largest sample within half_window of round(toa), -1 if none."""
    n_t = row.shape[0]
    centre = int(round(min(max(toa, 0.0), n_t - 1.0)))
    best, at = -1.0, -1
    for t in range(max(centre - half_window, 0), min(centre + half_window + 1, n_t)):
        if row[t] > best:
            best, at = row[t], t
    return at


def toa_features(
    frames: np.ndarray, background: np.ndarray | None, clean: np.ndarray, toa: np.ndarray
) -> np.ndarray:
    """(channels, n_toa_features) for the learned correction; a NaN row where there is no echo,
    or its window would leave the frame (the correction then keeps the refined ToA)."""
    y = _as_2d(frames, "frames")
    e = _as_2d(clean, "clean")
    bg = np.zeros((0, 0)) if background is None else _as_2d(background, "background")
    if e.shape != y.shape or (bg.size and bg.shape != y.shape):
        raise InputError("frames, background and clean must have the same shape")
    t = np.ascontiguousarray(toa, dtype=np.float64)
    if t.shape != (y.shape[0],):
        raise InputError(f"toa must have one value per channel ({y.shape[0]}), got {t.shape}")
    out = np.full((y.shape[0], n_toa_features(y.shape[0])), np.nan)
    _features_kernel(y, bg, e, t, FEATURE_HALF_WIDTH, out)
    return out


@jit
def _features_kernel(y, bg, e, toa, hw, out):
    n_ch, n_t = y.shape
    n_w = 2 * hw + 1
    has_bg = bg.shape[0] == n_ch
    for c in range(n_ch):
        if not math.isfinite(toa[c]):
            continue
        k = int(round(toa[c]))
        if k - hw < 0 or k + hw >= n_t:
            continue
        peak = max(e[c, k], 1.0)
        for i in range(n_w):
            out[c, i] = y[c, k - hw + i] / peak
            out[c, n_w + i] = bg[c, k - hw + i] / peak if has_bg else 0.0
            out[c, 2 * n_w + i] = e[c, k - hw + i] / peak
        out[c, 3 * n_w] = toa[c] - k
        out[c, 3 * n_w + 1] = math.log(peak)
        out[c, 3 * n_w + 2] = 1.0 if has_bg else 0.0
        for j in range(n_ch):
            out[c, 3 * n_w + 3 + j] = 1.0 if j == c else 0.0


class EchoTiming:
    """The step for one target: ``(frames, background or None, toa per channel) -> toa``.

    ``correction`` (a :class:`spiel_edge.pipeline.learned.toa_correction.ToaCorrection` or None) maps
    (features, refined toa) to the corrected toa. The result is finite wherever ``toa`` is.
    """

    def __init__(
        self,
        estimator: str = "log_parabola",
        half_window: int = 2,
        blind_zone: int = 0,
        correction=None,
    ):
        if estimator not in ESTIMATORS:
            raise InputError(f"estimator must be one of {sorted(ESTIMATORS)}, got {estimator!r}")
        self.estimator = estimator
        self.half_window = int(half_window)
        self.blind_zone = int(blind_zone)
        self.correction = correction

    @property
    def active(self) -> bool:
        return self.estimator != "none"

    def __call__(
        self, frames: np.ndarray, background: np.ndarray | None, toa: np.ndarray
    ) -> np.ndarray:
        if not self.active:
            return np.asarray(toa, dtype=np.float64)
        trees = getattr(self.correction, "trees", None)
        if trees is not None:  # one numba call for the whole step: the cheap path
            return self._fused(frames, background, toa, trees)
        clean = clean_envelope(frames, background, self.blind_zone)
        refined = refine_toa(clean, toa, self.half_window, self.estimator)
        if self.correction is None:
            return refined
        corrected = self.correction(toa_features(frames, background, clean, refined), refined)
        return np.where(np.isfinite(corrected), corrected, refined)

    def kernel_constants(self) -> dict | None:
        """This step's constants for the compiled path (``pipeline/compiled/abi.py``); None
        when its correction has no numba trees (it runs in onnxruntime)."""
        if not self.active:
            mode, trees = "none", {}
        elif self.correction is None:
            mode, trees = "refine", {}
        else:
            dense = getattr(self.correction, "trees", None)
            if dense is None:
                return None
            mode, trees = "trees", dict(zip(DENSE, dense, strict=True))
        return {
            "timing": mode,
            "blind": self.blind_zone,
            "half_window": self.half_window,
            "log": ESTIMATORS[self.estimator] == ESTIMATORS["log_parabola"],
            "limit": float(getattr(self.correction, "max_correction", 0.0)),
            **trees,
        }

    def _fused(self, frames, background, toa, trees) -> np.ndarray:
        y = _as_2d(frames, "frames")
        bg = np.zeros((0, 0)) if background is None else _as_2d(background, "background")
        t = np.ascontiguousarray(toa, dtype=np.float64)
        if (bg.size and bg.shape != y.shape) or t.shape != (y.shape[0],):
            raise InputError("frames, background and toa must agree in shape")
        out = np.empty(y.shape[0])
        log_domain = ESTIMATORS[self.estimator] == ESTIMATORS["log_parabola"]
        limit = float(self.correction.max_correction)
        fused_kernel(y, bg, self.blind_zone, t, self.half_window, log_domain, *trees, limit, out)
        return out


@jit
def fused_kernel(
    y, bg, blind_zone, toa, half_window, log_domain, feature, threshold, value, base, limit, out
):
    """clean_envelope -> refine_toa -> toa_features -> trees, as the separate wrappers do."""
    n_ch = y.shape[0]
    clean = np.empty_like(y)
    clean_kernel(y, bg, blind_zone, clean)
    refined = toa.copy()
    refine_kernel(clean, toa, half_window, log_domain, refined)
    feats = np.full((n_ch, 3 * N_WINDOW + N_SCALARS + n_ch), np.nan)
    _features_kernel(y, bg, clean, refined, int(FEATURE_HALF_WIDTH), feats)
    pred = np.empty(n_ch)
    predict_kernel(feature, threshold, value, base, feats, pred)
    for c in range(n_ch):
        p = pred[c]
        out[c] = refined[c] if not math.isfinite(p) else refined[c] - min(max(p, -limit), limit)


def timing_delays(profile) -> np.ndarray:
    """Per-channel delays (samples) for the ToA the profile's step produces."""
    delays = np.asarray(profile.geometry.delays(), dtype=np.float64)
    spec = profile.echo_timing
    if spec.estimator != "none" and spec.delay_shift_samples:
        delays = delays + np.asarray(spec.delay_shift_samples, dtype=np.float64)
    return delays
