"""The compiled path against the staged one, in one process (docs/performance.md).

    python -m tools.bench.bench_back [REPEAT]

Interleaved per acquisition: the compiled path (A, one kernel call with the numba MLP), the
staged path with the numba MLP (B) and with onnxruntime (C, what an association model that is
not the known MLP runs); median and p95 us and each one's ratio to A, on the vendored real
4 x 64 and 30 synthetic 16 x 1024 acquisitions.
"""

import json
import sys
import time

import numpy as np

from spiel_edge.data import load_subset
from spiel_edge.pipeline.compiled.fused import FusedPipeline
from spiel_edge.pipeline.learned.associate_onnx import OnnxAssociator, load_session
from spiel_edge.pipeline.staged import Pipeline
from spiel_edge.profile.schema import load_profile
from spiel_edge.sim.synthetic import ring_profile, synthesize


def configs(profile):
    numba_assoc = OnnxAssociator(profile)
    ort_assoc = OnnxAssociator(profile)
    ort_assoc.mlp, ort_assoc.engine = None, "onnxruntime"
    ort_assoc.session = load_session(ort_assoc.model_path)
    p_numba, p_ort = Pipeline(profile, numba_assoc), Pipeline(profile, ort_assoc)
    return {
        "A compiled": FusedPipeline(p_numba),
        "B staged, numba MLP": p_numba,
        "C staged, onnxruntime": p_ort,
    }


def run(name, profile, frames, backgrounds, repeat):
    cfg = configs(profile)
    times = {k: [] for k in cfg}
    for p in cfg.values():
        p.process(frames[0], backgrounds[0])
    for _ in range(repeat):
        for f, bg in zip(frames, backgrounds, strict=True):
            for k, p in cfg.items():
                t = time.perf_counter_ns()
                p.process(f, bg)
                times[k].append((time.perf_counter_ns() - t) / 1e3)
    out = {
        k: (round(float(np.median(v)), 1), round(float(np.percentile(v, 95)), 1))
        for k, v in times.items()
    }
    a = out["A compiled"][0]
    print(
        name,
        json.dumps(
            {
                k: {"median_us": m, "p95_us": p, "ratio_to_A": round(m / a, 2)}
                for k, (m, p) in out.items()
            }
        ),
    )


def main() -> None:
    repeat = int(sys.argv[1]) if len(sys.argv) > 1 else 3
    s = load_subset()
    run("real_4x64", load_profile("spiel-icra23"), s.frames, s.backgrounds, repeat)
    prof = ring_profile(16, 1024)
    rng = np.random.default_rng(0)
    pairs = [
        synthesize(prof, np.c_[rng.uniform(-80, 80, (2, 2)), rng.uniform(100, 300, 2)], seed=i)
        for i in range(30)
    ]
    run("synthetic_16x1024", prof, [p[0] for p in pairs], [p[1] for p in pairs], repeat)


if __name__ == "__main__":
    main()
