"""One SHA-256 over every Result of the fused pipeline: kernels changed, results the same?

    python -m tools.bench.results_digest

The vendored 4 x 64 acquisitions through the fused pipeline, geometric and learned
association, one and four targets, with and without their background: each Result's features
and every field of each target, as bytes. Run it on two checkouts (``PYTHONPATH``) and compare
the lines (docs/first-start.md, "Cold compile").
"""

import hashlib

import numpy as np

from spiel_edge.data import load_subset
from spiel_edge.pipeline.factory import build_pipeline
from spiel_edge.profile.schema import load_profile


def digest() -> tuple[int, str]:
    subset, profile = load_subset(), load_profile()
    h, n = hashlib.sha256(), 0
    for association in ("geometric", "auto"):
        pipeline = build_pipeline(profile, association, fused=True)
        for k in (1, 4):
            pipeline.set_max_targets(k)
            for frames, background in zip(subset.frames, subset.backgrounds, strict=True):
                for bg in (background, None):
                    result = pipeline.process(frames, bg)
                    h.update(np.ascontiguousarray(result.features).tobytes())
                    for target in result.targets:
                        fields = sorted(vars(target).items())
                        h.update(repr([(name, _raw(v)) for name, v in fields]).encode())
                    n += 1
    return n, h.hexdigest()


def _raw(value):
    return value.tobytes() if isinstance(value, np.ndarray) else value


if __name__ == "__main__":
    count, hexdigest = digest()
    print(f"{count} results {hexdigest}")
