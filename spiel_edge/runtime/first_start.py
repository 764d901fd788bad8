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
    cache_dir,
    closed_form_acquisition,
    pipeline_kernels,
    run_child,
    step_stream,
)

log = logging.getLogger(__name__)

RUN_STEPS = ("stream", "fused-geometric", "fused-learned", "tracker")  # what `run` compiles


def exercise_run(
    profile, association, max_targets, track: bool, toa_correction=None, pipeline=None
) -> None:
    """What ``run`` compiles before its first record: the stream decoder, the pipeline on a
    closed-form acquisition of the profile's shape (one target and ``max_targets``) and the
    tracker on the results. ``pipeline``: the run's own, built for ``profile`` (runtime/
    live.py builds it once): exercised here and left with the targets it was set to."""
    from spiel_edge.pipeline.factory import build_pipeline
    from spiel_edge.runtime.track_records import ResultTracker

    step_stream()
    if pipeline is None:
        pipeline = build_pipeline(profile, association, toa_correction)
    frames, background = closed_form_acquisition(profile)
    results = []
    kept = pipeline.max_targets
    try:
        for k in sorted({1, max_targets or 1}):
            pipeline.set_max_targets(k)
            results += [pipeline.process(frames, background), pipeline.process(frames, None)]
    finally:
        pipeline.set_max_targets(kept)
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
    pipeline=None,
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
            exercise_run(profile, association, max_targets, track, toa_correction, pipeline)
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
    if writable and _tiers_available():  # only what this configuration needs, counted
        interpreted, plan, units = make_plan(
            profile, association, max_targets, track, toa_correction
        )
        interpreted.leave()
        say_plan(progress, units)
        _compile_plan(plan, progress)
    elif writable:
        for step in RUN_STEPS:
            run_child(step, progress)
    _kernel_cache.listeners.append(progress)  # what the profile needs beyond the steps: here
    try:
        exercise_run(profile, association, max_targets, track, toa_correction, pipeline)
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
    """Say at once that kernels must compile (``first``: the one found missing); the count
    and the estimate follow (:func:`say_plan`). The display is returned."""
    from spiel_edge.runtime.compile_progress import Progress

    progress = Progress(total=1, stream=stream)
    progress.when = when
    if first is not None:
        progress.say(f"spiel-edge: kernel {first} has no compiled copy: compiling {when}")
    return progress


def say_plan(progress, units: list[str]) -> None:
    """How many kernels this command compiles, why and about how long (from the measured
    per-kernel times)."""
    from spiel_edge import _shipped
    from spiel_edge.runtime.compile_progress import about, estimate_for

    shipped = _shipped.status()
    why = "the prebuilt kernels lack them" if shipped["active"] else shipped["reason"]
    progress.total = max(len(units), 1)
    progress.say(
        f"spiel-edge: compiling the {len(units)} kernels this command needs for this CPU "
        f"{progress.when}, {about(estimate_for(units))} ({why}; once: later starts load them "
        f"from {cache_dir() or 'nowhere: no writable cache folder'})"
    )


def _tiers_available() -> bool:
    from spiel_edge import _tiers

    return bool(_tiers.KERNELS)


def _compile_plan(plan: list, progress) -> None:
    """The plan compiled in the warm-up's children (each within its memory budget)."""
    import tempfile
    from pathlib import Path

    from spiel_edge.runtime.tier_compile import write_plan
    from spiel_edge.runtime.warmup import ENV_PLAN

    fd, name = tempfile.mkstemp(prefix="spiel-edge-plan-", suffix=".pickle")
    os.close(fd)
    path = Path(name)
    before = os.environ.get(ENV_PLAN)
    try:
        write_plan(path, plan)
        os.environ[ENV_PLAN] = str(path)  # the children's
        run_child("plan", progress)
    finally:
        path.unlink(missing_ok=True)
        if before is None:
            os.environ.pop(ENV_PLAN, None)
        else:
            os.environ[ENV_PLAN] = before


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
        from spiel_edge.protocol import _cobs_numba
    except (ImportError, RuntimeError):  # no numba, or numba's own cache with no folder
        return False
    return bool(getattr(_cobs_numba.decode._cache, "writable", True))


def make_plan(
    profile, association=None, max_targets=None, track=True, toa_correction=None, exercise=None
):
    """What a command with this configuration compiles: the interpreted tier (entered: the
    caller leaves it, or runs on it), the plan ([(module, attribute, argument types)] of
    each call from Python) and the kernels that compile with it and have no compiled copy.
    ``exercise``: what the command runs instead of ``run``'s pipeline and tracker (``fuse``)."""
    from numba.core.registry import cpu_target

    from spiel_edge import _tiers
    from spiel_edge.errors import SpielError
    from spiel_edge.protocol import cobs
    from spiel_edge.runtime.warmup import pipeline_kernels

    pipeline_kernels()  # every kernel module imported: each kernel has its twin
    interpreted = _tiers.Interpreted()
    interpreted.enter(pure_cobs=False)
    cobs._warm = False  # a try with compiling forbidden may have marked it warm: in the plan
    try:
        if exercise is not None:
            exercise()
        else:
            exercise_run(profile, association, max_targets, track, toa_correction)
    except SpielError as exc:
        log.debug("interpreted plan: %s", exc)
    interpreted.use_pure_cobs()
    plan = [(*_tiers.where(k), t) for k, t in interpreted.calls]
    codegen = cpu_target.target_context.codegen()
    units = sorted(
        _tiers.qualified_name(k)
        for k in _tiers.reach([k for k, _t in interpreted.calls])
        if not (hasattr(k._cache, "has_copy") and k._cache.has_copy(codegen))
    )
    return interpreted, plan, units
