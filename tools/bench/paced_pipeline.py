"""The same pipeline call, back to back and paced (docs/first-start.md, "Paced at 50/s").

    python -m tools.bench.paced_pipeline [N]

The fused pipeline (four targets) and the record's JSON encoding on the vendored
acquisitions, one thread, ``time.thread_time`` around each call: back to back, after a sleep
of 0.5, 3 (a board as fast as it can) and 20 ms (a board at 50/s), and after a 20 ms busy
loop. No I/O and no loop of the run path's:
what the pacing alone costs on this machine.
"""

import json
import os
import sys
import time
from importlib import resources

import numpy as np

from spiel_edge.pipeline.factory import build_pipeline
from spiel_edge.profile.schema import resolve_profile
from spiel_edge.recordings.labelled import load_labelled

SUBSET = str(resources.files("spiel_edge") / "data" / "spiel_icra23_subset.npz")


def _spin(seconds: float) -> None:
    t = time.perf_counter()
    while time.perf_counter() - t < seconds:
        pass


def main(n: int) -> dict:
    pipeline = build_pipeline(resolve_profile("spiel-icra23"))
    pipeline.set_max_targets(4)
    recs = list(load_labelled(SUBSET).recordings())

    def one(r) -> float:
        t = time.thread_time()
        json.dumps(pipeline.process(r.frames, r.background).record())
        return time.thread_time() - t

    for r in recs[:20]:
        one(r)
    out = {}
    for name, before in (
        ("back_to_back", lambda: None),
        ("sleep_0.5ms", lambda: time.sleep(0.0005)),
        ("sleep_3ms", lambda: time.sleep(0.003)),  # a board as fast as it can: one window
        ("sleep_20ms", lambda: time.sleep(0.02)),
        ("back_to_back_again", lambda: None),
        ("busy_20ms", lambda: _spin(0.02)),
    ):
        cpu = []
        for i in range(n):
            before()
            cpu.append(one(recs[i % len(recs)]))
        out[name] = round(float(np.median(cpu)) * 1e6, 1)
    out["unit"] = "median CPU us per acquisition"
    out["load"] = [round(v, 2) for v in os.getloadavg()]
    return out


if __name__ == "__main__":
    print(json.dumps(main(int(sys.argv[1]) if len(sys.argv) > 1 else 300)))
