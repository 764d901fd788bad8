"""A tiered start (issue 39): the interpreted kernels give the compiled ones' records, the
switch between two acquisitions keeps the run's state, the background compile stops on a
signal with one line and leaves no cache entry that loads half-written.

The switch is exercised without a cold compile: ``SPIEL_EDGE_TIERED=force`` starts on the
interpreted tier although every kernel is cached (the background process then only loads),
and the stop tests compile a few one-line kernels."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time
from importlib import resources
from pathlib import Path

import numpy as np
import pytest

from spiel_edge import _jit, _tiers

SUBSET = str(resources.files("spiel_edge") / "data" / "spiel_icra23_subset.npz")


def _records(pipeline_factory, pairs, tracker_factory):
    from spiel_edge.runtime.track_records import track_records

    pipeline, tracker, out = pipeline_factory(), tracker_factory(), []
    for i, (frames, background) in enumerate(pairs):
        result = pipeline.process(frames, background)
        record = result.record()
        record["tracks"] = track_records(tracker.update(result, 0.02 * i, True))
        out.append(json.dumps(record))
    return out


@pytest.mark.parametrize("targets", [1, 4])
def test_interpreted_kernels_give_the_compiled_records(targets):
    from spiel_edge.data import load_subset
    from spiel_edge.pipeline.factory import build_pipeline
    from spiel_edge.profile.schema import load_profile
    from spiel_edge.runtime.track_records import ResultTracker
    from spiel_edge.runtime.warmup import pipeline_kernels

    pipeline_kernels()
    subset = load_subset()
    pairs = [
        (f.astype(float), b.astype(float))
        for f, b in zip(subset.frames[:16], subset.backgrounds[:16], strict=True)
    ]

    def pipeline():
        p = build_pipeline(load_profile(), None)
        p.set_max_targets(targets)
        return p

    def tracker():
        return ResultTracker(load_profile().track)

    compiled = _records(pipeline, pairs, tracker)
    interpreted = _tiers.Interpreted()
    interpreted.enter()
    try:
        twins = _records(pipeline, pairs, tracker)
    finally:
        interpreted.leave()
    assert twins == compiled
    called = {_tiers.qualified_name(k) for k, _types in interpreted.calls}
    kernel = (
        "one_target._acquisition_kernel"
        if targets == 1
        else "several_targets._scene_acquisition_kernel"
    )
    assert any(name.endswith(kernel) for name in called)  # the plan: what really ran
    # and the dispatchers are back where the code finds them
    from spiel_edge.pipeline.compiled import one_target

    assert hasattr(one_target._acquisition_kernel, "signatures")


def test_twins_call_twins_and_the_dispatchers_come_back(tmp_path, monkeypatch):
    (tmp_path / "tiny_pair.py").write_text(
        "from spiel_edge._jit import jit\n\n"
        "@jit\ndef inner(x):\n    return x + 1\n\n"
        "@jit\ndef outer(x):\n    return inner(x) * 2\n\n"
        "def wrapper(x):\n    return outer(x)\n"
    )
    monkeypatch.syspath_prepend(str(tmp_path))
    import tiny_pair

    kernels = [tiny_pair.inner, tiny_pair.outer]
    interpreted = _tiers.Interpreted(kernels)
    twin_outer = interpreted.twins[id(tiny_pair.outer)]
    assert twin_outer.__globals__["inner"] is interpreted.twins[id(tiny_pair.inner)]
    assert [_tiers.qualified_name(k) for k in _tiers.reach([tiny_pair.outer], kernels)] == [
        "tiny_pair.outer",
        "tiny_pair.inner",
    ]
    interpreted.enter(pure_cobs=False)
    try:
        assert tiny_pair.wrapper(np.int64(3)) == 8
        assert not tiny_pair.outer.dispatcher.signatures  # nothing compiled: interpreted
        ((kernel, types),) = interpreted.calls
        assert kernel is kernels[1] and str(types) == "(int64,)"
    finally:
        interpreted.leave()
    assert tiny_pair.outer is kernels[1] and tiny_pair.inner is kernels[0]


def _record_key(record: dict) -> dict:
    """What replay computes again: everything but the live stream's own fields."""
    live = {"seq", "host_time", "source", "stamp_host", "stamp_uncertainty_us", "tier", "truth_mm"}
    live |= {"stamp_source"}  # how the live stamp was made (board clock or arrival)
    live |= {"truth_targets_mm", "acquisition", "device_time_us"}
    return {k: v for k, v in record.items() if k not in live}


