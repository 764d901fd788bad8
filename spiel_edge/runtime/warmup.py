"""Compile (or load from numba's cache) every pipeline kernel, and report where each came from.

numba caches compiled kernels beside the sources, or, when the install is read-only, in
NUMBA_CACHE_DIR (the service kit sets it) or the user's cache folder. A warm start then loads
machine code instead of compiling. ``warmup()`` runs inputs that reach every kernel: the
vendored real acquisitions through the staged and the fused path (the geometric and, when it
loads, the learned associator; one target and four; with and without a background), the
tracker on those results, the stream decoder's COBS kernels, an RF variant of the profile
(envelope kernel) and a closed-form 8-channel acquisition (the hypothesise-and-verify
associator); it never imports the simulator. ``pipeline_kernels()`` is the one kernel finder (warm-up, doctor and bench).
"""

from __future__ import annotations

import dataclasses
import importlib
import logging
import math
import pkgutil
import time

import numpy as np

from spiel_edge.runtime.warmup_child import WarmupError, run_child

log = logging.getLogger(__name__)
__all__ = ["STEPS", "WarmupError", "run_child", "pipeline_kernels", "warmup"]


KERNEL_PACKAGES = (
    "spiel_edge.pipeline",
    "spiel_edge.recordings",
    "spiel_edge.device",
    "spiel_edge.track",
    "spiel_edge.protocol",
)


def pipeline_kernels() -> dict[str, object]:
    """Every cached numba dispatcher defined in the pipeline, io, tracker and stream-decoder
    modules, by qualified name (modules whose optional dependency is missing are skipped)."""
    found = {}
    for package_name in KERNEL_PACKAGES:
        try:
            package = importlib.import_module(package_name)
        except ImportError:  # a package renamed or gone: its kernels are not found here
            log.warning("kernel package %s not found", package_name)
            continue
        # sub-packages too (the pipeline's stages may live in sub-packages)
        for info in pkgutil.walk_packages(package.__path__, prefix=f"{package_name}."):
            name = info.name
            try:
                module = importlib.import_module(name)
            except ImportError:
                continue
            for attr, obj in vars(module).items():
                if (
                    getattr(obj, "_cache", None) is not None
                    and hasattr(obj, "stats")
                    and getattr(obj, "__module__", "") == name
                ):
                    found[f"{name}.{attr}"] = obj
    return found


def closed_form_acquisition(profile, target_mm=(0.0, 0.0, 150.0)):
    """``(frames, background)`` of ``profile``'s shape: one EMG-shaped echo per channel at the
    target's echo time (a closed form, no simulator), on an empty background."""
    g = profile.geometry
    toa = g.echo_paths_mm(np.asarray(target_mm, dtype=np.float64)) / profile.mm_per_sample
    u = (np.arange(profile.acquisition.n_samples)[None, :] - (toa + g.delays())[:, None]) / 1.5
    skew = np.vectorize(lambda v: 1.0 + math.erf(v / math.sqrt(2.0)))(u)
    frames = 2000.0 * np.exp(-0.5 * u * u) * skew
    return frames, np.zeros_like(frames)


def _ring_input(n_channels: int = 8, n_samples: int = 128):
    """A ring-array profile and a closed-form acquisition of a target 200 mm in front."""
    from spiel_edge.profile.schema import AcquisitionSpec, Geometry, Profile

    angles = np.linspace(0.0, 2.0 * np.pi, n_channels - 1, endpoint=False)
    ring = np.c_[75.0 * np.cos(angles), 75.0 * np.sin(angles), np.zeros(n_channels - 1)]
    geometry = Geometry(
        channels_mm=np.vstack([np.zeros(3), ring]), delay_samples=np.zeros(n_channels)
    )
    profile = Profile(
        name="warmup-ring", geometry=geometry, acquisition=AcquisitionSpec(n_samples=n_samples)
    )
    return (profile, *closed_form_acquisition(profile, (20.0, -10.0, 200.0)))


def _step_csv() -> None:
    from spiel_edge.recordings.spiel_csv import read_integers

    read_integers(b"0 15 860\n0 8 54\n")  # the spiel-csv scanner (replay, evaluate)


def _vendored_pairs(n: int = 4):
    from spiel_edge.data import load_subset

    subset = load_subset()
    return list(zip(subset.frames[:n], subset.backgrounds[:n], strict=True))


def _pipeline_results(association: str, fused: bool) -> list:
    """The vendored acquisitions through one pipeline: one target (the back kernel) and
    several (the scene's choice), with and without a background (the static-scene stand-in)."""
    from spiel_edge.pipeline.factory import build_pipeline
    from spiel_edge.profile.schema import load_profile

    pairs = _vendored_pairs()
    pipeline = build_pipeline(load_profile(), association, fused=fused)
    results = []
    for k in (1, 4):
        pipeline.set_max_targets(k)
        for f, b in pairs:
            results.append(pipeline.process(f, b))
        results.append(pipeline.process(pairs[0][0], None))
    return results


def _step_tracker() -> None:
    """The tracker's kernels (``run`` tracks by default), fed the fused geometric results."""
    from spiel_edge.profile.schema import load_profile
    from spiel_edge.runtime.track_records import ResultTracker

    results = _pipeline_results("geometric", True) + _pipeline_results("auto", True)
    tracker = ResultTracker(load_profile().track)
    for i, result in enumerate(results):
        tracker.update(result, 0.02 * i)


