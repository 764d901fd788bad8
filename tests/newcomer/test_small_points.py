"""The smaller newcomer points: the status line and the log, option help texts, ..."""

from __future__ import annotations

import logging
import sys

from spiel_edge.cli._status_line import StatusLine


def test_a_log_record_never_joins_the_status_line(capsys, monkeypatch):
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(logging.Formatter("%(levelname)s %(message)s"))
    root = logging.getLogger()
    monkeypatch.setattr(root, "handlers", [])  # only this test's handler (earlier CLI runs
    monkeypatch.setattr(root, "level", logging.WARNING)  # leave theirs on closed streams)
    root.addHandler(handler)
    try:
        status = StatusLine()
        status.show("20 records, 20 fixes")
        logging.getLogger("spiel_edge.test").warning("link lost")
        status.show("21 records, 21 fixes")
        status.close()
        logging.getLogger("spiel_edge.test").warning("after the end")
    finally:
        root.removeHandler(handler)
    err = capsys.readouterr().err
    # stderr is no terminal here: the status line is ended, not erased
    assert "\r20 records, 20 fixes\nWARNING link lost\n" in err
    assert "\r21 records, 21 fixes\nWARNING after the end\n" in err
    assert not handler.filters  # the filter goes with the status line


def test_firmware_update_progress_in_a_log_is_a_few_lines(tmp_path, capsys):
    from spiel_edge.cli import main
    from spiel_edge.sim import protocol_sim
    from tests.fwsign import signed_image

    image = tmp_path / "new.img"
    image.write_bytes(
        signed_image(b"SIM:OK " + bytes(range(256)) * 40, version="sim-0.2.0", target="sim")
    )
    url = "sim://newcomer-fw?max_payload=256"
    try:
        assert main(["firmware", "update", "--port", url, str(image)]) == 0
    finally:
        protocol_sim.forget(url)
    err = capsys.readouterr().err
    assert "\r" not in err
    progress = [line.split() for line in err.splitlines() if line.startswith("  ")]
    assert 1 <= len(progress) <= 4, err  # a line per quarter, not one per chunk
    size = len(image.read_bytes())  # header, body and signature: every byte is uploaded
    assert progress[-1] == [f"{size}/{size}", "bytes"]


def test_run_robot_records_are_in_unix_time_as_run_records(tmp_path):
    import json
    import time

    from spiel_edge.cli import main

    fused, single = tmp_path / "fused.ndjson", tmp_path / "one.ndjson"
    assert main(["run", "--robot", "virtual-4", "--frames", "4", "-o", str(fused)]) == 0
    assert main(["run", "--port", "sim://", "--frames", "4", "-o", str(single)]) == 0
    now = time.time()
    for path in (fused, single):
        for line in path.read_text().splitlines():
            record = json.loads(line)
            assert abs(record["host_time"] - now) < 120, (path.name, record["host_time"])
            for board in record.get("boards", {}).values():
                assert abs(board["host_time"] - record["host_time"]) < 1.0


def test_a_new_board_gets_a_starting_config_to_push(tmp_path, capsys):
    from spiel_edge.cli import main
    from spiel_edge.sim import protocol_sim

    board = tmp_path / "board.toml"
    assert main(["config", "template", str(board), "--name", "front"]) == 0
    text = board.read_text()
    assert text.endswith("\n") and 'name = "front"' in text and "[geometry]" in text
    url = "sim://newcomer-config"
    try:
        assert main(["config", "push", "--port", url, str(board), "--commit"]) == 0
        capsys.readouterr()
        assert main(["config", "pull", "--port", url]) == 0
        assert 'name = "front"' in capsys.readouterr().out
    finally:
        protocol_sim.forget(url)
    assert main(["config", "template", str(board)]) == 2  # exists: --force to overwrite


def test_simulate_says_a_modelled_board_needs_no_learned_correction(tmp_path):
    from tests.newcomer._pty import pty_board

    with pty_board(tmp_path / "board", "sim://?scene=model") as board:
        pass
    assert "--toa-correction none" in board.stderr_text
