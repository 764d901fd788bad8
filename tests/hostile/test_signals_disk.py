"""Signals, broken pipes and full disks. A signal that ends `run` finalizes its recording within
1 s even while stdout is blocked (nobody reads it); a full disk drops that output, keeps the
others and says so in the exit status; the reader of stdout going away is a normal end."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time

import pytest

from spiel_edge.recordings.mcap_reader import iter_mcap_recordings
from spiel_edge.recordings.mcap_scan import MAGIC

CLI = [sys.executable, "-m", "spiel_edge.cli"]


def _finalized(path) -> bool:
    with open(path, "rb") as fh:
        fh.seek(-len(MAGIC), os.SEEK_END)
        return fh.read() == MAGIC


def _wait_until_stalled(path, proc, timeout_s: float = 60.0) -> None:
    """Until the recording exists and stopped growing: stdout is full, the loop blocked."""
    deadline = time.monotonic() + timeout_s
    last, since = -1, time.monotonic()
    while time.monotonic() < deadline and proc.poll() is None:
        size = path.stat().st_size if path.exists() else -1
        if size != last:
            last, since = size, time.monotonic()
        elif size > 20_000 and time.monotonic() - since > 0.5:
            return
        time.sleep(0.05)
    pytest.fail(f"the run did not stall on its blocked stdout (size {last})")


SIGNALS = [signal.SIGTERM, signal.SIGHUP, signal.SIGINT]


@pytest.fixture(scope="module")
def stalled_runs(tmp_path_factory):
    """One `run --record` per signal, started together (they take seconds to warm up) and
    each left stalled on a stdout nobody reads."""
    root = tmp_path_factory.mktemp("signals")
    runs = {}
    for sig in SIGNALS:
        rec = root / f"r{int(sig)}.mcap"
        proc = subprocess.Popen(
            [*CLI, "run", "--port", "sim://?scene=model", "--rate", "0", "--record", rec],
            stdout=subprocess.PIPE,  # never read: the pipe fills and the loop blocks on it
            stderr=subprocess.PIPE,
        )
        runs[sig] = (proc, rec)
    yield runs
    for proc, _ in runs.values():
        if proc.poll() is None:
            proc.kill()
            proc.wait()


@pytest.mark.parametrize("sig", SIGNALS, ids=str)
def test_signal_finalizes_the_recording_with_stdout_blocked(stalled_runs, sig):
    proc, rec = stalled_runs[sig]
    _wait_until_stalled(rec, proc)
    sent = time.monotonic()
    proc.send_signal(sig)
    while not _finalized(rec) and time.monotonic() - sent < 5:
        time.sleep(0.01)
    took = time.monotonic() - sent
    proc.wait(timeout=10)
    assert _finalized(rec) and took < 1.0, f"finalized after {took:.2f} s"
    recs = list(iter_mcap_recordings(rec))
    assert recs and all(r.error is None for r in recs)
    assert b"Traceback" not in proc.stderr.read()
    assert proc.returncode == 0


def test_broken_pipe_is_a_normal_end(csv_folder):
    proc = subprocess.Popen(
        [*CLI, "replay", csv_folder[0], "--association", "geometric"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
    )
    first = proc.stdout.readline()
    proc.stdout.close()  # like `| head -1`
    err = proc.stderr.read()
    proc.wait(timeout=30)
    assert json.loads(first)["source"] and b"Traceback" not in err and b"Exception" not in err
    assert proc.returncode == 0, err


def test_replay_onto_a_full_disk(cli, csv_folder):
    ran = cli("replay", csv_folder[0], "--association", "geometric", "-o", "/dev/full")
    assert ran.status == 2 and "No space left" in ran.err


def test_a_full_disk_drops_the_recording_keeps_the_rest(cli, tmp_path):
    full = tmp_path / "full.mcap"
    full.symlink_to("/dev/full")
    out = tmp_path / "out.ndjson"
    ran = cli(
        "run", "--port", "sim://?scene=model", "--rate", "0", "--frames", "60",
        "--record", full, "-o", out,
    )  # fmt: skip
    assert ran.status == 1 and "McapSink" in ran.err
    assert len(out.read_text().splitlines()) == 60


def test_every_output_failing_is_an_error(cli):
    ran = cli(
        "run", "--port", "sim://?scene=model", "--rate", "0", "--frames", "5", "-o", "/dev/full"
    )
    assert ran.status == 2 and "every output failed" in ran.err


def test_atomic_outputs_keep_the_old_file_when_the_disk_fills(tmp_path, monkeypatch):
    from spiel_edge.safety import guard

    target = tmp_path / "cal.toml"
    target.write_text("old = 1\n")

    def full(fd):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(guard.os, "fsync", full)
    with pytest.raises(OSError), guard.atomic_write(target) as fh:
        fh.write("new = 2\n")
    assert target.read_text() == "old = 1\n"
    assert [p.name for p in tmp_path.iterdir()] == ["cal.toml"]  # no temporary file left
