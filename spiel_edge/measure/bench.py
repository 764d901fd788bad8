"""Benchmarks: microseconds per acquisition for each stage and end to end, start-up time and
peak memory of a service run.

Real 4 x 64 acquisitions come from the vendored recordings; synthetic 8 x 256 and 16 x 1024
acquisitions from the virtual board's echo model (:mod:`spiel_edge.sim.synthetic`, two targets each). Start-up is measured in
fresh interpreters: the second start must load numba's compiled kernels from its cache.

End-to-end figures of the fused path (:mod:`spiel_edge.pipeline.compiled.fused`, what the CLI runs)
and of the staged path (``Pipeline.process``) are measured interleaved, acquisition by
acquisition, so both see the same machine load; the plain numpy/scipy reference of the same
method (:mod:`spiel_edge.measure.reference`) runs on a few acquisitions when scipy is
installed, and the ratios are reference / fused and staged / fused from this one run.
"""

from __future__ import annotations

import json
import logging
import os
import subprocess
import sys
import time

import numpy as np

from spiel_edge.data import load_subset
from spiel_edge.measure import reference
from spiel_edge.measure.bench_ros2 import ros2_encoding_us
from spiel_edge.measure.bench_track import time_tracker
from spiel_edge.pipeline.compiled.fused import FusedPipeline
from spiel_edge.pipeline.factory import build_pipeline
from spiel_edge.pipeline.staged import STAGES, Pipeline
from spiel_edge.profile.schema import load_profile
from spiel_edge.sim.synthetic import ring_profile, synthesize

log = logging.getLogger(__name__)

STARTUP_SNIPPET = (
    "from spiel_edge.data import load_subset;"
    "from spiel_edge.pipeline.factory import build_pipeline;"
    "from spiel_edge.profile.schema import load_profile;"
    "from spiel_edge.runtime.warmup import pipeline_kernels;"
    "s = load_subset(); p = build_pipeline(load_profile());"
    "p.process(s.frames[0], s.backgrounds[0]);"
    "print(sum(bool(k.stats.cache_misses) for k in pipeline_kernels().values()))"
)


def _summarise(timings: list[dict[str, float]]) -> dict:
    out = {}
    for stage in (*STAGES, "end_to_end"):
        values = np.array([t[stage] for t in timings])
        out[stage] = {
            "median_us": round(float(np.median(values)), 2),
            "p95_us": round(float(np.percentile(values, 95)), 2),
        }
    return out


def time_pipeline(
    pipeline: Pipeline, frames: np.ndarray, backgrounds: np.ndarray | None, repeat: int
) -> dict:
    """Per-stage timings over every acquisition, after one warm-up pass."""
    bgs = backgrounds if backgrounds is not None else [None] * len(frames)
    for f, b in zip(frames, bgs, strict=True):
        pipeline.process(f, b)
    timings = [
        pipeline.process(f, b, timed=True).timings_us
        for _ in range(repeat)
        for f, b in zip(frames, bgs, strict=True)
    ]
    return {"acquisitions": len(timings), **_summarise(timings)}


def _stats(values_us: list[float]) -> dict:
    v = np.array(values_us)
    return {
        "median_us": round(float(np.median(v)), 2),
        "p95_us": round(float(np.percentile(v, 95)), 2),
    }


def compare_paths(
    staged: Pipeline, frames: np.ndarray, backgrounds: np.ndarray | None, repeat: int
) -> dict:
    """End-to-end microseconds of the fused and the staged path, interleaved per acquisition
    (alternating which goes first), and their ratio of medians."""
    fused = FusedPipeline(staged)
    bgs = backgrounds if backgrounds is not None else [None] * len(frames)
    pairs = list(zip(frames, bgs, strict=True))
    for f, b in pairs:  # warm both (compilation, caches)
        fused.process(f, b)
        staged.process(f, b)
    times = {"fused": [], "staged": []}
    clock = time.perf_counter_ns
    for r in range(repeat):
        for i, (f, b) in enumerate(pairs):
            order = (fused, staged) if (r + i) % 2 == 0 else (staged, fused)
            for pipe in order:
                t0 = clock()
                pipe.process(f, b)
                times["fused" if pipe is fused else "staged"].append((clock() - t0) / 1e3)
    out = {name: _stats(v) for name, v in times.items()}
    out["staged_over_fused"] = round(out["staged"]["median_us"] / out["fused"]["median_us"], 2)
    return out


