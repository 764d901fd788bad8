"""The interpreted tier with and without its numpy forms (docs/first-start.md, "Round 4").

    python -m tools.bench.tier_forms [ROUNDS]

``interpreted_tier()`` of ``spiel_edge.measure.bench_run`` (the fused pipeline and tracker on
16 vendored acquisitions, twice), alternating: the twins as registered (``numpy``) and with
``_tiers.NUMPY_FORMS`` emptied (``python``: every twin its kernel's Python function). Each in a
fresh interpreter, so the forms are registered or not from the start.
"""

import json
import os
import subprocess
import sys

ONE = """
import json, sys
from spiel_edge import _tiers
from spiel_edge.measure.bench_run import interpreted_tier
import spiel_edge.pipeline.learned.mlp, spiel_edge.pipeline.learned.tree_ensemble
if sys.argv[1] == "python":
    _tiers.NUMPY_FORMS.clear()
print(json.dumps(interpreted_tier()))
"""


def main(rounds: int) -> None:
    for _ in range(rounds):
        for form in ("python", "numpy"):
            out = subprocess.run(
                [sys.executable, "-c", ONE, form], capture_output=True, text=True, check=True
            )
            result = json.loads(out.stdout.strip().splitlines()[-1])
            load = [round(v, 2) for v in os.getloadavg()]
            print(json.dumps({"twins": form, **result, "load": load}), flush=True)


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 2)
