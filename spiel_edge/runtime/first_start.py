"""Before a command uses the pipeline: every kernel it needs from the cache, or, when one is
missing, said at once (which, why, about how long) and compiled with progress in child
processes (``warmup``'s steps), before a board is opened (issues 24 and 29).

``prepare_for_run`` tries the command's kernels with compiling forbidden
(``_kernel_cache.no_compile``): a warm start pays only the loading; the first kernel missing
ends the try and starts the compile. ``kernel_status`` counts the kernels with no compiled copy
for this CPU in any cache layer.
"""

from __future__ import annotations

import logging
import os
import time

from spiel_edge.runtime.warmup import (
    _run_child,
    _step_stream,
    cache_dir,
    closed_form_acquisition,
    pipeline_kernels,
)

log = logging.getLogger(__name__)

RUN_STEPS = ("stream", "fused-geometric", "fused-learned", "tracker")  # what `run` compiles


def _exercise_run(profile, association, max_targets, track: bool, toa_correction=None) -> None:
    """What ``run`` compiles before its first record: the stream decoder, the pipeline on a
    closed-form acquisition of the profile's shape (one target and ``max_targets``) and the
    tracker on the results."""
    from spiel_edge.pipeline.factory import build_pipeline
    from spiel_edge.runtime.tracking import ResultTracker

    _step_stream()
    pipeline = build_pipeline(profile, association, toa_correction)
    frames, background = closed_form_acquisition(profile)
    results = []
    for k in sorted({1, max_targets or 1}):
        pipeline.set_max_targets(k)
        results += [pipeline.process(frames, background), pipeline.process(frames, None)]
    if track:
        tracker = ResultTracker(profile.track)
        for i, result in enumerate(results):
            tracker.update(result, 0.02 * i)


def prepare_for_run(
    profile,
    association=None,
    max_targets=None,
    track=True,
    toa_correction=None,
    stream=None,
    notifier=None,
) -> dict:
    """Before ``run`` opens a board: load every kernel it needs from the cache, or, when one
    is missing, say so at once (what, why, about how long) and compile them with progress on
    ``stream`` (stderr), in child processes when the cache is writable (bounded memory).
    ``compiled``: whether anything compiled; ``seconds``: the time it took."""
    from spiel_edge import _kernel_cache
    from spiel_edge.errors import SpielError

    t0 = time.perf_counter()
    try:
        with _kernel_cache.no_compile():
            _exercise_run(profile, association, max_targets, track, toa_correction)
        return {"compiled": False, "seconds": round(time.perf_counter() - t0, 3)}
    except _kernel_cache.CompileNeeded as exc:
        if os.environ.get(_kernel_cache.ENV_FORBID, "0") not in ("", "0"):
            raise
        first = exc.name
    except SpielError as exc:  # an unusual profile: the live stream will tell
        log.debug("kernel preparation: %s", exc)
        return {"compiled": False, "seconds": round(time.perf_counter() - t0, 3)}
    progress = announce("before opening the board", stream, first)
    progress.notifier = notifier  # the service: STATUS per kernel, the start timeout extended
    if notifier is not None:
        notifier.starting("compiling kernels for this CPU")
    writable = cache_writable()
    if writable:
        for step in RUN_STEPS:
            _run_child(step, progress)
    _kernel_cache.listeners.append(progress)  # what the profile needs beyond the steps: here
    try:
        _exercise_run(profile, association, max_targets, track, toa_correction)
    except SpielError as exc:
        log.debug("kernel preparation: %s", exc)
    finally:
        _kernel_cache.listeners.remove(progress)
    seconds = time.perf_counter() - t0
    progress.finish(
        f"spiel-edge: kernels ready after {seconds:.0f} s"
        + ("" if writable else " (not kept: no writable cache folder)")
    )
    return {"compiled": True, "seconds": round(seconds, 3)}


def announce(when: str, stream=None, first: str | None = None):
    """Say at once that kernels must compile (``first``: the one found missing), then how
    many, why and about how long; return the display."""
    import platform

    from spiel_edge import _shipped
    from spiel_edge.runtime.compile_progress import Progress, about, estimate_seconds

    progress = Progress(total=1, stream=stream)
    if first is not None:  # at once: counting them imports every kernel module (seconds)
        progress.say(f"spiel-edge: kernel {first} has no compiled copy: compiling {when}")
    status = kernel_status()
    n, total = max(len(status["missing"]), 1), max(status["total"], 1)
    progress.total = n
    progress.say(
        f"spiel-edge: compiling {n} of {total} kernels for this CPU {when}, "
        f"{about(estimate_seconds(n, total, platform.machine()))} "
        f"({_why(status, _shipped.status())}; once: later starts load them from "
        f"{status['cache_dir'] or 'nowhere: no writable cache folder'})"
    )
    return progress


def _why(status: dict, shipped: dict) -> str:
    if shipped["active"]:
        return "the prebuilt kernels lack them"
    if status["missing"] and len(status["missing"]) < status["total"]:
        return f"{shipped['reason']}; the cache holds some of them: the code or numba changed"
    return f"{shipped['reason']}; the cache is empty"


def kernel_status() -> dict:
    """The kernels with no compiled copy for this CPU (cache key: CPU, numba, bytecode) in
    any cache layer; inlined helpers, never compiled alone, are left out."""
    from numba.core.registry import cpu_target

    codegen = cpu_target.target_context.codegen()
    kernels = {
        name: k
        for name, k in pipeline_kernels().items()
        if k.targetoptions.get("inline", "never") == "never" and hasattr(k._cache, "has_copy")
    }
    missing = sorted(name for name, k in kernels.items() if not k._cache.has_copy(codegen))
    return {"total": len(kernels), "missing": missing, "cache_dir": cache_dir()}


def cache_writable() -> bool:
    """Whether compiled kernels are kept (a kernel cache with a writable folder)."""
    try:
        from firmware_protocol import _cobs_numba
    except (ImportError, RuntimeError):  # no numba, or numba's own cache with no folder
        return False
    return bool(getattr(_cobs_numba.decode._cache, "writable", True))
