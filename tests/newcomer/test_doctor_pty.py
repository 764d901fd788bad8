"""``doctor --port`` does not FAIL a working board on a pty or the virtual board."""

from __future__ import annotations

import json

from spiel_edge.cli import main
from spiel_edge.service.doctor import port_kind
from tests.newcomer._pty import pty_board


def _doctor(port, capsys):
    rc = main(["doctor", "--port", port, "--skip-numba", "--json"])
    return rc, json.loads(capsys.readouterr().out)


def test_the_virtual_board_passes(capsys):
    rc, out = _doctor("sim://newcomer-doctor", capsys)
    assert rc == 0 and out["ok"], out
    board = next(c for c in out["checks"] if c["name"] == "board")
    assert "not needed for sim://newcomer-doctor (a virtual board, answering)" in board["detail"]


def test_a_board_on_a_pty_passes(tmp_path, capsys):
    link = tmp_path / "board"
    with pty_board(link):
        assert port_kind(str(link)) == "pseudo-terminal"
        rc, out = _doctor(str(link), capsys)
    assert rc == 0 and out["ok"], out
    names = {c["name"]: c for c in out["checks"]}
    assert names["board link"]["ok"] and "SIM0001" in names["board link"]["detail"]


def test_a_dead_port_still_fails(tmp_path, capsys):
    rc, out = _doctor(str(tmp_path / "nothing"), capsys)
    assert rc == 1 and not out["ok"]
    assert port_kind(str(tmp_path / "nothing")) is None
    assert port_kind("/dev/null") is None  # a character device, not a pty
