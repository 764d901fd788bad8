"""The fused per-acquisition path: one compiled call per acquisition where it can.

``FusedPipeline(pipeline).process(frames, background)`` returns the same Result as
``pipeline.process`` bit for bit (tests/core/test_fused.py asserts it on real and synthetic
data) with less Python around the kernels: shapes are validated once at the boundary (with
the staged path's messages), and the front kernel (:mod:`spiel_edge.pipeline.compiled.front`) runs the
finite check, preprocess (with the RF envelope), detect, memg, features and their ToA
ordering on a per-thread Workspace.

The back stages (associate, echo timing, echo quality, locate, covariance) are compiled too
when ``back.back_config`` (one target) or ``back_scene.scene_config`` (several) accepts the
pipeline (looked up again whenever ``set_max_targets`` replaces its scene): then front and back
run in one call (``back._acquisition_kernel`` / ``back_scene._scene_acquisition_kernel``;
two calls cost 7-12 us more per acquisition, much of it Python running cold after a kernel),
or in two when an onnxruntime model scores the echoes between them. Otherwise the back
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

from spiel_edge.errors import InputError
from spiel_edge.pipeline import staged as run
from spiel_edge.pipeline.compiled import one_target as back
from spiel_edge.pipeline.compiled import several_targets as back_scene
from spiel_edge.pipeline.compiled import steps as back_steps
from spiel_edge.pipeline.compiled.front import _front_kernel, front_scalars, raise_for
from spiel_edge.pipeline.compiled.workspace import ThreadWorkspaces

log = logging.getLogger(__name__)

FRONT_STAGES = ("preprocess", "detect", "memg", "features")


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
        self._run_acquisition = back.run_acquisition  # both kernels in one call
        self._prior_given = False  # onnxruntime scores the echoes between the two kernels
        self._workspaces = ThreadWorkspaces(
            p.geometry.n_channels, p.acquisition.n_samples, p.detect.max_echoes
        )
        self._shape = (p.geometry.n_channels, p.acquisition.n_samples)
        self._subtract = bool(p.preprocess.background_subtraction)
        self._scalars = front_scalars(p)

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
        raw = np.asarray(frames)
        config = self._kernel_config()
        if config is not None and not self._prior_given:
            return self._run_acquisition(self.pipeline, config, ws, y, bg, raw, background)
        status = _front_kernel(y, bg, *self._scalars, *ws.front_buffers)
        if status:
            raise_for(status)
        features, counts = ws.features.copy(), ws.counts.copy()
        if config is not None:
            given = self.pipeline.scene._bonus(features, counts)
            return self._run_back(
                self.pipeline, config, ws, features, counts, y, bg, raw, background, given
            )
        state = BackState(raw, background, features, counts)
        for step in self._back:
            step(self.pipeline, state)
        return state.result

    def _kernel_config(self) -> tuple | None:
        """The back kernel's arguments while the pipeline's scene stays the one they were
        built for (``set_max_targets`` replaces it), else None: the staged back steps."""
        if self.pipeline.scene is not self._scene:
            self._scene = self.pipeline.scene
            self._back_config = back.back_config(self.pipeline)
            self._run_back, self._run_acquisition = back.run_back, back.run_acquisition
            if self._back_config is None:
                self._back_config = back_scene.scene_config(self.pipeline)
                self._run_back = back_scene.run_scene
                self._run_acquisition = back_scene.run_scene_acquisition
            config = self._back_config
            prior = None if config is None else config[0][back_steps.I_PRIOR]
            self._prior_given = prior == back_steps.PRIOR_GIVEN
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
