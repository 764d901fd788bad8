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

log = logging.getLogger(__name__)


KERNEL_PACKAGES = ("spiel_edge.pipeline", "spiel_edge.io", "spiel_edge.track", "firmware_protocol")


def pipeline_kernels() -> dict[str, object]:
    """Every cached numba dispatcher defined in the pipeline, io, tracker and stream-decoder
    modules, by qualified name (modules whose optional dependency is missing are skipped)."""
    found = {}
    for package_name in KERNEL_PACKAGES:
        package = importlib.import_module(package_name)
        for info in pkgutil.iter_modules(package.__path__):
            name = f"{package_name}.{info.name}"
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


def _exercise() -> None:
    from spiel_edge.data import load_subset
    from spiel_edge.io.spiel_csv import _read_integers
    from spiel_edge.pipeline.factory import build_pipeline
    from spiel_edge.profile.schema import load_profile

    _read_integers(b"0 15 860\n0 8 54\n")  # the spiel-csv scanner (replay, evaluate)

    subset = load_subset()
    profile = load_profile()
    pairs = list(zip(subset.frames[:4], subset.backgrounds[:4], strict=True))
    results = []
    for association in ("geometric", "auto"):
        for fused in (True, False):
            pipeline = build_pipeline(profile, association, fused=fused)
            for k in (1, 4):  # one target (the back kernel) and several (the scene's choice)
                pipeline.set_max_targets(k)
                for f, b in pairs:
                    results.append(pipeline.process(f, b))
                results.append(pipeline.process(pairs[0][0], None))  # the static-scene stand-in
    _exercise_tracker(profile, results)
    _exercise_stream()
    rf = profile.replace(
        acquisition=dataclasses.replace(profile.acquisition, signal="rf", carrier_hz=5000.0)
    )
    for fused in (True, False):
        build_pipeline(rf, "geometric", fused=fused).process(*pairs[0])
    split = profile.replace(memg=dataclasses.replace(profile.memg, split_merged=True))
    for fused in (True, False):
        build_pipeline(split, "geometric", fused=fused).process(pairs[0][0])  # off by default
    ring, frames, background = _ring_input()
    for fused in (True, False):
        build_pipeline(ring, "geometric", fused=fused).process(frames, background)


def _exercise_tracker(profile, results) -> None:
    """The tracker's kernels (``run`` tracks by default), fed the results above in turn."""
    from spiel_edge.runtime.tracking import ResultTracker

    tracker = ResultTracker(profile.track)
    for i, result in enumerate(results):
        tracker.update(result, 0.02 * i)


def _exercise_stream() -> None:
    """The stream decoder's COBS kernels (a live board, the virtual one included)."""
    from firmware_protocol import cobs
    from spiel_edge.device.iq import iq_amplitude

    cobs.warm_up()
    pairs = np.zeros((1, 2), dtype=np.int16)  # I/Q streams (protocol 2): writable and
    iq_amplitude(pairs)  # read-only (reassembled) samples are two signatures
    pairs.setflags(write=False)
    iq_amplitude(pairs)


def warmup() -> dict:
    """Run inputs through every kernel; report seconds, kernels and where each came from."""
    t0 = time.perf_counter()
    _exercise()
    kernels = pipeline_kernels()
    used = {name: k for name, k in kernels.items() if k.signatures}
    return {
        "seconds": round(time.perf_counter() - t0, 3),
        # dispatchers run (a cold start also counts the helpers compiled into the kernels)
        "kernels": len(used),
        "cache_hits": sorted(n for n, k in used.items() if sum(k.stats.cache_hits.values())),
        "compiled": sorted(n for n, k in used.items() if k.stats.cache_misses),
        "cache_dir": cache_dir(),
    }


def cache_dir() -> str | None:
    """Where numba caches the pipeline's kernels in this environment (None: nowhere usable)."""
    try:
        from spiel_edge.pipeline import detect
    except RuntimeError as exc:  # numba raises at import when no cache location is writable
        log.debug("numba cache: %s", exc)
        return None
    return str(detect._detect_kernel._cache._cache_path)
