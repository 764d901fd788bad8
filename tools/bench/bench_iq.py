"""The fused 4 x 64 pipeline with envelope input and with I/Q input (the amplitude kernel of
spiel_edge/device/iq.py in front; the phase is computed only when recorded), on model-scene
acquisitions of the virtual board.

    python tools/bench/bench_iq.py --repeat 3

Prints JSON: median microseconds per acquisition of each and their ratio.
"""

from __future__ import annotations

import argparse
import json
import os
import time

import numpy as np


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=3, help="passes over the acquisitions")
    parser.add_argument("--n", type=int, default=200, help="acquisitions")
    args = parser.parse_args()
    from spiel_edge.device.iq import iq_amplitude
    from spiel_edge.link.sim_options import SimOptions
    from spiel_edge.pipeline.factory import build_pipeline
    from spiel_edge.profile.schema import load_profile
    from spiel_edge.sim.scenes import build_scene

    scene = build_scene(SimOptions(scene="model", seed=1))
    frames = [scene.frame(i, 64, i / 30.0, iq=True) for i in range(args.n)]
    envs = [f.samples.astype(np.float64) for f in frames]
    iqs = [np.ascontiguousarray(f.iq.reshape(f.iq.shape[0], -1)) for f in frames]
    for a in iqs:
        a.setflags(write=False)  # as reassembled from the wire
    background = frames[0].background.astype(np.float64)
    pipeline = build_pipeline(load_profile("spiel-icra23"), None, "none")
    pipeline.process(envs[0], background)
    iq_amplitude(iqs[0])

    def envelope_path(k):
        return pipeline.process(envs[k], background)

    def iq_path(k):
        env = iq_amplitude(iqs[k])
        return pipeline.process(env, background)

    times = {"envelope": [], "iq": []}
    for _ in range(args.repeat):  # interleaved, so that the machine's load hits both alike
        for k in range(args.n):
            for name, fn in (("envelope", envelope_path), ("iq", iq_path)):
                t = time.perf_counter_ns()
                fn(k)
                times[name].append((time.perf_counter_ns() - t) / 1e3)
    kernel = []
    for k in range(args.n):
        t = time.perf_counter_ns()
        iq_amplitude(iqs[k])
        kernel.append((time.perf_counter_ns() - t) / 1e3)
    env_us, iq_us = (float(np.median(times[k])) for k in ("envelope", "iq"))
    print(
        json.dumps(
            {
                "acquisitions": args.n * args.repeat,
                "envelope_us": round(env_us, 2),
                "iq_us": round(iq_us, 2),
                "ratio": round(iq_us / env_us, 3),
                "iq_kernel_us": round(float(np.median(kernel)), 2),
                "loadavg": [round(v, 2) for v in os.getloadavg()],
            }
        )
    )


if __name__ == "__main__":
    main()
