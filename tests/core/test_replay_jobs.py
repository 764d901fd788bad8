"""``replay``/``evaluate --jobs N``: the same records and figures as one job, errors and
signals handled, no worker left behind."""

from __future__ import annotations

import fcntl
import json
import os
import signal
import subprocess
import sys
import termios
import time
from pathlib import Path

import pytest

from spiel_edge.cli import main
from spiel_edge.runtime.parallel import Task, plan_tasks, resolve_jobs, run_task, usable_jobs
from tests.core.spiel_csv_fixture import write_spiel_csv

CLI = [sys.executable, "-m", "spiel_edge.cli"]
BROKEN = "99.0mm_99.0mm_100.0mm_9_1_frames.csv"  # labelled by its name, unreadable


@pytest.fixture(scope="module")
def folders(subset, tmp_path_factory):
    """80 vendored recordings (several runs of consecutive indices) and one unreadable file."""
    frames, bg = write_spiel_csv(subset, tmp_path_factory.mktemp("jobs"), range(80))
    (frames / BROKEN).write_text("1 2 x\n3 4 5\n")
    (bg / BROKEN).write_text("1 2 3\n")
    return frames, bg


def _replay(folders, out: Path, *extra: str) -> int:
    frames, bg = folders
    return main(["replay", str(frames), "--background", str(bg), "-o", str(out), *extra])


def test_replay_jobs_2_writes_the_same_bytes_as_one_job_errors_included(folders, tmp_path):
    one, two = tmp_path / "one.ndjson", tmp_path / "two.ndjson"
    assert _replay(folders, one) == 1  # the broken file: reported, the others processed
    assert _replay(folders, two, "--jobs", "2") == 1
    assert one.read_bytes() == two.read_bytes()
    lines = one.read_text().splitlines()
    assert len(lines) == 81 and sum('"error"' in line and BROKEN in line for line in lines) == 1


def test_tracked_replay_jobs_2_keeps_time_order_and_track_ids(folders, tmp_path):
    one, two = tmp_path / "one.ndjson", tmp_path / "two.ndjson"
    assert _replay(folders, one, "--track") == 1
    assert _replay(folders, two, "--track", "-j", "2") == 1
    assert one.read_bytes() == two.read_bytes()
    assert b'"track_id":3,' in one.read_bytes()  # ids issued in later tasks were shifted


def test_evaluate_jobs_2_gives_the_same_figures(folders, capsys):
    frames, bg = folders
    args = ["evaluate", str(frames), "--background", str(bg), "--json"]
    assert main(args) == 1
    one = capsys.readouterr()
    assert main([*args, "--jobs", "2"]) == 1
    two = capsys.readouterr()
    assert one.out == two.out and '"frames": ' in one.out
    assert f"failed: {BROKEN}" in two.err


def test_tasks_never_split_a_recording_and_keep_the_file_order():
    names = [f"10mm_0mm_{z}mm_1_{i}_frames.csv" for z in (100, 120, 140) for i in (1, 2, 3, 4, 5)]
    files = [Path(n) for n in sorted(names)]
    plain = plan_tasks(files, 2, track=False)
    assert [f for t in plain for f in t] == files and len(plain) == 8
    tracked = plan_tasks(files, 2, track=True)
    assert [f for t in tracked for f in t] == files
    for task in tracked:
        assert len({f.name.rsplit("_", 2)[0] for f in task}) == 1  # 5 per run > 2 per task


def test_jobs_option_is_range_checked_and_mcap_runs_one_job(tmp_path, profile, capsys):
    assert main(["replay", str(tmp_path), "--jobs", "-1"]) == 2
    assert "--jobs" in capsys.readouterr().err
    mcap = tmp_path / "x.mcap"
    mcap.write_bytes(b"")
    assert usable_jobs(4, mcap, None, False, profile) == 1
    assert usable_jobs(4, tmp_path, None, False, profile) == 4
    assert resolve_jobs(0) == (os.cpu_count() or 1)


def _many_files(folders, tmp_path) -> tuple[Path, Path]:
    """12 links to each file: enough to still be running when the signal comes."""
    frames, bg = folders
    big, big_bg = tmp_path / "f", tmp_path / "b"
    big.mkdir(), big_bg.mkdir()
    for copy in range(12):
        for path in frames.glob("*_frames.csv"):
            os.link(path, big / f"c{copy:02d}{path.name}")
            os.link(bg / path.name, big_bg / f"c{copy:02d}{path.name}")
    return big, big_bg