def _cli(*args, env=None, **kwargs):
    return subprocess.run(
        [sys.executable, "-m", "spiel_edge.cli", *args],
        env={**os.environ, **(env or {})},
        capture_output=True,
        text=True,
        timeout=300,
        **kwargs,
    )


def test_a_run_that_switches_tiers_records_what_replay_computes(tmp_path):
    mcap = tmp_path / "run.mcap"
    env = {"SPIEL_EDGE_TIERED": "force", "SPIEL_EDGE_COMPILE_AFTER_EXIT": "0"}
    run = _cli(
        "run",
        "--port",
        "sim://",
        "--frames",
        "150",
        "--rate",
        "30",
        "--no-track",
        "--record",
        str(mcap),
        env=env,
    )
    assert run.returncode == 0, run.stderr
    live = [json.loads(line) for line in run.stdout.splitlines()]
    tiers = [r.get("tier", "compiled") for r in live]
    assert tiers[0] == "interpreted" and tiers[-1] == "compiled", run.stderr
    assert tiers == sorted(tiers, key=lambda t: t == "compiled")  # one switch, never back
    assert "compiled kernels in use after" in run.stderr
    index = [r["acquisition"] for r in live]
    gaps = sum(b - a - 1 for a, b in zip(index, index[1:], strict=False))
    skipped = re.search(r"(\d+) skipped", run.stderr)
    assert gaps == (int(skipped.group(1)) if skipped else 0)  # every gap counted as skipped
    replay = _cli("replay", str(mcap), env={"SPIEL_EDGE_TIERED": "0"})
    assert replay.returncode == 0, replay.stderr
    replayed = [json.loads(line) for line in replay.stdout.splitlines()]
    assert len(replayed) == len(live)
    assert [_record_key(r) for r in replayed] == [_record_key(r) for r in live]


COLD = os.environ.get("SPIEL_TEST_COLD_SWITCH", "")


@pytest.mark.skipif(
    not COLD,
    reason="a real cold compile, 0.5-3 min on 2 cores: SPIEL_TEST_COLD_SWITCH=1 (ch101-one, "
    "19 kernels) or =spiel-icra23 (56 kernels)",
)
def test_a_run_switches_after_a_real_cold_compile_and_records_what_replay_computes(tmp_path):
    """From an empty kernel cache, as a checkout starts: interpreted at once, the background
    process really compiles, the run switches once without losing the board, every
    acquisition not processed is counted, and the records equal replay's of the recording."""
    profile = "spiel-icra23" if COLD == "spiel-icra23" else "ch101-one"
    targets = "40,20,180" if profile == "spiel-icra23" else "0,0,300"
    cache = tmp_path / "cache"
    cache.mkdir()
    env = {**os.environ, "NUMBA_CACHE_DIR": str(cache), "SPIEL_EDGE_COMPILE_AFTER_EXIT": "0"}
    env.pop("SPIEL_EDGE_TIERED", None)
    mcap, out = tmp_path / "run.mcap", tmp_path / "live.ndjson"
    port = f"sim://?scene=model&profile={profile}&targets={targets}&noise=5"
    args = ["run", "--port", port, "--profile", profile, "--rate", "20", "--no-track"]
    proc = subprocess.Popen(
        [sys.executable, "-m", "spiel_edge.cli", *args, "--record", str(mcap), "-o", str(out)],
        env=env,
        stderr=subprocess.PIPE,
        text=True,
    )
    said, deadline = [], time.monotonic() + 900
    try:
        for line in proc.stderr:
            said.append(line)
            if "compiled kernels in use after" in line or time.monotonic() > deadline:
                break
        time.sleep(3.0)  # 60 acquisitions on the compiled tier
        proc.send_signal(signal.SIGINT)
        said += proc.stderr.readlines()
        assert proc.wait(30) == 0, "".join(said)
    finally:
        if proc.poll() is None:
            proc.kill()
    text = "".join(said)
    assert "has no compiled copy" in text and "compiled kernels in use after" in text, text
    assert len(list(cache.rglob("*.nbi"))) >= 10  # it did compile, into the empty cache
    live = [json.loads(line) for line in out.read_text().splitlines()]
    tiers = [r.get("tier", "compiled") for r in live]
    assert tiers[0] == "interpreted" and tiers[-1] == "compiled"
    assert tiers == sorted(tiers, key=lambda t: t == "compiled")  # one switch, never back
    index = [r["acquisition"] for r in live]
    gaps = sum(b - a - 1 for a, b in zip(index, index[1:], strict=False))
    skipped = re.search(r"(\d+) skipped", text)
    assert gaps == (int(skipped.group(1)) if skipped else 0), text  # every gap counted
    switch = next(line for line in said if "compiled kernels in use after" in line)
    print(f"cold switch ({profile}): {switch.strip()}; {text.strip().splitlines()[-1]}")
    replay = _cli("replay", str(mcap), "--profile", profile, env={"NUMBA_CACHE_DIR": str(cache)})
    assert replay.returncode == 0, replay.stderr
    replayed = [json.loads(line) for line in replay.stdout.splitlines()]
    assert [_record_key(r) for r in replayed] == [_record_key(r) for r in live]


