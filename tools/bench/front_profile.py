"""The front kernel's pieces timed in-process on bench's 4 x 64 and 16 x 1024 sets (median us).

    cd /tmp && PYTHONPATH=<worktree> python <worktree>/tools/bench/front_profile.py

(docs/history/front-speed.md; PYTHONPATH from a non-worktree cwd picks the tree to time).
"""

import time

import numpy as np

from spiel_edge.data import load_subset
from spiel_edge.measure.bench import synthetic_set
from spiel_edge.pipeline.compiled import front as F
from spiel_edge.pipeline.compiled.fused import FusedPipeline
from spiel_edge.pipeline.staged import Pipeline
from spiel_edge.pipeline.stages.detect import detect_kernel
from spiel_edge.pipeline.stages.features import features_kernel
from spiel_edge.pipeline.stages.memg import memg_kernel
from spiel_edge.pipeline.stages.preprocess import preprocess_kernel
from spiel_edge.profile.schema import load_profile

clk = time.perf_counter_ns


def prof(name, prof, frames, bgs, rounds):
    fp = FusedPipeline(Pipeline(prof))
    ws = fp._workspaces.get()
    (blind, rf, car, hw, hi, lo, mina, muw, maxit, split, sms, smr, toa) = fp._scalars
    (env, bg_env, cleaned, peaks, counts, params, iters, uns, feats) = ws.front_buffers
    T = {k: [] for k in ("front", "finite", "pre", "det", "memg", "feat", "order", "process")}
    for r in range(rounds + 1):
        for f, b in zip(frames, bgs, strict=True):
            t0 = clk()
            F._front_kernel(f, b, *fp._scalars, *ws.front_buffers)
            t1 = clk()
            F._all_finite(f)
            F._all_finite(b)
            t2 = clk()
            preprocess_kernel(f, b, blind, cleaned)
            t3 = clk()
            peaks[:, :] = -1
            counts[:] = 0
            t3 = clk()
            detect_kernel(cleaned, hi, lo, mina, blind, peaks, counts)
            t4 = clk()
            params[:] = np.nan
            iters[:] = 0
            t4b = clk()
            memg_kernel(cleaned, peaks, counts, muw, maxit, params, iters)
            t5 = clk()
            uns[:] = np.nan
            t5b = clk()
            features_kernel(cleaned, params, peaks, toa, uns)
            t6 = clk()
            F._order_by_toa(uns, feats)
            t7 = clk()
            fp.process(f, b)
            t8 = clk()
            if r:
                for k, v in zip(
                    T,
                    (t1 - t0, t2 - t1, t3 - t2, t4 - t3, t5 - t4b, t6 - t5b, t7 - t6, t8 - t7),
                    strict=True,
                ):
                    T[k].append(v / 1e3)
    print(
        name,
        " ".join(f"{k}={np.median(v):.1f}" for k, v in T.items()),
        f"echoes/acq={counts.sum()}",
    )
    return T


sub = load_subset()
prof("4x64", load_profile(), sub.frames, sub.backgrounds, 5)
p16, fr, bg = synthetic_set(16, 1024, 30)
prof("16x1024", p16, fr, bg, 5)
