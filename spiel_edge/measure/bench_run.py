"""The whole ``run`` path per record, and the first-start figures (``spiel-edge bench``).

``run_path_cpu``: the virtual board serves a pseudo-terminal from a process of its own
(``spiel-edge simulate --pty``, so its cost is not counted); ``spiel-edge run --port <pty>``
runs twice, for ``small`` and ``big`` records, 4 x 64 with up to 4 targets, tracking and NDJSON
to a file. CPU seconds of each run (user + system, from the kernel's accounting of the child)
differ by the records in between: (cpu(big) - cpu(small)) / (big - small) is the CPU per record
of the steady state, start-up and shut-down cancelled. Latency: the run's own summary (from an
acquisition's last byte read to its record written).

``first_start``: seconds from ``spiel-edge run --port sim:// --frames 50`` starting to its first
line of output (stderr or stdout) and to its first record, in a fresh process with the given
cache folder; and ``warmup``'s seconds and peak resident memory (itself and its children).
"""

from __future__ import annotations

import os
import re
import select
import subprocess
import sys
import tempfile
import time

CLI = [
    sys.executable,
    "-c",
    "import sys; from spiel_edge.cli import main; sys.exit(main(sys.argv[1:]))",
]
RUN_ARGS = ("--max-targets", "4", "--track", "--no-status")


def _serve_pty(timeout_s: float = 60.0) -> tuple[subprocess.Popen, str]:
    server = subprocess.Popen(
        [*CLI, "simulate", "--pty"], stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True
    )
    ready, _, _ = select.select([server.stdout], [], [], timeout_s)
    if not ready:
        server.kill()
        raise RuntimeError("spiel-edge simulate --pty announced no pty")
    return server, server.stdout.readline().strip()


def _cpu_s(pid: int) -> float:
    """User + system CPU seconds of a running process (/proc/PID/stat)."""
    with open(f"/proc/{pid}/stat") as fh:
        fields = fh.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _wakeups(pid: int) -> int:
    """Voluntary context switches of a running process, all its threads (its waits that
    ended; what ``wait4`` reports at its end)."""
    total = 0
    for task in os.listdir(f"/proc/{pid}/task"):
        try:
            with open(f"/proc/{pid}/task/{task}/status") as fh:
                total += sum(
                    int(line.split()[1]) for line in fh if line.startswith("voluntary_ctxt")
                )
        except OSError:  # a thread that ended meanwhile
            continue
    return total


def run_path_cpu(records: int = 2000, rate: float = 0.0) -> dict:
    """CPU microseconds per record of ``spiel-edge run`` over a pty (4 x 64, 4 targets,
    tracking, NDJSON on stdout read here), the virtual board in another process: the run's
    CPU from its first record to its exit (kernel accounting), over the records after the
    first; start-up is left out. Its own summary line gives the latency. ``wakeups_per_record``:
    the process's voluntary context switches over the same span (each wait for the board that
    ended), per record: 1 is one wake-up per acquisition."""
    server, port = _serve_pty()
    try:
        args = ["run", "--port", port, "--frames", str(records), "--rate", str(rate), *RUN_ARGS]
        with tempfile.TemporaryFile() as err:
            t0 = time.perf_counter()
            proc = subprocess.Popen([*CLI, *args], stdout=subprocess.PIPE, stderr=err)
            first_line = proc.stdout.readline()
            at_first = _cpu_s(proc.pid) if first_line else None
            waits_at_first = _wakeups(proc.pid) if first_line else 0
            first_s = time.perf_counter() - t0
            lines = 1 + sum(1 for _ in proc.stdout)
            _, status, usage = os.wait4(proc.pid, 0)
            proc.returncode = os.waitstatus_to_exitcode(status)
            err.seek(0)
            text = err.read().decode(errors="replace")
    finally:
        server.terminate()
        try:
            server.wait(5)
        except subprocess.TimeoutExpired:
            server.kill()
    if proc.returncode not in (0, 3) or at_first is None:
        raise RuntimeError(
            f"spiel-edge {' '.join(args)} exited with {proc.returncode}: {text[-300:]}"
        )
    total = usage.ru_utime + usage.ru_stime
    latency = re.search(r"latency median ([\d.]+) ms, p95 ([\d.]+) ms", text)
    return {
        "records": lines,
        "rate_hz": rate,
        "cpu_us_per_record": round((total - at_first) / max(lines - 1, 1) * 1e6, 1),
        "wakeups_per_record": round((usage.ru_nvcsw - waits_at_first) / max(lines - 1, 1), 2),
        "startup_cpu_s": round(at_first, 2),
        "first_record_s": round(first_s, 2),
        "latency_ms": (
            {"median": float(latency.group(1)), "p95": float(latency.group(2))} if latency else None
        ),
    }


