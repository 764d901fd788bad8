import json
import os
import subprocess
import sys

SNIPPET = "import json; from spiel_edge.runtime.warmup import warmup; print(json.dumps(warmup()))"


def run_fresh(cache_dir):
    env = {**os.environ, "NUMBA_CACHE_DIR": str(cache_dir)}
    out = subprocess.run(
        [sys.executable, "-c", SNIPPET],
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
        check=True,
    )
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_second_start_loads_every_kernel_from_the_cache(tmp_path):
    first = run_fresh(tmp_path)
    assert first["kernels"] >= 6 and first["compiled"]
    second = run_fresh(tmp_path)
    assert second["compiled"] == []
    assert len(second["cache_hits"]) == second["kernels"] >= 10
    assert first["kernels"] >= second["kernels"]  # cold: helpers compiled as callees count too
    assert any(tmp_path.rglob("*.nbi"))
