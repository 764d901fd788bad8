"""The composition root of `run --robot` (robot/live.py, issue 42): a robot's fused run from
the library, its documented example, and its files checked before any board opens."""

from __future__ import annotations

import json
import re
import threading
from pathlib import Path

import pytest

from spiel_edge.errors import ConfigError, InputError
from spiel_edge.robot.live import RobotConfig, RobotRun, run

ROOT = Path(__file__).resolve().parents[2]


def test_run_a_robot_from_the_library(tmp_path, capsys):
    records = []
    out = tmp_path / "fused.ndjson"
    live = run(RobotConfig("virtual-4", frames=5, output=str(out)), on_record=records.append)
    assert live.runner.records == 5 and [r["seq"] for r in records] == [0, 1, 2, 3, 4]
    written = [json.loads(line) for line in out.read_text().splitlines()]
    assert written == json.loads(json.dumps(records))  # the file holds what on_record saw
    assert all(r["frame_id"] == "base_link" for r in records)
    assert set(records[-1]["boards"]) == {"front", "left", "back", "right"}
    assert not live.dropped and capsys.readouterr().out == ""


def test_no_output_but_the_callback(capsys):
    records = []
    run(RobotConfig("virtual-4", frames=3, output=None), on_record=records.append)
    assert len(records) == 3 and capsys.readouterr().out == ""


def test_a_missing_board_calibration_fails_before_any_board_opens(tmp_path):
    text = (ROOT / "spiel_edge/robot/builtin/virtual-4.toml").read_text()
    calibrated = text.replace("slot = 0\n", 'slot = 0\ncalibration = "no-such.toml"\n', 1)
    robot = tmp_path / "rover.toml"
    robot.write_text(calibrated)
    live = RobotRun(RobotConfig(str(robot), frames=1, output=None))
    with pytest.raises((ConfigError, InputError), match="no-such.toml"):
        live.prepare()
    assert live.runner is None  # no board was prepared, none opened
    live.close()  # safe after a failed prepare


def test_an_output_may_not_replace_the_robot_file(tmp_path):
    robot = tmp_path / "rover.toml"
    robot.write_text((ROOT / "spiel_edge/robot/builtin/virtual-4.toml").read_text())
    live = RobotRun(RobotConfig(str(robot), frames=1, output=str(robot), force=True))
    with pytest.raises(ConfigError, match="input"):
        live.prepare()
    assert live.runner is None


def test_stopping_ends_the_run():
    stop = threading.Event()
    records = []

    def on_record(record):
        records.append(record)
        if len(records) == 2:
            stop.set()

    run(RobotConfig("virtual-4", output=None), on_record=on_record, stop=stop)
    assert 2 <= len(records) <= 3


def test_the_documented_example_runs():
    text = (ROOT / "docs" / "live-api.md").read_text()
    blocks = re.findall(r"```python\n(.*?)```", text, re.S)
    example = next(b for b in blocks if "robot.live" in b)
    scope: dict = {}
    exec(compile(example, "docs/live-api.md", "exec"), scope)  # noqa: S102  (our own docs)
    assert len(scope["records"]) == 20 and scope["live"].runner.records == 20


def test_a_board_without_a_background_is_named_not_told_to_give_one(caplog):
    """A robot's board processes as `run` does; its warning for a missing background capture
    names the board and does not ask for --background, which `run --robot` refuses."""
    import time

    import numpy as np

    from spiel_edge.data import load_subset
    from spiel_edge.device import LiveAcquisition

    live = RobotRun(RobotConfig("virtual-4", output=None))
    live.prepare()
    worker = live.runner.workers[0]
    worker._open()
    try:
        frames = load_subset().frames[0].astype(np.uint16)
        acq = LiveAcquisition(0, 0, 22_000, frames, time.perf_counter_ns(), time.time())
        with caplog.at_level("WARNING"):
            result, error = worker.live.runner.process(acq)
        assert error is None and result is not None
        said = [r.getMessage() for r in caplog.records if "background" in r.getMessage()]
        assert len(said) == 1 and f"board {worker.board.name}" in said[0], said
        assert "give --background" not in said[0]
    finally:
        worker.session.close()
        live.close()