def reference_figures(profile, frames, backgrounds, fused_median_us: float, count: int) -> dict:
    """Milliseconds per acquisition of the numpy/scipy reference, and reference / fused."""
    if not reference.available():
        return {"available": False, "why": "scipy is not installed (pip install scipy)"}
    reference.process(profile, frames[0], backgrounds[0])  # imports scipy outside the timing
    times = []
    for f, b in zip(frames[:count], backgrounds[:count], strict=True):
        t0 = time.perf_counter_ns()
        reference.process(profile, f, b)
        times.append((time.perf_counter_ns() - t0) / 1e3)
    median = float(np.median(times))
    return {
        "available": True,
        "acquisitions": len(times),
        "median_ms": round(median / 1e3, 2),
        "reference_over_fused": round(median / fused_median_us, 1),
    }


def synthetic_set(n_channels: int, n_samples: int, count: int, seed: int = 0):
    profile = ring_profile(n_channels, n_samples)
    rng = np.random.default_rng(seed)
    pairs = [
        synthesize(
            profile, np.c_[rng.uniform(-80, 80, (2, 2)), rng.uniform(100, 300, 2)], seed=seed + i
        )
        for i in range(count)
    ]
    return profile, np.array([f for f, _ in pairs]), np.array([b for _, b in pairs])


def startup_seconds(runs: int = 2) -> list[float]:
    """Wall time of fresh interpreters importing the pipeline and processing one acquisition
    (logged: how many kernels each had to compile, 0 when the cache is warm)."""
    times = []
    for _ in range(runs):
        t0 = time.perf_counter()
        out = subprocess.run(
            [sys.executable, "-c", STARTUP_SNIPPET],
            check=True,
            capture_output=True,
            text=True,
            timeout=600,
        )
        times.append(round(time.perf_counter() - t0, 3))
        log.info("start-up compiled %s kernel(s)", out.stdout.strip().splitlines()[-1])
    return times


SERVICE_RUN = ("run", "--port", "sim://", "--frames", "300", "-o", os.devnull)
# The child reports its own high-water mark at exit: the kernel's wait4/ru_maxrss would carry
# this (large) parent's RSS over fork and exec into the child's figure.
PEAK_SNIPPET = """
import atexit, sys
def _peak():
    with open("/proc/self/status") as status:
        sys.stderr.write(next(line for line in status if line.startswith("VmHWM:")))
atexit.register(_peak)
from spiel_edge.cli import main
sys.exit(main(sys.argv[1:]))
"""


def peak_rss_mib(args: tuple[str, ...] = SERVICE_RUN, timeout_s: float = 300.0) -> float | None:
    """Peak resident memory (MiB) of a fresh ``spiel-edge ARGS`` process (its ``VmHWM``;
    None where /proc has none); a run that fails or outlives ``timeout_s`` raises
    RuntimeError."""
    if not os.path.exists("/proc/self/status"):
        return None
    cmd = [sys.executable, "-c", PEAK_SNIPPET, *args]
    try:
        out = subprocess.run(
            cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, timeout=timeout_s
        )
    except subprocess.TimeoutExpired:
        raise RuntimeError(f"spiel-edge {' '.join(args)} ran longer than {timeout_s} s") from None
    if out.returncode:
        raise RuntimeError(f"spiel-edge {' '.join(args)} exited with {out.returncode}")
    line = [ln for ln in out.stderr.splitlines() if ln.startswith("VmHWM:")][-1]
    return round(int(line.split()[1]) / 1024.0, 1)


