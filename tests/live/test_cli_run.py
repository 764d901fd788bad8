"""``spiel-edge run`` and ``spiel-edge simulate`` in-process, on the virtual board."""

from __future__ import annotations

import json

import numpy as np

from spiel_edge.cli import main
from spiel_edge.link import discover
from spiel_edge.recordings.mcap_reader import recording_metadata


def records(path) -> list[dict]:
    return [json.loads(line) for line in path.read_text().splitlines()]


def test_run_writes_one_record_per_acquisition(sim_url, tmp_path, capsys):
    out = tmp_path / "out.ndjson"
    assert (
        main(["run", "--port", sim_url(), "--frames", "40", "--rate", "400", "-o", str(out)]) == 0
    )
    recs = records(out)
    assert [r["seq"] for r in recs] == list(range(40)) == [r["acquisition"] for r in recs]
    first = recs[0]
    for key in (
        "device_time_us",
        "host_time",
        "source",
        "position_mm",
        "reason",
        "residual_mm",
        "echoes",
        "matched",
        "truth_mm",
    ):
        assert key in first
    assert np.all(np.diff([r["device_time_us"] for r in recs]) == 2500)  # 400 Hz board clock
    errors = [
        np.linalg.norm(np.subtract(r["position_mm"], r["truth_mm"]))
        for r in recs
        if r["position_mm"]
    ]
    assert (
        len(errors) >= 36 and np.median(errors) < 40
    )  # real recordings, geometric or learned association
    assert "40 records" in capsys.readouterr().err


def test_run_on_the_echo_model_is_accurate(sim_url, tmp_path):
    # no --toa-correction: the learned correction fits the recorded board's echo shapes, not
    # the echo model's, so run leaves it out on a modelled envelope (with it: median ~7 mm)
    out = tmp_path / "out.ndjson"
    port = sim_url("scene=model&seed=3")
    assert main(["run", "--port", port, "--frames", "60", "--rate", "500", "-o", str(out)]) == 0
    recs = records(out)
    errors = [
        np.linalg.norm(np.subtract(r["position_mm"], r["truth_mm"]))
        for r in recs
        if r["position_mm"]
    ]
    assert len(errors) >= 57 and np.median(errors) < 5.5 and np.max(errors) < 18


def test_run_takes_the_port_from_the_environment(sim_url, tmp_path, monkeypatch):
    monkeypatch.setenv("SPIEL_PORT", sim_url("scene=model"))
    out = tmp_path / "out.ndjson"
    assert main(["run", "--frames", "3", "-o", str(out)]) == 0
    assert len(records(out)) == 3


def test_run_without_a_board_says_how_to_name_one(monkeypatch, capsys):
    monkeypatch.delenv("SPIEL_PORT", raising=False)
    monkeypatch.setattr(
        discover, "find_boards", lambda ids=discover.BOARD_USB_IDS, usb_backend=None: []
    )
    assert main(["run", "--frames", "1"]) == 2
    err = capsys.readouterr().err
    assert "no board found" in err and "--port sim://" in err


def test_run_rejects_a_profile_that_does_not_match_the_board(sim_url, tmp_path, capsys):
    profile = tmp_path / "three.toml"
    profile.write_text(
        'name = "three"\n[geometry]\nchannels_mm = [[0.0, 0.0, 0.0], [75.0, 0.0, 0.0], [0.0, 75.0, 0.0]]\n'
        '[associate]\nmethod = "geometric"\n'
    )
    assert main(["run", "--port", sim_url(), "--frames", "1", "--profile", str(profile)]) == 2
    assert "expects 3 x 64" in capsys.readouterr().err


def test_run_reports_bad_ports_and_backgrounds(sim_url, tmp_path, capsys):
    assert main(["run", "--port", sim_url("ber=5"), "--frames", "1"]) == 2
    assert "ber must be a probability" in capsys.readouterr().err
    bad = tmp_path / "bg.npy"
    np.save(bad, np.zeros(5))
    assert main(["run", "--port", sim_url(), "--frames", "1", "--background", str(bad)]) == 2
    assert "(channels, samples)" in capsys.readouterr().err


def test_run_with_a_fixed_background_file(sim_url, tmp_path):
    from spiel_edge.link.sim_options import SimOptions
    from spiel_edge.sim.scenes import build_scene

    port = sim_url("scene=model&targets=20,10,140")
    background = build_scene(SimOptions.from_url(port)).background(64)
    np.save(tmp_path / "bg.npy", background)
    out = tmp_path / "out.ndjson"
    assert (
        main(
            [
                "run",
                "--port",
                port,
                "--frames",
                "5",
                "--background",
                str(tmp_path / "bg.npy"),
                "-o",
                str(out),
            ]
        )
        == 0
    )
    for r in records(out):
        assert np.linalg.norm(np.subtract(r["position_mm"], [20, 10, 140])) < 10


def test_simulate_needs_a_transport(capsys):
    assert main(["simulate"]) == 2
    assert "--pty" in capsys.readouterr().err


def test_run_records_what_replay_reproduces(sim_url, tmp_path):
    out, again, rec = tmp_path / "out.ndjson", tmp_path / "again.ndjson", tmp_path / "run.mcap"
    port = sim_url("scene=model&seed=4")
    assert (
        main(
            [
                "run",
                "--port",
                port,
                "--frames",
                "12",
                "--rate",
                "300",
                "-o",
                str(out),
                "--record",
                str(rec),
            ]
        )
        == 0
    )
    # the echo model: run left the learned ToA correction out, and said so for replay
    assert recording_metadata(rec)["toa_correction"] == "none"
    assert main(["replay", str(rec), "-o", str(again)]) == 0
    live, replayed = records(out), records(again)
    assert len(replayed) == 12
    assert [r["position_mm"] for r in live] == [r["position_mm"] for r in replayed]
