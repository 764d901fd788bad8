"""Bad paths for every command that reads or writes files: never an overwritten file, never a
hang on a FIFO or device, every output checked before the work starts."""

from __future__ import annotations

import os

import pytest

from tests.hostile.conftest import digest

NO_BOARD = "serial:///nonexistent/tty-spiel"


@pytest.fixture
def fifo(tmp_path):
    path = tmp_path / "pipe_frames.csv"
    os.mkfifo(path)
    return path


@pytest.fixture
def loop(tmp_path):
    path = tmp_path / "loop"
    os.symlink(path, path)
    return path


def test_replay_refuses_to_overwrite(cli, csv_folder, precious):
    ran = cli("replay", csv_folder[0], "-o", precious.path)
    assert ran.status == 2 and "--force" in ran.err
    precious.check()


def test_replay_force_overwrites_when_asked(cli, csv_folder, precious):
    ran = cli("replay", csv_folder[0], "--association", "geometric", "-o", precious.path, "--force")
    assert ran.status == 0 and precious.path.read_text().count("\n") == 3


def test_replay_never_writes_over_its_input_even_forced(cli, recording, tmp_path):
    copy = tmp_path / "rec.mcap"
    copy.write_bytes(recording.read_bytes())
    before = digest(copy)
    for extra in ([], ["--force"]):
        ran = cli("replay", copy, "-o", copy, *extra)
        assert ran.status == 2 and "input" in ran.err
    assert digest(copy) == before


@pytest.mark.parametrize(
    "output",
    ["missing/dir/out.ndjson", ".", "x" * 300 + ".ndjson", "missing/" + "y" * 300],
    ids=["missing-folder", "a-folder", "name-too-long", "long-in-missing"],
)
def test_replay_bad_output_fails_before_work(cli, csv_folder, tmp_path, output):
    ran = cli("replay", csv_folder[0], "-o", tmp_path / output)
    assert ran.status == 2 and ran.out == ""


@pytest.mark.parametrize("kind", ["missing", "fifo", "device", "loop"])
def test_replay_bad_inputs(cli, tmp_path, fifo, loop, kind):
    path = {"missing": tmp_path / "no.mcap", "fifo": fifo, "device": "/dev/zero", "loop": loop}[
        kind
    ]
    ran = cli("replay", path, "--format", "mcap", "-o", tmp_path / "o.ndjson")
    assert ran.status == 2
    assert not (tmp_path / "o.ndjson").exists()


def test_replay_fifo_inside_a_folder_is_an_input_error(cli, tmp_path, fifo, csv_folder):
    ran = cli("replay", fifo.parent, "-o", tmp_path / "o.ndjson")
    assert ran.status == 1 and "not a regular file" in (tmp_path / "o.ndjson").read_text()


@pytest.mark.parametrize(
    ("args", "needle"),
    [
        (["-o", "{precious}"], "--force"),
        (["--record", "{precious_mcap}"], "--force"),
        (["-o", "{tmp}/same.mcap", "--record", "{tmp}/same.mcap"], "also the output"),
        (["--record", "{tmp}/missing/%Y.mcap"], "does not exist"),
        (["--record", "{tmp}/rec.txt"], ".mcap"),
        (["--background", "{precious}", "-o", "{precious}", "--force"], "input"),
        (["--calibration", "{fifo}"], "regular"),
        (["--calibration", "/dev/zero"], "regular"),
        (["--background", "{fifo}"], "regular"),
        (["-o", "{tmp}/missing/out.ndjson"], "does not exist"),
        (["--profile", "{fifo}"], "regular"),
        (["--profile", "/dev/zero"], "regular"),
    ],
    ids=lambda v: "-".join(v) if isinstance(v, list) else v,
)
def test_run_checks_files_before_the_board(cli, tmp_path, precious, fifo, args, needle):
    mcap = tmp_path / "precious.mcap"
    mcap.write_bytes(b"not yet replaced")
    fill = {"precious": precious.path, "precious_mcap": mcap, "tmp": tmp_path, "fifo": fifo}
    ran = cli("run", "--port", NO_BOARD, *[a.format(**fill) for a in args])
    assert ran.status == 2 and needle in ran.err, ran
    assert "nonexistent" not in ran.err  # refused before the board was looked at
    precious.check()
    assert mcap.read_bytes() == b"not yet replaced"


