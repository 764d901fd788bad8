"""``spiel-edge config`` pull/show/diff/push/commit against a fake board session."""

from __future__ import annotations

import pytest

from spiel_edge.board_config import schema as bc
from spiel_edge.cli import config as cli_config
from spiel_edge.cli import main
from spiel_edge.compat import tomllib
from tests.calibrate.fake_board import FakeBoardSession, TwoSlotFlash


@pytest.fixture
def board(monkeypatch):
    flash = TwoSlotFlash()
    sessions = []

    def opener(port):
        sessions.append(FakeBoardSession(flash))
        return sessions[-1]

    monkeypatch.setattr(cli_config, "open_session", opener)
    return flash, sessions


def test_push_commit_pull_show_diff(board, tmp_path, capsys):
    flash, sessions = board
    assert main(["config", "pull", "--port", "sim://"]) == 2
    assert "no config" in capsys.readouterr().err
    cal = tmp_path / "cal.toml"
    cal.write_text(
        "[geometry]\nchannels_mm = [[0,0,0],[-37,-65,0],[75,0,0],[-37,65,0]]\ndelay_samples = [2.0, 1.5, 1.9, 1.7]\n"
    )
    assert main(["config", "push", "--port", "sim://", "--name", "proto-7", str(cal)]) == 0
    err = capsys.readouterr().err
    assert "staged" in err and "+ board.name = 'proto-7'" in err
    assert flash.active() is None  # not committed yet
    assert main(["config", "commit", "--port", "sim://"]) == 0
    out = tmp_path / "board.toml"
    assert main(["config", "pull", "--port", "sim://", str(out)]) == 0
    pulled = tomllib.loads(out.read_text())
    assert pulled["board"]["name"] == "proto-7" and pulled["geometry"]["delay_samples"] == [
        2.0,
        1.5,
        1.9,
        1.7,
    ]
    capsys.readouterr()
    assert main(["config", "diff", "--port", "sim://", str(out)]) == 0
    assert capsys.readouterr().out.strip() == "no changes"
    out.write_text(out.read_text().replace("gain_db = 20.0", "gain_db = 26.0"))
    assert main(["config", "diff", "--port", "sim://", str(out)]) == 0
    assert capsys.readouterr().out.strip() == "~ acquisition.gain_db: 20.0 -> 26.0"
    assert main(["config", "push", "--port", "sim://", "--commit", str(out)]) == 0
    assert main(["config", "show", "--port", "sim://"]) == 0
    shown = capsys.readouterr().out
    assert (
        "slot 0: generation 1" in shown
        and "slot 1: generation 2" in shown
        and "gain_db = 26.0" in shown
    )
    assert all(s.closed for s in sessions)


def test_invalid_file_is_rejected_before_writing(board, tmp_path, capsys):
    flash, sessions = board
    bad = tmp_path / "bad.toml"
    bad.write_text("[acquisition]\ngain_db = 90\n")
    assert main(["config", "push", "--port", "sim://", str(bad)]) == 2
    assert "acquisition.gain_db must be float in [0, 60]" in capsys.readouterr().err
    assert sessions[-1].staging == b"" and flash.active() is None


def test_commit_with_a_wrong_crc_fails(board, tmp_path, capsys):
    flash, _ = board
    good = tmp_path / "good.toml"
    good.write_text(
        bc.to_toml(bc.from_profile(__import__("spiel_edge.profile.schema").profile.load_profile()))
    )
    assert main(["config", "push", "--port", "sim://", str(good)]) == 0
    assert main(["config", "commit", "--port", "sim://", "--crc", "zz"]) == 2
    assert main(["config", "commit", "--port", "sim://", "--crc", "deadbeef"]) == 2
    assert "CRC" in capsys.readouterr().err and flash.active() is None
