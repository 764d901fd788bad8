"""Compile (or load from numba's cache) every pipeline kernel, and report where each came from.

numba caches compiled kernels beside the sources, or, when the install is read-only, in
NUMBA_CACHE_DIR (the service kit sets it) or the user's cache folder. A warm start then loads
machine code instead of compiling: ``warmup()`` tells which kernels hit the cache.
"""

from __future__ import annotations

import time

from numba.core.registry import CPUDispatcher

from spiel_edge.pipeline import associate, detect, echo_quality, features, locate, memg, preprocess


def pipeline_kernels() -> dict[str, CPUDispatcher]:
    """The entry kernels (``_*_kernel``) of the pipeline modules, by qualified name; the
    helpers they call are compiled into them and cached with them."""
    out = {}
    for module in (preprocess, detect, memg, features, associate, echo_quality, locate):
        for name, obj in vars(module).items():
            if isinstance(obj, CPUDispatcher) and name.endswith("_kernel"):
                out[f"{module.__name__}.{name}"] = obj
    return out


def warmup() -> dict:
    """Run one vendored acquisition through the default pipeline; report compile/cache use."""
    from spiel_edge.data import load_subset
    from spiel_edge.pipeline.factory import build_pipeline
    from spiel_edge.profile.schema import load_profile

    t0 = time.perf_counter()
    subset = load_subset()
    pipeline = build_pipeline(load_profile(), "geometric")
    pipeline.process(subset.frames[0], subset.backgrounds[0])
    kernels = pipeline_kernels()
    used = {name: k for name, k in kernels.items() if k.signatures}
    return {
        "seconds": round(time.perf_counter() - t0, 3),
        "kernels": len(used),
        "cache_hits": sorted(n for n, k in used.items() if sum(k.stats.cache_hits.values())),
        "compiled": sorted(n for n, k in used.items() if k.stats.cache_misses),
    }