def test_a_task_stops_between_two_files_once_stopped(folders, profile):
    from spiel_edge.pipeline.factory import build_pipeline

    frames, bg = folders
    files = tuple(sorted(frames.glob("*_frames.csv"))[:5])
    pipeline = build_pipeline(profile, "geometric")
    asked = []

    def stopped() -> bool:  # true once two files were read
        asked.append(1)
        return len(asked) > 2

    items, _ = run_task(pipeline, Task(files, str(bg), None, False, False), stopped)
    assert [item.source for item in items] == [f.name for f in files[:2]]
    items, _ = run_task(pipeline, Task(files, str(bg), None, False, False))
    assert len(items) == 5


def _descendants(pid: int) -> set[int]:
    parents = {}
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                stat = (entry / "stat").read_text()
            except OSError:
                continue
            parents[int(entry.name)] = int(stat.rsplit(")", 1)[1].split()[1])
    found, frontier = set(), {pid}
    while frontier:
        frontier = {p for p, parent in parents.items() if parent in frontier} - found
        found |= frontier
    return found


def _alive(pid: int) -> bool:
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT], ids=str)
def test_a_signal_stops_the_workers_and_finalizes_the_output(folders, tmp_path, sig):
    big, big_bg = _many_files(folders, tmp_path)
    proc = subprocess.Popen(
        [*CLI, "replay", str(big), "--background", str(big_bg), "-j", "2"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        bufsize=0,  # unbuffered: communicate() below reads the pipe, not a reader's buffer
    )
    first = proc.stdout.readline()  # the workers are busy now
    workers = _descendants(proc.pid)  # the fork server, its worker, a resource tracker
    proc.send_signal(sig)
    # generous guards against a hang, not deadlines: an emulated arm64 run is 10-30x slower
    rest, err = proc.communicate(timeout=90)
    assert proc.returncode == 1 and b"stopped by a signal" in err and b"Traceback" not in err
    deadline = time.monotonic() + 30
    while any(map(_alive, workers)) and time.monotonic() < deadline:
        time.sleep(0.05)
    left = [p for p in workers if _alive(p)]
    assert len(workers) >= 2 and left == []
    lines = (first + rest).decode().splitlines()  # complete lines, in file order
    names = sorted(p.name for p in big.glob("*_frames.csv"))
    assert 0 < len(lines) < len(names)
    assert [json.loads(line)["source"] for line in lines] == names[: len(lines)]


def _wait_until_stdout_is_full(proc, timeout_s: float = 120.0) -> None:
    deadline = time.monotonic() + timeout_s
    last, since = -1, time.monotonic()
    while time.monotonic() < deadline and proc.poll() is None:
        pending = int.from_bytes(
            fcntl.ioctl(proc.stdout.fileno(), termios.FIONREAD, b"\0\0\0\0"), "little"
        )
        if pending != last:
            last, since = pending, time.monotonic()
        elif pending > 30_000 and time.monotonic() - since > 0.5:
            return
        time.sleep(0.05)
    pytest.fail(f"the replay did not stall on its stdout ({last} bytes pending)")


def test_a_signal_with_stdout_blocked_ends_the_workers_too(folders, tmp_path):
    """The loop cannot stop (its write blocks): the watchdog finalizes, terminates the workers
    and exits; nothing is left running."""
    big, big_bg = _many_files(folders, tmp_path)
    proc = subprocess.Popen(
        [*CLI, "replay", str(big), "--background", str(big_bg), "-j", "2"],
        stdout=subprocess.PIPE,  # not read until the end: the pipe fills and the write blocks
        stderr=subprocess.PIPE,
    )
    _wait_until_stdout_is_full(proc)
    workers = _descendants(proc.pid)
    proc.send_signal(signal.SIGTERM)
    proc.wait(timeout=90)
    deadline = time.monotonic() + 30
    while any(map(_alive, workers)) and time.monotonic() < deadline:
        time.sleep(0.05)
    left = [p for p in workers if _alive(p)]
    for pid in left:  # a worker left behind holds the pipes open: end it, then report it
        os.kill(pid, signal.SIGKILL)
    assert len(workers) >= 2 and left == []
    err = proc.stderr.read()
    assert proc.returncode == 1 and b"stopped by a signal" in err and b"Traceback" not in err
    proc.stdout.close()
