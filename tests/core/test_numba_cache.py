import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

from spiel_edge.runtime import cold_start

SNIPPET = (
    "import json; from spiel_edge.runtime.warmup import warmup; "
    "print(json.dumps(warmup(isolate=False)))"  # in-process: the time it always took
)


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


def _prewarm(cache_dir: Path) -> int:
    """The kernels this test process already compiled (numba's cache beside the sources, or
    its NUMBA_CACHE_DIR) copied into ``cache_dir`` in NUMBA_CACHE_DIR's layout: the warm-up
    below compiles only what the suite has not (the whole compile again cost 100-130 s of
    the suite's 10 minutes); what it asserts about the cache after warm-up is unchanged."""
    own = os.environ.get("NUMBA_CACHE_DIR")
    if own:
        shutil.copytree(own, cache_dir, dirs_exist_ok=True)
        return sum(1 for _ in cache_dir.rglob("*.nbi"))
    copied = 0
    root = Path(cold_start.__file__).resolve().parents[2]
    for package in ("spiel_edge",):
        for pycache in (root / package).rglob("__pycache__"):
            files = [f for f in pycache.iterdir() if f.suffix in (".nbi", ".nbc", ".nbo")]
            if not files:
                continue
            dest = cache_dir / cold_start._numba_subpath(pycache.parent / "any.py")
            dest.mkdir(parents=True, exist_ok=True)
            for f in files:
                shutil.copy2(f, dest / f.name)
                copied += f.suffix == ".nbi"
    return copied


def _cache_files(cache_dir) -> dict:
    return {str(p): (p.stat().st_size, p.stat().st_mtime_ns) for p in cache_dir.rglob("*.nb[ic]")}


# A warm process: the vendored acquisitions through the CLI's pipeline (one target with its
# background, four without), then what it imported and whether any LLVM optimisation ran.
PROBE = """
import json, sys
from numba.core import codegen
runs = []
stock = codegen.CPUCodeLibrary._optimize_final_module
def counted(self):
    runs.append(self.name)
    return stock(self)
codegen.CPUCodeLibrary._optimize_final_module = counted
from spiel_edge.data import load_subset
from spiel_edge.pipeline.factory import build_pipeline
from spiel_edge.profile.schema import load_profile
subset = load_subset()
pipeline = build_pipeline(load_profile())
out = [pipeline.process(f, b).record() for f, b in zip(subset.frames[:6], subset.backgrounds[:6])]
pipeline.set_max_targets(4)
out += [pipeline.process(f).record() for f in subset.frames[:6]]
report = {"records": out, "optimised": list(runs), "registries": "numba.np.arraymath" in sys.modules}
# then a compilation in the same process (a new signature of a kernel whose callees come from
# the cache): it must link them as numba would, their bitcode parsed on demand
import numpy as np
from spiel_edge.pipeline.stages import detect, memg
y = subset.frames[0].astype(np.float32)
peaks, counts = detect.detect(subset.frames[0] - subset.backgrounds[0], threshold=100.0)
params = np.full((y.shape[0], peaks.shape[1], 4), np.nan)
memg.memg_kernel(y, peaks, counts, 3.0, 30, params, np.zeros(peaks.shape, dtype=np.int64))
report["compiled"] = np.nan_to_num(params, nan=-1.0).ravel().tolist()
print(json.dumps(report))
"""


def _probe(cache_dir, lean=True) -> dict:
    env = {**os.environ, "NUMBA_CACHE_DIR": str(cache_dir), "SPIEL_EDGE_NUMBA_LEAN": str(int(lean))}
    out = subprocess.run(
        [sys.executable, "-c", PROBE], env=env, capture_output=True, text=True, timeout=600
    )
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout.strip().splitlines()[-1])


def _cli(cache_dir, *args) -> None:
    env = {**os.environ, "NUMBA_CACHE_DIR": str(cache_dir)}
    cmd = [sys.executable, "-m", "spiel_edge.cli", *map(str, args), "-o", os.devnull]
    subprocess.run(cmd, env=env, capture_output=True, timeout=600, check=True)


def test_second_start_loads_every_kernel_from_the_cache(tmp_path, subset):
    from tests.core.spiel_csv_fixture import write_spiel_csv

    cache = tmp_path / "cache"
    _prewarm(cache)
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
    assert first["kernels"] >= 6
    second = run_fresh(cache)
    assert second["compiled"] == []
    assert len(second["cache_hits"]) == second["kernels"] >= 10
    assert first["kernels"] >= second["kernels"]  # cold: helpers compiled as callees count too
    assert any(cache.rglob("*.nbi"))
    _check_lean_start(cache)


def _check_lean_start(cache) -> None:
    """After warm-up a start runs no LLVM optimisation and imports no lowering registry
    (spiel_edge/_cache_load.py), with the records of numba's own loading, bit for bit; a
    damaged runtime file is compiled again and rewritten whole."""
    (runtime,) = cache.rglob("spiel_edge-nrt-*.nbo")
    lean, stock = _probe(cache), _probe(cache, lean=False)  # lean first: it compiles
    assert stock["optimised"] and stock["registries"]  # numba's own path, as a control
    assert lean["optimised"] == [] and not lean["registries"]
    assert lean["records"] == stock["records"]
    assert lean["compiled"] == stock["compiled"] and max(lean["compiled"]) > 0
    assert any(len(r["targets"]) > 1 for r in lean["records"])  # several targets ran too
    good = runtime.read_bytes()
    runtime.write_bytes(good[: len(good) // 2])
    damaged = _probe(cache)
    assert damaged["optimised"] == ["nrt"] and damaged["records"] == stock["records"]
    assert runtime.read_bytes() == good