@pytest.mark.parametrize(
    "args",
    [
        ["-o", "{precious}"],
        ["-o", "{tmp}/missing/cal.toml"],
        ["-o", "{tmp}/c.png", "--plot", "{tmp}/c.png"],
    ],
    ids=["exists", "missing-folder", "two-outputs-one-path"],
)
def test_calibrate_checks_outputs_before_fitting(cli, csv_folder, tmp_path, precious, args):
    fill = {"precious": precious.path, "tmp": tmp_path}
    ran = cli("calibrate", "--recordings", csv_folder[0], *[a.format(**fill) for a in args])
    assert ran.status == 2 and "written" not in ran.err
    precious.check()


@pytest.mark.parametrize(
    ("args", "needle"),
    [
        (["background", "-o", "{precious}"], "--force"),
        (["background", "-o", "{tmp}/missing/bg.npy"], "does not exist"),
        (["config", "pull", "{precious}"], "--force"),
        (["config", "pull", "{tmp}/missing/c.toml"], "does not exist"),
        (["simulate", "--pty", "--link", "{precious}"], "not a symlink"),
    ],
    ids=lambda v: "-".join(v) if isinstance(v, list) else v,
)
def test_board_commands_check_outputs_before_the_board(cli, tmp_path, precious, args, needle):
    fill = {"precious": precious.path, "tmp": tmp_path}
    extra = [] if args[0] == "simulate" else ["--port", NO_BOARD]
    ran = cli(*[a.format(**fill) for a in args], *extra)
    assert ran.status == 2 and needle in ran.err, ran
    precious.check()


@pytest.mark.parametrize("kind", ["same", "exists", "fifo", "device", "missing"])
def test_recover_paths(cli, recording, tmp_path, precious, fifo, kind):
    src, out = recording, tmp_path / "out.mcap"
    if kind == "same":
        src = out = tmp_path / "copy.mcap"
        out.write_bytes(recording.read_bytes())
    elif kind == "exists":
        out = precious.path
    elif kind in ("fifo", "device", "missing"):
        src = {"fifo": fifo, "device": "/dev/zero", "missing": tmp_path / "none.mcap"}[kind]
    before = out.read_bytes() if out.exists() else None
    ran = cli("recover", src, "-o", out)
    assert ran.status == 2
    assert (out.read_bytes() if out.exists() else None) == before
    precious.check()


@pytest.mark.parametrize("kind", ["fifo", "device", "huge", "binary", "missing"])
def test_config_files_bounded_and_regular(cli, tmp_path, fifo, csv_folder, kind):
    path = {"fifo": fifo, "device": "/dev/zero", "missing": tmp_path / "none.toml"}.get(kind)
    if kind == "huge":
        path = tmp_path / "huge.toml"
        path.write_text("# " + "x" * (2 << 20))
    elif kind == "binary":
        path = tmp_path / "bin.toml"
        path.write_bytes(b"\xff\xfe\x00garbage")
    for command in (
        ["replay", csv_folder[0], "--profile", path],
        ["replay", csv_folder[0], "--calibration", path],
    ):
        ran = cli(*command, "-o", tmp_path / "o.ndjson")
        assert ran.status == 2, ran
    ran = cli("config", "push", path, "--port", NO_BOARD)
    assert ran.status == 2


def test_evaluate_on_a_folder_with_nothing_usable(cli, tmp_path):
    (tmp_path / "a_frames.csv").write_text("not numbers\n")
    ran = cli("evaluate", tmp_path)
    assert ran.status in (1, 2)
    empty = tmp_path / "empty"
    empty.mkdir()
    assert cli("evaluate", empty).status == 2
