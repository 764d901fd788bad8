"""The one composition root of a board's run (runtime/live.py, issue 42): the library's
"run a board" API, its documented example, one validation per acquisition, and a walk of
`run --port` that climbs back up the layers at most 3 times."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest

from spiel_edge.errors import ConfigError
from spiel_edge.runtime.live import LiveConfig, LiveRun, run

ROOT = Path(__file__).resolve().parents[2]


def test_run_a_board_from_the_library(tmp_path):
    records = []
    out = tmp_path / "records.ndjson"
    stats = run(
        LiveConfig(port="sim://", frames=5, output=str(out), max_targets=2),
        on_record=records.append,
    )
    assert stats.records == 5 and [r["seq"] for r in records] == [0, 1, 2, 3, 4]
    written = [json.loads(line) for line in out.read_text().splitlines()]
    assert written == json.loads(json.dumps(records))  # the file holds what on_record saw
    assert stats.fixes >= 4 and all(len(r["targets"]) <= 2 for r in records)
    assert all(r["source"] == "sim://" and "truth_mm" in r for r in records)


def test_no_output_but_the_callback(capsys):
    records = []
    run(LiveConfig(port="sim://", frames=2, output=None), on_record=records.append)
    assert len(records) == 2 and capsys.readouterr().out == ""  # no NDJSON on stdout


def test_a_bad_profile_fails_before_the_board():
    live = LiveRun(LiveConfig(port="sim://?unplug_after=1", profile="no-such-profile"))
    with pytest.raises(ConfigError, match="unknown profile"):
        live.prepare()
    assert live.session is None  # the board was never touched


def test_a_slot_needs_its_starter():
    with pytest.raises(ConfigError, match="in_slot"):
        LiveRun(LiveConfig(port="sim://", slot="virtual-4:front"))


def test_the_documented_example_runs():
    text = (ROOT / "docs" / "live-api.md").read_text()
    example = re.search(r"```python\n(.*?)```", text, re.S).group(1)
    scope: dict = {}
    exec(compile(example, "docs/live-api.md", "exec"), scope)  # noqa: S102  (our own docs)
    assert len(scope["records"]) == 20 and scope["stats"].records == 20


def test_an_acquisition_is_validated_once(monkeypatch):
    """preprocess checks the frames (and a background); the later stages trust its output."""
    from spiel_edge.data import load_subset
    from spiel_edge.pipeline.staged import Pipeline
    from spiel_edge.pipeline.stages import _validate, detect, features, memg, preprocess, split
    from spiel_edge.profile.schema import load_profile

    calls = []
    real = _validate.as_frames

    def counted(arr, name="frames"):
        calls.append(name)
        return real(arr, name)

    for module in (detect, features, memg, preprocess, split):
        monkeypatch.setattr(module, "as_frames", counted)
    subset = load_subset()
    frames = subset.frames[0]
    pipeline = Pipeline(load_profile("spiel-icra23"))
    pipeline.process(frames, subset.backgrounds[0])
    assert calls == ["frames", "background"]  # was 6: each stage checked the envelope again
    with pytest.raises(Exception, match="NaN"):  # the public stage still checks on its own
        detect.detect(np.full((4, 64), np.nan), threshold=1.0)


def test_a_walk_of_port_climbs_back_up_at_most_3_times():
    from tests.house.call_walk import walk

    w, code = walk(
        ["run", "--port", "sim://", "--frames", "3", "-o", "/dev/null", "--max-targets", "2"]
    )
    assert code == 0
    assert len(w.climbs) <= 3, w.report()
    assert not [edge for edge in w.climbs if ".cli." in edge[1]], (
        w.report()
    )  # nothing calls the CLI
    # the profile loaded once, the ToA correction chosen once, the board's pipeline sized once
    assert w.calls["spiel_edge.profile.schema:load_profile"] == 1
    assert w.calls["spiel_edge.runtime.loop:live_toa_correction"] == 1
    assert w.calls["spiel_edge.runtime.loop:open_pipeline"] == 1
    # one pipeline: the kernel check exercises the run's own (was 2: the check built another)
    assert w.calls["spiel_edge.pipeline.factory:build_pipeline"] == 1


def test_run_robot_opens_each_board_as_run_does_and_runs_runs_loop():
    """Each board of `run --robot` through LiveRun and LiveRunner (no loop of its own): one
    pipeline and one ToA choice per board, plus the kernel check's one per profile."""
    from tests.house.call_walk import walk

    w, code = walk(["run", "--robot", "virtual-4", "--frames", "3", "-o", "/dev/null"])
    assert code == 0
    assert w.calls["spiel_edge.runtime.live:LiveRun.prepare"] == 4
    assert w.calls["spiel_edge.runtime.live:LiveRun.open"] == 4
    assert w.calls["spiel_edge.runtime.loop:LiveRunner.run"] == 4
    assert w.calls["spiel_edge.runtime.loop:live_toa_correction"] == 4
    assert w.calls["spiel_edge.pipeline.factory:build_pipeline"] == 1 + 4
    assert w.calls["spiel_edge.robot.board_worker:BoardWorker._step"] >= 12  # 3 cycles x 4
    assert len(w.climbs) <= 3, w.report()


def test_run_robot_says_the_foxglove_view_address(tmp_path, capsys):
    pytest.importorskip("foxglove", reason="extra 'foxglove' not installed")
    from spiel_edge.cli import main
    from tests.robot.test_serve import _robot

    out = tmp_path / "fused.ndjson"
    argv = ["run", "--robot", str(_robot(tmp_path)), "--frames", "3", "-o", str(out)]
    assert main([*argv, "--foxglove", "0"]) == 0
    err = capsys.readouterr().err
    assert "(layout: packaging/foxglove/spiel-edge.json)" in err, err  # as `run --foxglove`
    assert "ws://127.0.0.1:" in err, err


def test_a_recording_without_ndjson(tmp_path, capsys):
    records = []
    mcap = tmp_path / "run.mcap"
    run(
        LiveConfig(port="sim://", frames=3, output=None, record=str(mcap)), on_record=records.append
    )
    assert len(records) == 3 and mcap.stat().st_size > 0
    assert capsys.readouterr().out == ""  # a recording, and nothing on stdout


def test_a_board_as_fast_as_it_can_keeps_a_clock_the_host_trusts(caplog):
    """`--rate 0` on the virtual board: its stamps advance with its acquisitions, so no stamp
    falls back to the arrival time (a burst stamped with one time did, with two warnings)."""
    records = []
    with caplog.at_level("WARNING"):
        run(LiveConfig(port="sim://", rate=0, frames=120, output=None), on_record=records.append)
    assert len(records) == 120
    assert {r.get("stamp_source") for r in records} <= {"board", None}
    assert not [r.message for r in caplog.records if "clock" in r.getMessage()]
