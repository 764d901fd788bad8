"""The compiled path: one compiled call per acquisition, the staged path whole otherwise.

``FusedPipeline(pipeline).process(frames, background)`` returns the same Result as
``pipeline.process`` bit for bit (tests/core/test_fused.py asserts it on real and synthetic
data) with less Python around the kernels: shapes are validated once at the boundary (with
the staged path's messages), then one acquisition kernel runs every stage on a per-thread
Workspace: ``one_target`` for one target, ``several_targets`` for several (joint selection).

Two routes only. The compiled one needs every stage in a compiled form: the constants of
``pipeline.kernel_constants()`` (``abi.kernel_config``; looked up again whenever
``set_max_targets`` replaces the scene). Otherwise, and whenever the pipeline has a stage
this module does not run (a stage name in ``staged.STAGES`` missing from COMPILED_STAGES, or
a Pipeline subclass that does not declare ``compiled_equivalent``) or per-stage timings are asked for, the staged
path runs the whole acquisition: the learned associator's ``reference`` mode or an
onnxruntime model, greedy selection, more than 6 listening channels for several targets, an
onnxruntime ToA correction.
"""

from __future__ import annotations

import logging

import numpy as np

from spiel_edge.errors import InputError
from spiel_edge.pipeline import staged
from spiel_edge.pipeline.compiled import one_target, several_targets
from spiel_edge.pipeline.compiled.abi import KernelConfig, kernel_config
from spiel_edge.pipeline.compiled.workspace import ThreadWorkspaces
from spiel_edge.pipeline.stages.error_model import apply_error_model

log = logging.getLogger(__name__)

COMPILED_STAGES = ("preprocess", "detect", "memg", "features", "associate", "echo_timing", "locate")


def unsupported_stages(pipeline: staged.Pipeline) -> list[str]:
    """Stages (or reasons) the compiled path cannot run for this pipeline; empty when it can."""
    missing = [s for s in staged.STAGES if s not in COMPILED_STAGES]
    known = [s for s in staged.STAGES if s in COMPILED_STAGES]
    if known != [s for s in COMPILED_STAGES if s in known]:
        missing.append("stages reordered")
    if not type(pipeline).compiled_equivalent:  # a subclass that did not declare it
        missing.append(f"{type(pipeline).__name__} (not compiled_equivalent)")
    return missing


class FusedPipeline:
    """Wraps a Pipeline; ``process`` is a drop-in replacement for ``Pipeline.process``, and the
    rest of the Pipeline's interface is passed on."""

    def __init__(self, pipeline: staged.Pipeline):
        self.pipeline = pipeline
        p = pipeline.profile
        self.profile = p
        self.fallback = unsupported_stages(pipeline)
        if self.fallback:
            log.info("compiled path falls back to the staged one for %s", ", ".join(self.fallback))
        self._writable_bg: tuple[np.ndarray, np.ndarray] | None = None  # (read-only, copy)
        self._scene = None  # the scene the kernel constants below were built for
        self.config: KernelConfig | None = None
        self._run = None  # one_target.run or several_targets.run
        self._workspaces = ThreadWorkspaces(
            p.geometry.n_channels, p.acquisition.n_samples, p.detect.max_echoes
        )
        self._shape = (p.geometry.n_channels, p.acquisition.n_samples)
        self._subtract = bool(p.preprocess.background_subtraction)

    # the Pipeline's interface, passed on
    @property
    def associator(self):
        return self.pipeline.associator

    @property
    def echo_timing(self):
        return self.pipeline.echo_timing

    @property
    def scene(self):
        return self.pipeline.scene

    @property
    def max_targets(self) -> int:
        return self.pipeline.max_targets

    @property
    def static_model(self):
        return self.pipeline.static_model

    def set_max_targets(self, k: int) -> None:
        self.pipeline.set_max_targets(k)

    def check_shape(self, frames: np.ndarray, what: str = "frames") -> None:
        self.pipeline.check_shape(frames, what)

    @property
    def kernel(self) -> str | None:
        """The acquisition kernel for the current scene ("one_target", "several_targets"),
        or None when the staged path runs."""
        run = None if self.fallback else self._kernel()
        return None if run is None else run.__module__.rsplit(".", 1)[1]

    def process(
        self, frames: np.ndarray, background: np.ndarray | None = None, *, timed: bool = False
    ) -> staged.Result:
        run = None if timed or self.fallback else self._kernel()
        if run is None:
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
        y = as_float64(frames, "frames")
        bg = as_float64(background, "background") if background is not None else ws.background[:0]
        if not bg.flags.writeable:  # e.g. the static model: one kernel signature, not two
            bg = self._writable(bg)
        result = run(self.pipeline, self.config, ws, y, bg, np.asarray(frames), background)
        model = self.profile.scene.error_model
        if model:  # per target, after the kernel (pipeline/stages/error_model.py)
            captured = background is not None and background is not self.pipeline.static_model
            apply_error_model(result, model, self.pipeline.facing, captured)
        return result

    def _writable(self, bg: np.ndarray) -> np.ndarray:
        """A writable copy of a read-only background, kept while the same one comes (the
        kernels read it only: a read-only array would be a second signature to compile)."""
        kept = self._writable_bg
        if kept is None or kept[0] is not bg:
            kept = self._writable_bg = (bg, np.array(bg))
        return kept[1]

    def _kernel(self):
        """The run function of the kernel for the pipeline's scene while it stays the one the
        constants were built for (``set_max_targets`` replaces it), else None."""
        if self.pipeline.scene is not self._scene:
            self._scene = self.pipeline.scene
            self.config = kernel_config(self.pipeline)
            several = self.pipeline.scene.max_targets > 1
            self._run = None
            if self.config is not None:
                self._run = several_targets.run if several else one_target.run
            log.debug("compiled path %s", "on" if self._run is not None else "off")
        return self._run


def as_float64(arr: np.ndarray, name: str) -> np.ndarray:
    """float64 C-contiguous view (a copy only when needed); dtype checked as the staged path."""
    if type(arr) is np.ndarray and arr.dtype == np.float64 and arr.flags.c_contiguous:
        return arr  # the usual case, without numpy's dtype lookups
    a = np.asarray(arr)
    if not np.issubdtype(a.dtype, np.number):
        raise InputError(f"{name} must be numeric, got dtype {a.dtype}")
    return np.ascontiguousarray(a, dtype=np.float64)