def run_bench(
    repeat: int = 5, association: str | None = None, startup: bool = True, reference_count: int = 8
) -> dict:
    subset = load_subset()
    profile = load_profile()
    pipeline = build_pipeline(profile, association, fused=False)
    result = {
        "association": getattr(pipeline.associator, "name", type(pipeline.associator).__name__),
        "real_4x64": time_pipeline(pipeline, subset.frames, subset.backgrounds, repeat),
        "paths_4x64": compare_paths(pipeline, subset.frames, subset.backgrounds, repeat),
    }
    for n_ch, n_t, count in ((8, 256, 100), (16, 1024, 30)):
        prof, frames, backgrounds = synthetic_set(n_ch, n_t, count)
        result[f"synthetic_{n_ch}x{n_t}"] = time_pipeline(
            Pipeline(prof), frames, backgrounds, max(1, repeat // 2)
        )
        result[f"paths_{n_ch}x{n_t}"] = compare_paths(
            Pipeline(prof), frames, backgrounds, max(1, repeat // 2)
        )
    if reference_count > 0:
        result["reference_4x64"] = reference_figures(
            profile,
            subset.frames,
            subset.backgrounds,
            result["paths_4x64"]["fused"]["median_us"],
            reference_count,
        )
    result["end_to_end"] = result["real_4x64"]["end_to_end"]
    for stage in STAGES:
        result[stage] = result["real_4x64"][stage]
    result["max_targets_4"] = max_targets_cost(pipeline, subset.frames, repeat)
    result["scene_4_tracked"] = tracked_scene_cost(
        build_pipeline(profile, association), subset.frames, repeat
    )
    result["onnx_scoring"] = _onnx_scoring(profile)
    result["ros2_encoding"] = ros2_encoding_us()
    result["tracker_8_tracks"] = time_tracker()
    if startup:
        result["startup_s"] = startup_seconds()
        result["peak_rss_mib"] = peak_rss_mib()  # issue 14: run --port sim:// --frames 300
    return result


def max_targets_cost(pipeline: Pipeline, frames: np.ndarray, repeat: int, k: int = 4) -> dict:
    """Median end-to-end us with up to ``k`` targets vs one, on the same frames WITHOUT a
    background (the robot's case, where further targets are searched most), in one run."""
    single, multi = [], []
    before = pipeline.max_targets
    try:
        for _ in range(max(1, repeat // 2)):
            for limit, out in ((1, single), (k, multi)):
                pipeline.set_max_targets(limit)
                for f in frames:
                    out.append(pipeline.process(f, None, timed=True).timings_us["end_to_end"])
    finally:
        pipeline.set_max_targets(before)
    one, many = float(np.median(single)), float(np.median(multi))
    return {
        "k": k,
        "single_median_us": round(one, 2),
        "k_median_us": round(many, 2),
        "ratio": round(many / one, 3),
    }


def tracked_scene_cost(pipeline, frames: np.ndarray, repeat: int, k: int = 4) -> dict:
    """What a robot's acquisition costs on the default (fused) path: up to ``k`` targets
    WITHOUT a background, then the tracker's update; end-to-end microseconds per acquisition
    (the acquisitions in recording order, 20 ms apart)."""
    from spiel_edge.runtime.track_records import ResultTracker

    pipeline.set_max_targets(k)
    tracker = ResultTracker(pipeline.profile.track)
    for i, f in enumerate(frames):  # warm: kernels loaded, tracks born
        tracker.update(pipeline.process(f, None), 0.02 * i)
    times, clock, t_s = [], time.perf_counter_ns, 0.02 * len(frames)
    for _ in range(repeat):
        for f in frames:
            t0 = clock()
            tracker.update(pipeline.process(f, None), t_s)
            times.append((clock() - t0) / 1e3)
            t_s += 0.02
    return {"k": k, "acquisitions": len(times), **_stats(times)}


def _onnx_scoring(profile) -> dict | None:
    """Microseconds to score one acquisition's echoes with the ONNX model (None without it)."""
    from spiel_edge.errors import ModelError

    try:
        from spiel_edge.pipeline.learned.associate_onnx import bench_scoring

        return bench_scoring(n=1000, profile=profile)
    except (ImportError, ModelError):
        return None


def to_json(result: dict) -> str:
    return json.dumps(result, separators=(",", ":"))