def _processes_with(marker: str) -> list[int]:
    found = []
    for proc in Path("/proc").iterdir():
        if not proc.name.isdigit():
            continue
        try:
            if marker.encode() in (proc / "environ").read_bytes():
                found.append(int(proc.name))
        except OSError:
            continue
    return found


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM, signal.SIGHUP])
def test_a_signal_during_the_compile_stops_it_with_one_line(tmp_path, signum):
    marker = f"SPIEL_EDGE_TEST_MARK={tmp_path.name}"
    env = {
        **os.environ,
        "SPIEL_EDGE_TIERED": "force",
        "SPIEL_EDGE_TEST_MARK": tmp_path.name,
    }
    proc = subprocess.Popen(
        [sys.executable, "-m", "spiel_edge.cli", "run", "--port", "sim://", "--no-track"],
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    proc.stdout.readline()  # the first record: interpreted, the compile under way
    assert len(_processes_with(marker)) >= 2  # the command and its compile
    proc.send_signal(signum)
    out, err = proc.communicate(timeout=60)
    assert proc.returncode == 0, err
    assert "Traceback" not in err and "ended with status" not in err
    stopped = [line for line in err.splitlines() if line.startswith("spiel-edge: compile stopped")]
    switched = [line for line in err.splitlines() if "compiled kernels in use" in line]
    assert len(stopped) == 1 or switched, err  # (under load it may have finished first)
    for _ in range(50):
        if not _processes_with(marker):
            break
        time.sleep(0.1)
    assert _processes_with(marker) == []


TINY = "from spiel_edge._jit import jit\n" + "".join(
    f"\n@jit\ndef k{i}(x):\n    s = 0.0\n    for j in range({i + 2}):\n"
    f"        s += (x + j) ** {i + 1} / (1.0 + j)\n    return s\n"
    for i in range(8)
)

LOAD_ALL = """
import json
from spiel_edge import _kernel_cache
warnings = []
_kernel_cache.listeners.append(lambda e, n, d: warnings.append(str(d)) if e == "warning" else None)
import tiny_plan
loaded = missing = 0
with _kernel_cache.no_compile():
    for i in range(8):
        try:
            getattr(tiny_plan, f"k{i}")(1.5)
            loaded += 1
        except _kernel_cache.CompileNeeded:
            missing += 1
print(json.dumps({"loaded": loaded, "missing": missing, "warnings": warnings}))
"""


def test_a_compile_cut_by_sigterm_leaves_nothing_that_loads_half_written(tmp_path):
    from numba.core import types

    from spiel_edge.runtime.tier_compile import write_plan

    (tmp_path / "tiny_plan.py").write_text(TINY)
    plan = tmp_path / "plan.pickle"
    write_plan(plan, [("tiny_plan", f"k{i}", (types.float64,)) for i in range(8)])
    env = {
        **os.environ,
        "PYTHONPATH": os.pathsep.join([str(tmp_path), *sys.path]),
        "NUMBA_CACHE_DIR": str(tmp_path / "cache"),
        "SPIEL_EDGE_TEST_MARK": tmp_path.name,
    }
    proc = subprocess.Popen(
        [sys.executable, "-m", "spiel_edge.runtime.tier_compile", str(plan)],
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        text=True,
        start_new_session=True,
    )
    compiled = 0
    for line in proc.stdout:
        message = json.loads(line)
        compiled += message.get("event") == "compiled"
        if compiled == 2:
            os.killpg(proc.pid, signal.SIGTERM)  # as the command stops it
            break
    assert proc.wait(timeout=60) != 0
    for _ in range(50):
        if not _processes_with(f"SPIEL_EDGE_TEST_MARK={tmp_path.name}"):
            break
        time.sleep(0.1)
    assert _processes_with(f"SPIEL_EDGE_TEST_MARK={tmp_path.name}") == []
    out = subprocess.run(
        [sys.executable, "-c", LOAD_ALL], env=env, capture_output=True, text=True, timeout=300
    )
    assert out.returncode == 0, out.stderr
    result = json.loads(out.stdout.strip().splitlines()[-1])
    assert result["warnings"] == []  # no damaged file met
    assert result["loaded"] >= 2 and result["loaded"] + result["missing"] == 8
    # every file in the cache is whole: sealed, or numba's own temporary never read
    from spiel_edge._kernel_layers import SEAL_TAG

    for path in (tmp_path / "cache").rglob("tiny_plan.*.nb*"):
        data = path.read_bytes()
        assert data[-(len(SEAL_TAG) + 32) : -32] == SEAL_TAG, path


def test_the_jit_registry_holds_every_kernel():
    from spiel_edge.runtime.warmup import pipeline_kernels

    found = pipeline_kernels()
    registered = {id(k) for k in _tiers.KERNELS}
    assert all(id(k) in registered for k in found.values())
    assert _jit.GATED


def test_bench_reports_the_first_record_from_an_empty_cache_and_the_interpreted_tier():
    from spiel_edge.measure.bench_run import first_record_cold, interpreted_tier

    cold = first_record_cold(frames=2)
    assert cold["exit"] == 0 and cold["records_by_tier"] == {"interpreted": 2}
    assert 0 < cold["first_record_s"] <= cold["end_s"]
    tier = interpreted_tier(passes=1, acquisitions=3)
    assert tier["acquisitions"] == 3
    assert tier["interpreted_median_us"] > tier["compiled_median_us"] > 0


def test_replay_starts_tiered_and_gives_the_same_records(tmp_path):
    mcap = tmp_path / "run.mcap"
    run = _cli(
        "run",
        "--port",
        "sim://",
        "--frames",
        "60",
        "--rate",
        "0",
        "--no-track",
        "--record",
        str(mcap),
    )
    assert run.returncode == 0, run.stderr
    env = {"SPIEL_EDGE_TIERED": "force", "SPIEL_EDGE_COMPILE_AFTER_EXIT": "0"}
    tiered = _cli("replay", str(mcap), env=env)
    assert tiered.returncode == 0, tiered.stderr
    assert "starting on the interpreted kernels" in tiered.stderr
    plain = _cli("replay", str(mcap), env={"SPIEL_EDGE_TIERED": "0"})
    assert plain.returncode == 0, plain.stderr
    assert tiered.stdout == plain.stdout and len(plain.stdout.splitlines()) == 60


def test_progress_counts_each_kernel_once_and_says_which_tier_runs():
    import io

    from spiel_edge.runtime.tiered import TieredStart

    out = io.StringIO()
    tiers = TieredStart(stream=out)
    tiers.tier = "interpreted"
    tiers.planned = {f"m.k{i}" for i in range(4)}
    tiers.total, tiers.estimate_s = 4, 40.0
    for name in ("m.k0", "m.k0", "m.k1", "m.k2", "m.k2", "m.k3"):  # second signatures
        tiers._on_event("compile", name, "(sig)")
        tiers._on_event("compiled", name, 5.0)
    lines = out.getvalue().splitlines()
    assert [line.split(" kernels")[0].split()[-1] for line in lines] == ["1/4", "2/4", "3/4", "4/4"]
    assert tiers.progress()["compiled"] == 4 and tiers.progress()["estimate_left_s"] == 10
    tiers._on_event("compiled", "m.unplanned", 1.0)  # more than planned: counted honestly
    assert tiers.progress()["to_compile"] == 5 and tiers.progress()["compiled"] == 5
    assert tiers.status_text() == "kernels interpreted, loading the compiled ones"
    tiers.total += 1  # one more to go
    assert tiers.status_text() == "kernels interpreted, compiling 5/6 (~9 s left)"
    tiers.stopped = True
    assert tiers.status_text() == "kernels interpreted (compile stopped at 5/6)"


def test_status_line_summary_and_diagnostics_say_the_tier():
    import io

    from spiel_edge.runtime.loop import LiveRunner
    from spiel_edge.runtime.tiered import TieredStart

    class Session:
        url = "sim://"
        hello = None

        def counts(self):
            return {"lost": 0, "damaged": 0, "overruns": 0, "reconnects": 0, "disconnects": 0}

    class Sink:
        def set_status_provider(self, provider):
            self.provider = provider

    sink = Sink()
    runner = LiveRunner(Session(), pipeline=None, sink=sink)
    tiers = TieredStart(stream=io.StringIO())
    tiers.tier, tiers.planned, tiers.total, tiers.estimate_s = "interpreted", {"m.k"}, 1, 30.0
    runner.tiers = tiers
    runner.stats.skipped = 7
    values = sink.provider()["values"]
    assert values["kernels"] == "kernels interpreted, compiling 0/1 (~30 s left)"
    assert values["skipped"] == 7
    assert "skipped 7  kernels interpreted, compiling 0/1" in runner.status_line()
    tiers.tier = "compiled"
    tiers.rounds = 1
    assert runner.status_line().endswith("kernels compiled")
    assert "7 skipped (interpreted kernels behind the board); kernels compiled" in runner.summary()


def test_a_command_without_its_own_loop_switches_at_a_kernel_call(monkeypatch):
    """evaluate and calibrate (runtime.tiered.tiered_work): interpreted at once, the compiled
    kernels from the first kernel call after they are loaded, the same results throughout."""
    from spiel_edge.pipeline.factory import build_pipeline
    from spiel_edge.profile.schema import resolve_profile
    from spiel_edge.recordings.labelled import load_labelled
    from spiel_edge.runtime import tiered

    monkeypatch.setenv("SPIEL_EDGE_TIERED", "force")
    monkeypatch.setenv("SPIEL_EDGE_COMPILE_AFTER_EXIT", "0")
    monkeypatch.setattr(tiered, "POLL_S", 0.0)
    monkeypatch.setattr(tiered.TieredStart, "_load", lambda self: None)  # loaded: when we say
    profile = resolve_profile("spiel-icra23")
    recs = list(load_labelled(SUBSET).recordings())[:24]
    plain = build_pipeline(profile)
    expected = [json.dumps(plain.process(r.frames, r.background).record()) for r in recs]
    got = []
    with tiered.tiered_work(profile, what="evaluate") as tiers:
        assert tiers is not None and tiers.is_interpreted
        pipeline = build_pipeline(profile)
        for r in recs[:12]:
            got.append(json.dumps(pipeline.process(r.frames, r.background).record()))
        assert tiers.is_interpreted and tiers.interpreted.active  # the twins ran them
        tiers._ready.set()  # the compiled kernels are loaded (the cache is warm)
        for r in recs[12:]:
            got.append(json.dumps(pipeline.process(r.frames, r.background).record()))
        assert tiers.tier == "compiled" and not tiers.interpreted.active
    assert got == expected
    fused = vars(sys.modules["spiel_edge.pipeline.compiled.fused"]).values()
    assert not any(hasattr(v, "dispatcher") for v in fused)  # the dispatchers are back


def test_evaluate_starts_tiered_and_gives_the_same_summary():
    path = SUBSET
    env = {"SPIEL_EDGE_TIERED": "force", "SPIEL_EDGE_COMPILE_AFTER_EXIT": "0"}
    tiered = _cli("evaluate", path, "--json", env=env)
    assert tiered.returncode == 0, tiered.stderr
    assert "starting on the interpreted kernels" in tiered.stderr
    plain = _cli("evaluate", path, "--json", env={"SPIEL_EDGE_TIERED": "0"})
    assert plain.returncode == 0, plain.stderr
    assert "interpreted" not in plain.stderr
    assert json.loads(tiered.stdout) == json.loads(plain.stdout)


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM])
def test_a_signal_during_evaluate_stops_its_compile_with_one_line(tmp_path, signum):
    marker = f"SPIEL_EDGE_TEST_MARK={tmp_path.name}"
    env = {**os.environ, "SPIEL_EDGE_TIERED": "force", "SPIEL_EDGE_TEST_MARK": tmp_path.name}
    proc = subprocess.Popen(
        [sys.executable, "-m", "spiel_edge.cli", "evaluate", SUBSET, "--json"],
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    seen = ""
    while "starting on the interpreted kernels" not in seen:
        line = proc.stderr.readline()
        assert line, "evaluate ended before its tiered start"
        seen += line
    time.sleep(0.3)  # the compile launched, the evaluation under way on the twins
    proc.send_signal(signum)
    out, err = proc.communicate(timeout=60)
    err = seen + err
    assert "Traceback" not in err
    stopped = [line for line in err.splitlines() if line.startswith("spiel-edge: compile stopped")]
    assert len(stopped) <= 1, err
    if proc.returncode != 0:  # stopped by the signal (not finished before it came)
        assert stopped or "compiled kernels in use" in err, err
    for _ in range(50):
        if not _processes_with(marker):
            break
        time.sleep(0.1)
    assert _processes_with(marker) == []  # no compile left running after a signal


def _board_records(tmp_path, robot, n: int = 60) -> list[str]:
    """--replay arguments: each board's records as `run -o` writes them, a post 600 mm ahead
    that the front board sees while the robot drives along x."""
    args = []
    for j, b in enumerate(robot.boards):
        lines = []
        for k in range(n):
            t = 1000.0 + k * 0.025 + j * 0.005
            p_base = np.array([600.0 - 200.0 * (t - 1000.0), 0.0, 0.0])
            targets = []
            if b.name == "front":
                cov = (np.eye(3) * 16).tolist()
                targets = [{"position_mm": list(b.mount.to_board(p_base)), "covariance_mm2": cov}]
            record = {"acquisition": k, "device_time_us": int((5.0 + t - 1000) * 1e6)}
            lines.append(json.dumps({**record, "host_time": t, "targets": targets}))
        path = tmp_path / f"{b.name}.ndjson"
        path.write_text("\n".join(lines) + "\n")
        args += ["--replay", f"{b.name}={path}"]
    return args


def test_fuse_starts_tiered_on_the_tracker_alone_and_fuses_the_same(tmp_path):
    from spiel_edge.robot.description import load_robot

    replay = _board_records(tmp_path, load_robot("virtual-4"))
    env = {"SPIEL_EDGE_TIERED": "force", "SPIEL_EDGE_COMPILE_AFTER_EXIT": "0"}
    tiered = _cli("fuse", "--robot", "virtual-4", *replay, env=env)
    assert tiered.returncode == 0, tiered.stderr
    assert "starting on the interpreted kernels" in tiered.stderr
    counted = re.search(r"compiles the (\d+) kernels|loads the compiled kernels", tiered.stderr)
    assert counted, tiered.stderr
    if counted.group(1):  # the tracker's tree only, not run's pipeline (90 kernels)
        assert int(counted.group(1)) <= 25, tiered.stderr
    plain = _cli("fuse", "--robot", "virtual-4", *replay, env={"SPIEL_EDGE_TIERED": "0"})
    assert plain.returncode == 0, plain.stderr
    assert "interpreted" not in plain.stderr
    fused = [json.loads(line) for line in tiered.stdout.splitlines()]
    assert len(fused) == 60 and any(r["tracks"] for r in fused)
    assert tiered.stdout == plain.stdout


PRIORITY = """
import json, os, subprocess, sys
from spiel_edge.runtime.tier_compile import lower_priority
said = lower_priority()
child = subprocess.run(
    [sys.executable, "-c", "import os; print(os.nice(0), os.sched_getscheduler(0))"],
    capture_output=True, text=True, check=True,
).stdout.split()
print(json.dumps({"said": said, "nice": os.nice(0), "policy": os.sched_getscheduler(0),
                  "child": [int(v) for v in child]}))
"""


def test_the_background_compile_and_its_workers_run_at_the_lowest_priority():
    out = subprocess.run(
        [sys.executable, "-c", PRIORITY], capture_output=True, text=True, timeout=60
    )
    assert out.returncode == 0, out.stderr
    got = json.loads(out.stdout.strip().splitlines()[-1])
    assert got["nice"] == 19 and got["child"][0] == 19  # the warm-up's children inherit it
    assert "nice 19" in got["said"]
    if hasattr(os, "SCHED_IDLE"):  # Linux: the idle class, for the worker too
        assert got["policy"] == os.SCHED_IDLE == got["child"][1]
        assert "SCHED_IDLE" in got["said"]


class _FixedBoard:
    """A session of fixed acquisitions: the vendored subset, 20 ms apart on the board's clock
    (two runs over it see the same inputs, unlike a live board's)."""

    url = "test://fixed"

    def __init__(self, n: int):
        from spiel_edge.data import load_subset
        from spiel_edge.device import LiveAcquisition

        subset = load_subset()
        self.items = [
            LiveAcquisition(
                index=i,
                timestamp_us=20_000 * i,
                sample_rate_hz=22_000,
                samples=subset.frames[i % len(subset.frames)].astype(np.uint16),
                received_ns=time.perf_counter_ns(),
                host_time=1.0e9 + 0.02 * i,
                background=subset.backgrounds[i % len(subset.frames)].astype(np.uint16),
            )
            for i in range(n)
        ]

    def acquisitions(self, stop):
        yield from self.items

    def counts(self) -> dict:
        return {"lost": 0, "damaged": 0, "overruns": 0, "reconnects": 0}

    def newest_only(self, behind_s: float) -> int:
        return 0  # nothing waits: every acquisition is handled


class _SwitchAfter:
    """A TieredStart's two calls the live loop makes: interpreted kernels for the first ``n``
    acquisitions, then the dispatchers back (as TieredStart switches once its compile ended)."""

    rounds = ()

    def __init__(self, n: int):
        self.interpreted = _tiers.Interpreted()
        self.interpreted.enter()
        self.tier, self.n = "interpreted", n

    @property
    def is_interpreted(self) -> bool:
        return self.tier == "interpreted"

    def between(self) -> bool:
        self.n -= 1
        if self.n > 0:
            return False
        self.interpreted.leave()
        self.tier = "compiled"
        return True

    def status_text(self) -> str:
        return self.tier


def test_the_tracker_keeps_its_tracks_across_the_switch():
    """The same tracker, pipeline and session on both tiers: a run that switches after 8
    acquisitions gives the tracks of a run that never did (ids, ages, velocities), and its
    tracks at the end are as old as the whole run."""
    from spiel_edge.outputs import Sink
    from spiel_edge.pipeline.factory import build_pipeline
    from spiel_edge.profile.schema import load_profile
    from spiel_edge.runtime.loop import LiveRunner
    from spiel_edge.runtime.track_records import ResultTracker
    from spiel_edge.runtime.warmup import pipeline_kernels

    pipeline_kernels()
    profile = load_profile()

    class Collect(Sink):
        def __init__(self):
            self.records = []

        def write(self, record):
            self.records.append(record)

    def live(tiers) -> list[dict]:
        pipeline = build_pipeline(profile, None)
        pipeline.set_max_targets(2)
        sink = Collect()
        runner = LiveRunner(_FixedBoard(24), pipeline, sink, tracker=ResultTracker(profile.track))
        runner.tiers = tiers
        try:
            runner.run(__import__("threading").Event())
        finally:
            if tiers is not None and tiers.is_interpreted:
                tiers.interpreted.leave()
        return sink.records

    switched = live(_SwitchAfter(8))
    assert [r.get("tier", "compiled") for r in switched] == ["interpreted"] * 8 + ["compiled"] * 16
    straight = live(None)
    assert [{**r, "tier": None} for r in switched] == [{**r, "tier": None} for r in straight]
    last = switched[-1]["tracks"]
    assert last and max(t["age"] for t in last) == 24  # one track from the first acquisition on
