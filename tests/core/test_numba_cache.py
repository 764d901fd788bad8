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


def _cache_files(cache_dir) -> dict:
    return {str(p): (p.stat().st_size, p.stat().st_mtime_ns) for p in cache_dir.rglob("*.nb[ic]")}


def _cli(cache_dir, *args) -> None:
    env = {**os.environ, "NUMBA_CACHE_DIR": str(cache_dir)}
    cmd = [sys.executable, "-m", "spiel_edge.cli", *map(str, args), "-o", os.devnull]
    subprocess.run(cmd, env=env, capture_output=True, timeout=600, check=True)


def test_second_start_loads_every_kernel_from_the_cache(tmp_path, subset):
    from tests.core.spiel_csv_fixture import write_spiel_csv

    cache = tmp_path / "cache"
    first = run_fresh(cache)
    warmed = _cache_files(cache)
    # what the service and the tools run after `warmup` compiles nothing more: a live stream
    # (decoder, tracker), several targets, no background capture (the static-scene stand-in)
    frames, _ = write_spiel_csv(subset, tmp_path / "csv", indices=range(2))
    _cli(cache, "run", "--port", "sim://", "--frames", "3", "--rate", "0")
    _cli(cache, "run", "--port", "sim://", "--frames", "3", "--rate", "0", "--max-targets", "4")
    _cli(cache, "replay", frames, "--max-targets", "4", "--track")
    _cli(cache, "replay", frames)
    assert _cache_files(cache) == warmed
    assert first["kernels"] >= 6 and first["compiled"]
    second = run_fresh(cache)
    assert second["compiled"] == []
    assert len(second["cache_hits"]) == second["kernels"] >= 10
    assert first["kernels"] >= second["kernels"]  # cold: helpers compiled as callees count too
    assert any(cache.rglob("*.nbi"))