def step_stream() -> None:
    """The stream decoder's COBS kernels (a live board, the virtual one included)."""
    from spiel_edge.device.iq import iq_amplitude
    from spiel_edge.protocol import cobs

    cobs.warm_up()
    pairs = np.zeros((1, 2), dtype=np.int16)  # I/Q streams (protocol 2): writable and
    iq_amplitude(pairs)  # read-only (reassembled) samples are two signatures
    pairs.setflags(write=False)
    iq_amplitude(pairs)


def _step_variants() -> None:
    """Profiles off the default path: an RF signal (envelope kernel), merged-echo splitting,
    and an 8-channel ring (the hypothesise-and-verify associator)."""
    from spiel_edge.pipeline.factory import build_pipeline
    from spiel_edge.profile.schema import load_profile

    profile = load_profile()
    pairs = _vendored_pairs(1)
    rf = profile.replace(
        acquisition=dataclasses.replace(profile.acquisition, signal="rf", carrier_hz=5000.0)
    )
    split = profile.replace(memg=dataclasses.replace(profile.memg, split_merged=True))
    ring, frames, background = _ring_input()
    for fused in (True, False):
        build_pipeline(rf, "geometric", fused=fused).process(*pairs[0])
        build_pipeline(split, "geometric", fused=fused).process(pairs[0][0])  # off by default
        build_pipeline(ring, "geometric", fused=fused).process(frames, background)


# The warm-up in steps, each small enough to compile in its own process within a bounded
# memory (numba keeps every module it compiled until the process ends): the fused path first,
# the one `run` takes, then what shares its kernels.
STEPS = {
    "stream": step_stream,
    "fused-geometric": lambda: _pipeline_results("geometric", True),
    "fused-learned": lambda: _pipeline_results("auto", True),
    "staged-geometric": lambda: _pipeline_results("geometric", False),
    "staged-learned": lambda: _pipeline_results("auto", False),
    "tracker": _step_tracker,
    "variants": _step_variants,
    "csv": _step_csv,
}


ENV_PLAN = "SPIEL_EDGE_COMPILE_PLAN"  # a tiered start's plan file (runtime/tier_compile.py)


def _step_plan() -> None:
    """A tiered start's compile plan: every call of ``$SPIEL_EDGE_COMPILE_PLAN`` (a pickle of
    ``[(module, attribute, argument types)]``) compiled or loaded; not part of a full warm-up."""
    import os
    import pickle

    with open(os.environ[ENV_PLAN], "rb") as fh:
        plan = pickle.load(fh)
    for module, attr, argtypes in plan:
        getattr(importlib.import_module(module), attr).compile(argtypes)


EXTRA_STEPS = {"plan": _step_plan}  # run by name only (warmup_child), never by _exercise


def _exercise(steps=None) -> None:
    for name in steps or STEPS:
        STEPS[name]()


def _report(t0: float, kernels: dict) -> dict:
    used = {name: k for name, k in kernels.items() if k.signatures}
    return {
        "seconds": round(time.perf_counter() - t0, 3),
        # dispatchers run (a cold start also counts the helpers compiled into the kernels)
        "kernels": len(used),
        "cache_hits": sorted(n for n, k in used.items() if sum(k.stats.cache_hits.values())),
        "compiled": sorted(n for n, k in used.items() if k.stats.cache_misses),
        "cache_dir": cache_dir(),
    }


def warmup(isolate: bool = True, progress=None) -> dict:
    """Run inputs through every kernel; report seconds, kernels and where each came from.

    ``isolate``: each step in a child process of its own (peak memory that of the largest
    step, not of all), else all here. ``progress``: a ``compile_progress.Progress`` (or any
    ``_kernel_cache`` listener) told of each kernel compiled. ``peak_rss_mib``: the largest
    resident size of this process and its children."""
    t0 = time.perf_counter()
    if not isolate:
        from spiel_edge import _kernel_cache

        if progress is not None:
            _kernel_cache.listeners.append(progress)
        try:
            _exercise()
        finally:
            if progress is not None:
                _kernel_cache.listeners.remove(progress)
        report = _report(t0, pipeline_kernels())
    else:
        report = _isolated(t0, progress)
    report["peak_rss_mib"] = peak_rss_mib()
    return report


def _isolated(t0: float, progress) -> dict:
    merged: dict = {"kernels": set(), "cache_hits": set(), "compiled": set()}
    for step in STEPS:
        child = run_child(step, progress)
        for key in merged:
            merged[key].update(child[key])
    return {
        "seconds": round(time.perf_counter() - t0, 3),
        "kernels": len(merged["kernels"]),
        "cache_hits": sorted(merged["cache_hits"]),
        "compiled": sorted(merged["compiled"]),
        "cache_dir": cache_dir(),
    }


def peak_rss_mib() -> float:
    """The largest resident set of this process and of any child it waited for, in MiB."""
    import resource

    own = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    children = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    return round(max(own, children) / 1024.0, 1)  # Linux: KiB


def cache_dir() -> str | None:
    """Where numba caches the pipeline's kernels in this environment (None: nowhere usable)."""
    try:
        from spiel_edge.pipeline.stages import detect
    except RuntimeError as exc:  # numba raises at import when no cache location is writable
        log.debug("numba cache: %s", exc)
        return None
    cache = detect.detect_kernel._cache
    return str(cache._cache_path) if getattr(cache, "writable", True) else None


if __name__ == "__main__":
    import sys

    from spiel_edge.runtime import warmup  # this module under its own name, not __main__
    from spiel_edge.runtime.warmup_child import child_main

    sys.exit(child_main(sys.argv[1:], warmup))