def first_start(env: dict | None = None, frames: int = 50, timeout_s: float = 900.0) -> dict:
    """Seconds to the first line of output and to the first record of ``spiel-edge run
    --port sim:// --frames N --rate 0`` in a fresh process (``env``: e.g. an empty
    NUMBA_CACHE_DIR), and whether it compiled anything (its stderr says so)."""
    t0 = time.perf_counter()
    proc = subprocess.Popen(
        [*CLI, "run", "--port", "sim://", "--frames", str(frames), "--rate", "0", "--no-status"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        env=env,
    )
    first_line = first_record = None
    err = b""
    streams = [proc.stdout, proc.stderr]
    deadline = t0 + timeout_s
    while streams and time.perf_counter() < deadline:
        ready, _, _ = select.select(streams, [], [], 1.0)
        for stream in ready:
            chunk = os.read(stream.fileno(), 65536)
            if not chunk:
                streams.remove(stream)
                continue
            now = time.perf_counter() - t0
            first_line = first_line if first_line is not None else now
            if stream is proc.stdout and first_record is None:
                first_record = now
            if stream is proc.stderr:
                err += chunk
    if streams:
        proc.kill()
    proc.wait()
    text = err.decode(errors="replace")
    return {
        "first_output_s": round(first_line, 2) if first_line is not None else None,
        "first_record_s": round(first_record, 2) if first_record is not None else None,
        "compiled": "compiling" in text,
        "exit": proc.returncode,
    }


def first_line_cold(args: tuple[str, ...] = ("run", "--port", "sim://", "--frames", "50")) -> dict:
    """Seconds from starting ``spiel-edge ARGS`` on an empty cache to its first line of
    output; then the command and its children are stopped (no full compile: cheap)."""
    import signal

    with tempfile.TemporaryDirectory() as cache:
        env = {**os.environ, "NUMBA_CACHE_DIR": cache, "SPIEL_EDGE_HOST_KERNELS": "1"}
        t0 = time.perf_counter()
        proc = subprocess.Popen(
            [*CLI, *args],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            env=env,
            start_new_session=True,  # its warm-up children stop with it
        )
        try:
            ready, _, _ = select.select([proc.stdout, proc.stderr], [], [], 120.0)
            seconds = time.perf_counter() - t0 if ready else None
            line = ready[0].readline().decode(errors="replace").strip() if ready else ""
        finally:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    return {"first_output_s": None if seconds is None else round(seconds, 2), "line": line[:160]}


def warmup_figures(env: dict | None = None, timeout_s: float = 1800.0) -> dict:
    """``spiel-edge warmup --json`` in a fresh process: seconds, kernels compiled, peak RSS of
    it and its children (the warm-up's own report), seconds to its first line of output."""
    import json

    t0 = time.perf_counter()
    proc = subprocess.Popen(
        [*CLI, "warmup", "--json"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=env
    )
    ready, _, _ = select.select([proc.stderr], [], [], timeout_s)
    first = time.perf_counter() - t0 if ready else None
    out, _err = proc.communicate(timeout=timeout_s)
    report = json.loads(out.decode().strip().splitlines()[-1])
    return {
        "first_output_s": round(first, 2) if first is not None else None,
        "seconds": report["seconds"],
        "compiled": len(report["compiled"]),
        "kernels": report["kernels"],
        "peak_rss_mib": report.get("peak_rss_mib"),
    }


def cold_figures() -> dict:
    """First-start figures: the first line of a cold ``run`` and ``warmup`` (stopped after
    it), a whole cold ``warmup`` on an empty cache (compiles every kernel: minutes; its peak
    RSS), then ``run`` from that cache."""
    out = {
        "cold_run_first_line": first_line_cold(),
        "cold_warmup_first_line": first_line_cold(("warmup",)),
    }
    with tempfile.TemporaryDirectory() as cache:
        env = {**os.environ, "NUMBA_CACHE_DIR": cache}
        out["cold_warmup"] = warmup_figures(env)
        out["warm_run"] = first_start(env)
    return out


def first_record_cold(frames: int = 5, timeout_s: float = 120.0) -> dict:
    """``spiel-edge run --port sim:// --frames N`` on an empty cache: seconds to its first
    record and to its end, and its records' tiers (a tiered start runs the interpreted
    kernels while a background process compiles; it is stopped at the end: cheap)."""
    import json

    with tempfile.TemporaryDirectory() as cache:
        env = {
            **os.environ,
            "NUMBA_CACHE_DIR": cache,
            "SPIEL_EDGE_HOST_KERNELS": "1",
            "SPIEL_EDGE_COMPILE_AFTER_EXIT": "0",
        }
        t0 = time.perf_counter()
        proc = subprocess.Popen(
            [*CLI, "run", "--port", "sim://", "--frames", str(frames), "--no-status"],
            stdout=subprocess.PIPE,
            stderr=subprocess.DEVNULL,
            env=env,
            text=True,
        )
        first, tiers = None, {}
        try:
            for line in proc.stdout:
                if not line.startswith("{"):
                    continue
                first = first if first is not None else time.perf_counter() - t0
                tier = json.loads(line).get("tier", "compiled")
                tiers[tier] = tiers.get(tier, 0) + 1
            proc.wait(timeout=timeout_s)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
    return {
        "first_record_s": None if first is None else round(first, 2),
        "end_s": round(time.perf_counter() - t0, 2),
        "records_by_tier": tiers,
        "exit": proc.returncode,
    }


def interpreted_tier(passes: int = 2, acquisitions: int = 16) -> dict:
    """Microseconds per acquisition of the fused pipeline and tracker on the interpreted
    kernels (a tiered start's first tier) and on the compiled ones, on the vendored
    acquisitions (one target, with their backgrounds)."""
    import numpy as np

    from spiel_edge import _tiers
    from spiel_edge.data import load_subset
    from spiel_edge.pipeline.factory import build_pipeline
    from spiel_edge.profile.schema import load_profile
    from spiel_edge.runtime.track_records import ResultTracker
    from spiel_edge.runtime.warmup import pipeline_kernels

    pipeline_kernels()
    subset = load_subset()
    pairs = [
        (f.astype(np.float64), b.astype(np.float64))
        for f, b in zip(
            subset.frames[:acquisitions], subset.backgrounds[:acquisitions], strict=True
        )
    ]

    def per_acquisition() -> list[float]:
        pipeline = build_pipeline(load_profile(), None)
        tracker = ResultTracker(load_profile().track)
        times = []
        for p in range(passes):
            for i, (frames, background) in enumerate(pairs):
                t = time.perf_counter()
                tracker.update(pipeline.process(frames, background), 0.02 * (p * len(pairs) + i))
                times.append((time.perf_counter() - t) * 1e6)
        return times

    compiled = per_acquisition()
    interpreted = _tiers.Interpreted()
    interpreted.enter()
    try:
        slow = per_acquisition()
    finally:
        interpreted.leave()
    return {
        "interpreted_median_us": round(float(np.median(slow)), 1),
        "interpreted_p95_us": round(float(np.percentile(slow, 95)), 1),
        "compiled_median_us": round(float(np.median(compiled)), 1),
        "acquisitions": len(slow),
    }
