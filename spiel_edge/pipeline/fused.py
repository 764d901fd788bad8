"""The fused per-acquisition path: one compiled front kernel, then the back steps.

``FusedPipeline(pipeline).process(frames, background)`` returns the same Result as
``pipeline.process`` bit for bit (tests/core/test_fused.py asserts it on real and synthetic
data) with less Python around the kernels: shapes are validated once at the boundary (with
the staged path's messages), and one kernel runs the finite check, preprocess (with the RF
envelope), detect, memg, features and their ToA ordering on a per-thread Workspace.

For one target the back stages (associate, echo timing, echo quality, locate, covariance) are
a second compiled call, :mod:`spiel_edge.pipeline.back`, when ``back.back_config`` accepts the
pipeline (looked up again whenever ``set_max_targets`` replaces its scene). Otherwise the back
steps run after the front kernel, one function per stage name in BACK_STEPS. The staged path stays
the reference: whenever the pipeline has a stage this module does not implement (a stage name
in ``run.STAGES`` missing from FRONT_STAGES + BACK_STEPS, or a Pipeline subclass overriding
``process``), or per-stage timings are asked for, ``process`` runs the staged path for the
whole acquisition, so new steps are never skipped. To fuse a new step, implement it here as a
back step ``fn(pipeline, state)`` and add its stage name to BACK_STEPS in stage order.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from spiel_edge._jit import jit
from spiel_edge.errors import InputError
from spiel_edge.pipeline import back, back_scene, back_steps, run
from spiel_edge.pipeline.detect import _detect_kernel
from spiel_edge.pipeline.features import TOA_CODES, TOA_COLUMN, _features_kernel
from spiel_edge.pipeline.memg import _memg_kernel
from spiel_edge.pipeline.preprocess import _envelope_kernel, _preprocess_kernel
from spiel_edge.pipeline.split import _split_kernel
from spiel_edge.pipeline.workspace import ThreadWorkspaces

log = logging.getLogger(__name__)

FRONT_STAGES = ("preprocess", "detect", "memg", "features")
FRAMES_NOT_FINITE, BACKGROUND_NOT_FINITE = 1, 2


@dataclass
class BackState:
    """What the back steps read and fill for one acquisition."""

    frames: np.ndarray  # the raw frames as given (for the saturation / flat-frame reasons)
    background: np.ndarray | None  # None when the profile does not subtract one
    features: np.ndarray
    counts: np.ndarray
    hypotheses: list | None = None  # the scene associator's (matched, cost), best first
    result: run.Result | None = None


def _associate_step(pipeline: run.Pipeline, state: BackState) -> None:
    state.hypotheses = pipeline.scene(state.features, state.counts)


def _echo_timing_step(pipeline: run.Pipeline, state: BackState) -> None:
    """Nothing here: the echo-timing step runs per target inside ``Pipeline._locate``."""
    pipeline._clock, pipeline._echo_timing_ns = run._no_clock, 0  # untimed, as process()


def _locate_step(pipeline: run.Pipeline, state: BackState) -> None:
    state.result = pipeline._locate(
        state.features, state.counts, state.hypotheses, state.frames, state.background
    )


BACK_STEPS = {
    "associate": _associate_step,
    "echo_timing": _echo_timing_step,
    "locate": _locate_step,
}


def unsupported_stages(pipeline: run.Pipeline) -> list[str]:
    """Stages (or reasons) the fused path cannot run for this pipeline; empty when it can."""
    missing = [s for s in run.STAGES if s not in FRONT_STAGES and s not in BACK_STEPS]
    if tuple(run.STAGES[: len(FRONT_STAGES)]) != FRONT_STAGES:
        missing.append("front stages reordered")
    if type(pipeline).process is not run.Pipeline.process:
        missing.append(f"{type(pipeline).__name__}.process")
    return missing


class FusedPipeline:
    """Wraps a Pipeline; ``process`` is a drop-in replacement for ``Pipeline.process``."""

    def __init__(self, pipeline: run.Pipeline):
        self.pipeline = pipeline
        p = pipeline.profile
        self.profile = p
        self.fallback = unsupported_stages(pipeline)
        if self.fallback:
            log.info("fused path falls back to the staged one for %s", ", ".join(self.fallback))
        self._back = [BACK_STEPS[s] for s in run.STAGES[len(FRONT_STAGES) :] if s in BACK_STEPS]
        self._scene, self._back_config = None, None  # the back kernel's, per scene (K)
        self._run_back = back.run_back  # or back_scene.run_scene for several targets
        self._workspaces = ThreadWorkspaces(
            p.geometry.n_channels, p.acquisition.n_samples, p.detect.max_echoes
        )
        acq, d = p.acquisition, p.detect
        self._shape = (p.geometry.n_channels, acq.n_samples)
        self._subtract = bool(p.preprocess.background_subtraction)
        self._scalars = (
            int(p.preprocess.blind_zone_samples),
            acq.signal == "rf",
            float(acq.carrier_hz / acq.sample_rate_hz),
            max(1, int(round(0.5 / (acq.carrier_hz / acq.sample_rate_hz)))),  # as envelope()
            float(d.threshold),
            float(d.threshold * d.hysteresis),
            float(d.min_amplitude),
            float(p.memg.mu_window),
            int(p.memg.max_iterations),
            bool(p.memg.split_merged),
            float(p.memg.split_min_sigma),
            float(p.memg.split_max_cost_ratio),
            TOA_CODES[p.memg.toa],
        )

    def __getattr__(self, name: str):
        return getattr(self.pipeline, name)  # anything else is the staged pipeline's

    def process(
        self, frames: np.ndarray, background: np.ndarray | None = None, *, timed: bool = False
    ) -> run.Result:
        if timed or self.fallback:
            return self.pipeline.process(frames, background, timed=timed)
        # the staged path's checks, skipped for the usual ndarray of the profile's shape
        if type(frames) is not np.ndarray or frames.shape != self._shape:
            self.pipeline.check_shape(frames)
        if background is not None and (
            type(background) is not np.ndarray or background.shape != self._shape
        ):
            self.pipeline.check_shape(background, "background")
        if not self._subtract:
            background = None
        elif background is None:
            background = self.pipeline.static_model  # None unless the profile names one
        ws = self._workspaces.get()
        y = _numeric(frames, "frames")
        bg = _numeric(background, "background") if background is not None else ws.background[:0]
        status = _front_kernel(y, bg, *self._scalars, *ws.front_buffers)
        if status == FRAMES_NOT_FINITE:
            raise InputError("frames contains NaN or infinite samples")
        if status == BACKGROUND_NOT_FINITE:
            raise InputError("background contains NaN or infinite samples")
        features, counts = ws.features.copy(), ws.counts.copy()
        config = self._kernel_config()
        if config is not None:
            prior = config[0][back_steps.I_PRIOR]
            given = (
                self.pipeline.scene._bonus(features, counts)
                if prior == back_steps.PRIOR_GIVEN
                else None
            )
            raw = np.asarray(frames)
            return self._run_back(
                self.pipeline, config, ws, features, counts, y, bg, raw, background, given
            )
        state = BackState(np.asarray(frames), background, features, counts)
        for step in self._back:
            step(self.pipeline, state)
        return state.result

    def _kernel_config(self) -> tuple | None:
        """The back kernel's arguments while the pipeline's scene stays the one they were
        built for (``set_max_targets`` replaces it), else None: the staged back steps."""
        if self.pipeline.scene is not self._scene:
            self._scene = self.pipeline.scene
            self._back_config = back.back_config(self.pipeline)
            self._run_back = back.run_back
            if self._back_config is None:
                self._back_config = back_scene.scene_config(self.pipeline)
                self._run_back = back_scene.run_scene
            log.debug("back kernel %s", "on" if self._back_config is not None else "off")
        return self._back_config


def _numeric(arr: np.ndarray, name: str) -> np.ndarray:
    """float64 C-contiguous view (a copy only when needed); dtype checked as the staged path."""
    if type(arr) is np.ndarray and arr.dtype == np.float64 and arr.flags.c_contiguous:
        return arr  # the usual case, without numpy's dtype lookups
    a = np.asarray(arr)
    if not np.issubdtype(a.dtype, np.number):
        raise InputError(f"{name} must be numeric, got dtype {a.dtype}")
    return np.ascontiguousarray(a, dtype=np.float64)


@jit
def _all_finite(a):
    ok = True
    for i in range(a.shape[0]):
        for j in range(a.shape[1]):
            ok &= np.isfinite(a[i, j])
    return ok


@jit
def _front_kernel(
    y,
    bg,
    blind,
    rf,
    carrier,
    half_width,
    hi,
    lo,
    min_amp,
    mu_window,
    max_iter,
    split,
    split_min_sigma,
    split_max_ratio,
    toa_code,
    env,
    bg_env,
    cleaned,
    peaks,
    counts,
    params,
    iterations,
    unsorted,
    features,
):
    """Finite check, preprocess, detect, memg (and the merged-echo split), features and the ToA ordering; 0 when done,
    else FRAMES_NOT_FINITE or BACKGROUND_NOT_FINITE."""
    if not _all_finite(y):
        return FRAMES_NOT_FINITE
    if bg.shape[0] > 0 and not _all_finite(bg):
        return BACKGROUND_NOT_FINITE
    if rf:
        _envelope_kernel(y, carrier, half_width, env)
        y = env
        if bg.shape[0] > 0:
            _envelope_kernel(bg, carrier, half_width, bg_env)
            bg = bg_env
    _preprocess_kernel(y, bg, blind, cleaned)
    peaks[:, :] = -1
    counts[:] = 0
    _detect_kernel(cleaned, hi, lo, min_amp, blind, peaks, counts)
    params[:, :, :] = np.nan
    iterations[:, :] = 0
    _memg_kernel(cleaned, peaks, counts, mu_window, max_iter, params, iterations)
    if split:
        _split_kernel(
            cleaned,
            peaks,
            counts,
            params,
            iterations,
            split_min_sigma,
            split_max_ratio,
            mu_window,
            max_iter,
        )
    unsorted[:, :, :] = np.nan
    _features_kernel(cleaned, params, peaks, toa_code, unsorted)
    _order_by_toa(unsorted, features)
    return 0


@jit
def _order_by_toa(unsorted, out):
    """Each channel's rows by ascending ToA, NaN last, ties in input order (as a stable sort)."""
    n_ch, k_max, n_f = unsorted.shape
    order = np.empty(k_max, dtype=np.int64)
    for c in range(n_ch):
        for k in range(k_max):
            key = unsorted[c, k, TOA_COLUMN]
            key = np.inf if np.isnan(key) else key
            i = k - 1
            while i >= 0:
                prev = unsorted[c, order[i], TOA_COLUMN]
                prev = np.inf if np.isnan(prev) else prev
                if prev <= key:
                    break
                order[i + 1] = order[i]
                i -= 1
            order[i + 1] = k
        for k in range(k_max):
            for f in range(n_f):
                out[c, k, f] = unsorted[c, order[k], f]
