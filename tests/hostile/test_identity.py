"""Files by identity, not by name (issue 28, part 1): an output that is a hard link to an input
is refused even with --force; two commands on one output cannot both succeed; an output is a
regular file, a terminal, a pipe with a reader or a null device, and opening it never blocks."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import threading
import time

import pytest

from spiel_edge.errors import ConfigError
from spiel_edge.safety import guard
from tests.hostile.conftest import digest

NO_BOARD = "serial:///nonexistent/tty-spiel"
CLI = [sys.executable, "-m", "spiel_edge.cli"]


@pytest.fixture(autouse=True)
def _no_claims_left():
    yield
    guard.release_claims()


def _twin(path, tmp_path, name):
    """A hard link to ``path`` (the same file under another name)."""
    link = tmp_path / name
    os.link(path, link)
    return link


# --- hard links: the same file under two names ------------------------------------------------


ROBOT_TOML = """[robot]
name = "mine"
[trigger]
period_ms = 25.0
[[board]]
name = "front"
port = "sim://front?scene=robot&robot=virtual-4&board=front&movers=1"
slot = 0
"""


@pytest.mark.parametrize(
    "command",
    ["run --robot", "run --slot", "fuse --robot", "fuse --replay", "fuse --record", "pack"],
)
def test_robot_fuse_and_pack_never_overwrite_their_inputs_even_forced(cli, tmp_path, command):
    """The robot file, a board's recorded records and a firmware body are inputs: no output
    replaces them, --force or not, and nothing runs."""
    robot = tmp_path / "mine.toml"
    robot.write_text(ROBOT_TOML)
    records = tmp_path / "front.ndjson"
    records.write_text('{"acquisition": 0, "device_time_us": 1, "host_time": 1.0}\n')
    recording = tmp_path / "front.mcap"
    recording.write_bytes(b"\x89MCAP0\r\n")
    body = tmp_path / "body.bin"
    body.write_bytes(bytes(range(256)) * 8)
    args, victim = {
        "run --robot": (["run", "--robot", robot, "--frames", "2", "-o", robot], robot),
        "run --slot": (["run", "--port", "sim://", "--frames", "2", "--slot", f"{robot}:front", "-o", robot], robot),
        "fuse --robot": (["fuse", "--robot", robot, "--replay", f"front={records}", "-o", robot], robot),
        "fuse --replay": (["fuse", "--robot", robot, "--replay", f"front={records}", "-o", records], records),
        "fuse --record": (["fuse", "--robot", robot, "--replay", f"front={recording}", "--record", recording], recording),
        "pack": (["firmware", "pack", body, "--version", "1.0", "--target", "sim", "-o", body], body),
    }[command]  # fmt: skip
    before = digest(victim)
    ran = cli(*args, "--force")
    assert ran.status == 2 and "is the input" in ran.err, ran
    assert digest(victim) == before


@pytest.mark.parametrize("force", [[], ["--force"]], ids=["plain", "forced"])
@pytest.mark.parametrize(
    ("option", "output"),
    [
        ("--calibration", "-o"),
        ("--background", "-o"),
        ("--calibration", "--record"),
        ("--background", "--record"),
    ],
)
def test_run_refuses_an_output_that_is_an_inputs_hard_link(cli, tmp_path, option, output, force):
    source = tmp_path / ("in.toml" if option == "--calibration" else "bg.npy")
    source.write_bytes(b"[geometry]\n" if option == "--calibration" else b"precious")
    before = digest(source)
    twin = _twin(source, tmp_path, "out.mcap" if output == "--record" else "out.ndjson")
    ran = cli("run", "--port", NO_BOARD, option, source, output, twin, *force)
    assert ran.status == 2 and "the same file under another name" in ran.err, ran
    assert "nonexistent" not in ran.err  # refused before the board
    assert digest(source) == before


@pytest.mark.parametrize("force", [[], ["--force"]], ids=["plain", "forced"])
def test_replay_refuses_an_output_linked_to_its_input(cli, recording, tmp_path, force):
    copy = tmp_path / "rec.mcap"
    copy.write_bytes(recording.read_bytes())
    twin = _twin(copy, tmp_path, "out.ndjson")
    ran = cli("replay", copy, "-o", twin, *force)
    assert ran.status == 2 and "input" in ran.err
    assert digest(copy) == digest(recording)


@pytest.mark.parametrize("force", [[], ["--force"]], ids=["plain", "forced"])
def test_replay_refuses_an_output_linked_to_its_calibration(cli, csv_folder, tmp_path, force):
    cal = tmp_path / "cal.toml"
    cal.write_text("[geometry]\n")
    twin = _twin(cal, tmp_path, "o.ndjson")
    ran = cli("replay", csv_folder[0], "--calibration", cal, "-o", twin, *force)
    assert ran.status == 2 and "--calibration" in ran.err
    assert cal.read_text() == "[geometry]\n"


@pytest.mark.parametrize("force", [[], ["--force"]], ids=["plain", "forced"])
def test_recover_refuses_an_output_linked_to_its_input(cli, recording, tmp_path, force):
    copy = tmp_path / "rec.mcap"
    copy.write_bytes(recording.read_bytes())
    twin = _twin(copy, tmp_path, "fixed.mcap")
    ran = cli("recover", copy, "-o", twin, *force)
    assert ran.status == 2 and "input" in ran.err
    assert digest(copy) == digest(recording)


@pytest.mark.parametrize("force", [[], ["--force"]], ids=["plain", "forced"])
@pytest.mark.parametrize("option", ["--positions", "--calibration"])
def test_calibrate_refuses_an_output_linked_to_an_input(cli, tmp_path, option, force):
    source = tmp_path / "in.csv"
    source.write_text("0,0,100\n")
    twin = _twin(source, tmp_path, "cal.toml")
    ran = cli("calibrate", option, source, "-o", twin, "--port", NO_BOARD, *force)
    assert ran.status == 2 and "the same file under another name" in ran.err, ran
    assert source.read_text() == "0,0,100\n"


def test_two_outputs_that_are_one_file_are_refused(cli, tmp_path):
    first = tmp_path / "a.mcap"
    first.write_bytes(b"x")
    twin = _twin(first, tmp_path, "b.mcap")
    ran = cli("run", "--port", NO_BOARD, "-o", first, "--record", twin, "--force")
    assert ran.status == 2 and "also the output" in ran.err
    assert first.read_bytes() == b"x"


def test_a_symlink_to_an_input_is_the_input(cli, recording, tmp_path):
    copy = tmp_path / "rec.mcap"
    copy.write_bytes(recording.read_bytes())
    (tmp_path / "alias.ndjson").symlink_to(copy)
    ran = cli("replay", copy, "-o", tmp_path / "alias.ndjson", "--force")
    assert ran.status == 2 and digest(copy) == digest(recording)


# --- what an output may be -------------------------------------------------------------------


def _fifo(tmp_path, name="out.fifo"):
    path = tmp_path / name
    os.mkfifo(path)
    return path


def _reader(path):
    """A reader on a FIFO (the other end of `-o fifo`); returns (thread, chunks)."""
    chunks: list[bytes] = []

    def read() -> None:
        with open(path, "rb") as fh:
            while data := fh.read(65536):
                chunks.append(data)

    thread = threading.Thread(target=read, daemon=True)
    thread.start()
    time.sleep(0.05)
    return thread, chunks


@pytest.mark.parametrize(
    "command",
    [
        ["run", "--port", NO_BOARD, "-o"],
        ["run", "--port", NO_BOARD, "--record"],
        ["replay", "{rec}", "-o"],
        ["recover", "{rec}", "-o"],
        ["background", "--port", NO_BOARD, "-o"],
        ["config", "pull", "--port", NO_BOARD],
        ["calibrate", "--recordings", "{tmp}", "-o"],
    ],
    ids=lambda c: "-".join(a for a in c if not a.startswith(("{", "serial"))),
)
def test_a_pipe_nobody_reads_is_refused_at_once(cli, recording, tmp_path, command):
    fifo = _fifo(tmp_path, "o.mcap")
    t0 = time.monotonic()
    args = [a.format(rec=recording, tmp=tmp_path) for a in command]
    ran = cli(*args, fifo)
    assert ran.status == 2 and "nobody reads" in ran.err, ran
    assert time.monotonic() - t0 < 10


def test_a_pipe_with_a_reader_gets_the_records(cli, csv_folder, tmp_path):
    fifo = _fifo(tmp_path)
    thread, chunks = _reader(fifo)
    ran = cli("replay", csv_folder[0], "--association", "geometric", "-o", fifo)
    thread.join(10)
    assert ran.status == 0 and b"".join(chunks).count(b"\n") == 3


def test_a_pipe_reader_is_not_ended_by_the_check(tmp_path):
    """The check opens the pipe's write end; it keeps it open (closing it would give the
    reader an end of file before the command wrote anything)."""
    fifo = _fifo(tmp_path)
    thread, chunks = _reader(fifo)
    guard.FilePlan().output(fifo, "-o")
    time.sleep(0.1)
    assert thread.is_alive()
    with guard.open_exclusive(fifo, force=False) as fh:
        fh.write(b"record\n")
    guard.release_claims()
    thread.join(5)
    assert b"".join(chunks) == b"record\n"


@pytest.mark.parametrize("device", ["/dev/null", "/dev/zero", "/dev/full"])
def test_null_devices_are_outputs(device):
    assert guard.FilePlan().output(device, "-o") is not None


def test_a_socket_is_refused(tmp_path):
    path = tmp_path / "s.sock"
    with socket.socket(socket.AF_UNIX) as sock:
        sock.bind(str(path))
        with pytest.raises(ConfigError, match="socket"):
            guard.FilePlan().output(path, "-o")


@pytest.mark.parametrize("device", ["/dev/urandom", "/dev/random", "/dev/mem", "/dev/kmsg"])
def test_other_devices_are_refused(device):
    if not os.path.exists(device):
        pytest.skip(f"{device} is absent here")
    with pytest.raises(ConfigError, match="device|cannot write"):
        guard.FilePlan().output(device, "-o")


def test_a_file_that_became_a_pipe_since_the_check_never_blocks(tmp_path):
    path = tmp_path / "late.ndjson"
    guard.FilePlan().output(path, "-o")
    os.mkfifo(path)  # another program put a pipe there meanwhile
    t0 = time.monotonic()
    with pytest.raises(ConfigError, match="exists|nobody reads"):
        guard.open_exclusive(path, force=False, text=True)
    assert time.monotonic() - t0 < 1


# --- two commands on one output -------------------------------------------------------------


def test_a_forced_output_is_locked_against_a_second_command(tmp_path):
    path = tmp_path / "out.ndjson"
    path.write_text("old\n")
    guard.FilePlan(force=True).output(path, "-o")  # the first command holds the lock
    with pytest.raises(ConfigError, match="another command is writing it"):
        guard.FilePlan(force=True).output(path, "--output")


def test_a_forced_recording_open_by_another_process_is_refused(tmp_path):
    path = tmp_path / "busy.mcap"
    path.write_bytes(b"being written")
    holder = subprocess.Popen(
        [
            sys.executable,
            "-c",
            "import fcntl, sys, time; f = open(sys.argv[1], 'rb'); "
            "fcntl.flock(f, fcntl.LOCK_EX); print('locked', flush=True); time.sleep(30)",
            str(path),
        ],
        stdout=subprocess.PIPE,
    )
    try:
        assert holder.stdout.readline().strip() == b"locked"
        with pytest.raises(ConfigError, match="another command"):
            guard.FilePlan(force=True).output(path, "--record")
        assert path.read_bytes() == b"being written"
    finally:
        holder.kill()
        holder.wait()


def test_an_output_that_appeared_meanwhile_is_not_replaced(tmp_path):
    path = tmp_path / "cal.toml"
    guard.FilePlan().output(path, "-o")
    path.write_text("another command's\n")
    with pytest.raises(ConfigError, match="appeared during"), guard.atomic_write(path) as fh:
        fh.write("ours\n")
    assert path.read_text() == "another command's\n"
    assert [p.name for p in tmp_path.iterdir()] == ["cal.toml"]  # no temporary left


def test_a_forced_output_replaced_meanwhile_is_not_replaced_again(tmp_path):
    path = tmp_path / "cal.toml"
    path.write_text("old\n")
    guard.FilePlan(force=True).output(path, "-o")
    other = tmp_path / "other"
    other.write_text("another program's\n")
    os.replace(other, path)
    with (
        pytest.raises(ConfigError, match="replaced by another program"),
        guard.atomic_write(path) as fh,
    ):
        fh.write("ours\n")
    assert path.read_text() == "another program's\n"


def test_a_forced_output_is_replaced_when_nobody_else_touched_it(tmp_path):
    path = tmp_path / "cal.toml"
    path.write_text("old\n")
    guard.FilePlan(force=True).output(path, "-o")
    with guard.atomic_write(path) as fh:
        fh.write("new\n")
    assert path.read_text() == "new\n"


def test_an_ndjson_stream_that_appeared_meanwhile_is_not_truncated(tmp_path):
    from spiel_edge.outputs.ndjson import NdjsonSink

    path = tmp_path / "o.ndjson"
    guard.FilePlan().output(path, "-o")
    path.write_text("another run's records\n")
    with pytest.raises(ConfigError, match="exists"):
        NdjsonSink(path, exclusive=True)
    assert path.read_text() == "another run's records\n"


def test_two_recovers_on_one_new_output_cannot_both_succeed(recording, tmp_path):
    out = tmp_path / "fixed.mcap"
    procs = [
        subprocess.Popen(
            [*CLI, "recover", str(recording), "-o", str(out)],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
        )
        for _ in range(2)
    ]
    results = [(p.wait(120), p.stderr.read().decode()) for p in procs]
    statuses = sorted(status for status, _ in results)
    assert statuses == [0, 2], results
    loser = next(err for status, err in results if status != 0)
    assert "exists" in loser or "appeared during" in loser, loser
    assert "Traceback" not in loser
    assert out.stat().st_size > 1000  # the winner's recording, whole


def test_a_forced_new_output_that_appeared_meanwhile_is_not_replaced(tmp_path):
    """--force allows replacing the file that was there at the check; a file another command
    created since (there was none) is not replaced either."""
    path = tmp_path / "new.toml"
    guard.FilePlan(force=True).output(path, "-o")
    path.write_text("another command's\n")
    with pytest.raises(ConfigError, match="appeared during"), guard.atomic_write(path) as fh:
        fh.write("ours\n")
    assert path.read_text() == "another command's\n"


@pytest.mark.parametrize("force", [[], ["--force"]], ids=["plain", "forced"])
@pytest.mark.parametrize("how", ["same-name", "hard-link"])
@pytest.mark.parametrize("command", ["run", "replay", "calibrate"])
def test_a_profile_file_is_an_input_too(cli, csv_folder, tmp_path, command, how, force):
    from spiel_edge.profile.schema import dump_toml, load_profile, profile_to_dict

    profile = tmp_path / "mine.toml"
    profile.write_text(dump_toml(profile_to_dict(load_profile("spiel-icra23"))))
    before = digest(profile)
    out = profile if how == "same-name" else _twin(profile, tmp_path, "out.toml")
    args = {
        "run": ["run", "--port", NO_BOARD],
        "replay": ["replay", csv_folder[0]],
        "calibrate": ["calibrate", "--recordings", csv_folder[0]],
    }[command]
    ran = cli(*args, "--profile", profile, "-o", out, *force)
    assert ran.status == 2 and "--profile" in ran.err, ran
    assert digest(profile) == before
