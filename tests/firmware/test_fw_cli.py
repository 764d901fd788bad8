"""Host commands against the posix C firmware on a pty: `run` gives the records `replay` gives
for the same recordings (position and every echo), with and without `--background`; config
push/commit/pull round-trips; calibrate captures; background captures."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from spiel_edge.cli import main
from tools.release.firmware_scans import read_folder, write_scans

N_FRAMES = 300
COMPARED = ("position_mm", "reason", "residual_mm", "echoes", "matched", "targets")


@pytest.fixture(scope="module")
def recordings(tmp_path_factory, subset):
    """300 spiel-csv recordings (the subset looped), one background folder of identical
    files, the same background as one file, and the scans file of the recordings."""
    root = tmp_path_factory.mktemp("fw-recordings")
    frames, bg = root / "frames", root / "bg"
    frames.mkdir()
    bg.mkdir()
    background = subset.backgrounds[0]
    for k in range(N_FRAMES):
        name = f"{k:04d}_{subset.names[k % len(subset)]}"
        np.savetxt(frames / name, subset.frames[k % len(subset)], fmt="%d")
        np.savetxt(bg / name, background, fmt="%d")
    np.savetxt(root / "background.csv", background, fmt="%d")
    scans = write_scans(root / "recordings.spas", read_folder(frames), 22000)
    return frames, bg, root / "background.csv", scans


def records(path: Path) -> list[dict]:
    return [json.loads(line) for line in path.read_text().splitlines()]


def compared(recs: list[dict]) -> list[dict]:
    return [{k: r.get(k) for k in COMPARED} for r in recs]


@pytest.mark.parametrize("with_background", [False, True], ids=["plain", "background"])
def test_run_on_the_c_firmware_gives_the_records_of_replay(
    posix_board, recordings, tmp_path, with_background
):
    frames, bg_folder, bg_file, scans = recordings
    board = posix_board(scans=scans)
    live, replayed = tmp_path / "run.ndjson", tmp_path / "replay.ndjson"
    extra = ["--background", str(bg_file)] if with_background else []
    args = ["run", "--port", board.port, "--frames", str(N_FRAMES), "--rate", "0"]
    assert main([*args, "--no-track", "-o", str(live), *extra]) == 0
    extra = ["--background", str(bg_folder)] if with_background else []
    assert main(["replay", str(frames), "-o", str(replayed), *extra]) == 0
    got, want = records(live), records(replayed)
    assert len(got) == len(want) == N_FRAMES
    assert [r["acquisition"] for r in got] == list(range(N_FRAMES))  # nothing lost or skipped
    assert compared(got) == compared(want)
    assert sum(r["position_mm"] is not None for r in got) > N_FRAMES // 2  # real fixes


def test_config_push_commit_pull_round_trips(posix_board, tmp_path, capsys):
    board = posix_board()
    first = tmp_path / "first.toml"
    assert main(["config", "pull", "--port", board.port, str(first)]) == 2  # none stored yet
    capsys.readouterr()
    partial = tmp_path / "name.toml"
    partial.write_text('[board]\nname = "posix-board"\n')
    assert main(["config", "push", "--port", board.port, str(partial)]) == 0
    assert "staged" in capsys.readouterr().err
    assert main(["config", "commit", "--port", board.port]) == 0
    pulled = tmp_path / "pulled.toml"
    assert main(["config", "pull", "--port", board.port, str(pulled)]) == 0
    text = pulled.read_text()
    assert 'name = "posix-board"' in text and "[geometry]" in text
    capsys.readouterr()
    assert main(["config", "diff", "--port", board.port, str(pulled)]) == 0
    assert "no changes" in capsys.readouterr().out
    assert main(["config", "show", "--port", board.port]) == 0
    assert "# active slot: 0" in capsys.readouterr().out
    board.stop()  # the config survives a power cycle (the flash file)
    board = posix_board()
    again = tmp_path / "again.toml"
    assert main(["config", "pull", "--port", board.port, str(again)]) == 0
    assert again.read_text() == text


def test_background_and_calibrate_capture(posix_board, tmp_path, subset, capsys):
    # the scans: target-free frames for the background capture, then three positions
    picks = [i for i in range(len(subset)) if subset.truth_mm[i][2] != 90.0][:: len(subset) // 8]
    picks = picks[:8]
    empty = np.repeat(subset.backgrounds[picks[0]][None], 1 + 4, axis=0)  # probe + 4 captures
    targets = np.concatenate([np.repeat(subset.frames[i][None], 4, axis=0) for i in picks])
    scans = write_scans(tmp_path / "cal.spas", np.concatenate([empty, targets]), 22000)
    positions = tmp_path / "positions.csv"
    np.savetxt(positions, subset.truth_mm[picks], delimiter=",")
    board = posix_board(scans=scans)
    out = tmp_path / "cal.toml"
    ran = main(
        [
            "calibrate",
            "--port",
            board.port,
            "--positions",
            str(positions),
            "--captures",
            "4",
            "--no-prompt",
            "--force",  # capture is under test; 8 positions cannot beat the profile (issue 41)
            "-o",
            str(out),
        ]
    )
    err = capsys.readouterr().err
    assert ran == 0, err
    assert "[geometry]" in out.read_text()
    board.stop()
    board = posix_board(scans=scans)
    npy = tmp_path / "bg.npy"
    assert main(["background", "--port", board.port, "--frames", "5", "-o", str(npy)]) == 0
    np.testing.assert_array_equal(np.load(npy), subset.backgrounds[picks[0]])
