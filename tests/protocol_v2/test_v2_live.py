"""Heartbeat, board logs and I/Q streams on the virtual board; a version-1 board with every
host command."""

from __future__ import annotations

import json
import logging
import threading
import time

import numpy as np

from spiel_edge.cli import main
from spiel_edge.device import DeviceSession
from spiel_edge.pipeline.factory import build_pipeline
from spiel_edge.profile.schema import load_profile
from spiel_edge.protocol import SampleFormat
from spiel_edge.sim.protocol_sim import device_for_url


def test_a_board_whose_heartbeat_stops_is_named_before_the_stream_timeout(sim_url, caplog):
    url = sim_url("stall_after=20&stall_ms=3000&serial=HB0042")
    stop = threading.Event()
    with caplog.at_level(logging.WARNING), DeviceSession(url) as dev:
        assert dev.stall_s == 2.0 and dev.telemetry.period_s == 0.5
        dev.start_stream(rate_hz=50)
        last = None
        for acq in dev.acquisitions(stop):
            if acq.index >= 19:
                last = time.monotonic()
            if dev.counters.disconnects:
                break
        named = time.monotonic() - last
    text = caplog.text
    assert "board HB0042" in text and "no heartbeat for" in text, text
    assert named < dev.stall_s, named  # before the stall check would even have asked


def test_a_log_flood_is_bounded_and_the_run_goes_on(sim_url, capfd, tmp_path):
    url = sim_url("log_flood=2000")
    out = tmp_path / "run.ndjson"
    assert main(["run", "--port", url, "--frames", "60", "-o", str(out)]) == 0
    err = capfd.readouterr().err
    shown = [line for line in err.splitlines() if "flood flood" in line]
    assert len(out.read_text().splitlines()) == 60
    summary = err.strip().splitlines()[-1]  # the run's summary names the counters
    received = int(summary.split("board_logs ")[1].split(",")[0])
    assert received > 1000, summary  # the board did flood
    assert 0 < len(shown) <= 40 + 20 * 5, len(shown)  # burst + 20/s over the run, at most
    assert all(len(line) < 400 for line in shown)


def test_unknown_heartbeat_flags_are_reported_once_and_the_run_goes_on(sim_url, capfd, tmp_path):
    url = sim_url("heartbeat_flags=0x80000100")
    out = tmp_path / "run.ndjson"
    assert main(["run", "--port", url, "--frames", "90", "-o", str(out)]) == 0
    assert capfd.readouterr().err.count("unknown error flags 0x80000100") == 1
    records = [json.loads(line) for line in out.read_text().splitlines()]
    assert len(records) == 90
    assert all("stamp_host" in r and r["stamp_uncertainty_us"] > 0 for r in records)


def stream(url: str, fmt: int, n: int) -> list:
    with DeviceSession(url) as dev:
        dev.start_stream(rate_hz=100, sample_format=fmt)
        out = []
        for acq in dev.acquisitions(threading.Event()):
            out.append(acq)
            if len(out) >= n:
                return out
    return out


def test_iq_positions_equal_envelope_positions_on_the_model_scene(sim_url):
    query = "scene=model&targets=30,-20,160&seed=5"
    env = stream(sim_url(query), SampleFormat.U16_ENVELOPE, 30)
    iq = stream(sim_url(query), SampleFormat.I16_IQ, 30)
    pipeline = build_pipeline(load_profile("spiel-icra23"), None, "none")
    diffs, fixes = [], 0
    for a, b in zip(env, iq, strict=True):
        assert a.index == b.index and b.phase is not None and b.phase.shape == a.samples.shape
        # the amplitude of the I/Q (rounded, as the CH101 computes it) is the envelope
        np.testing.assert_array_equal(b.samples, a.samples)
        ra = pipeline.process(a.samples.astype(np.float64), a.background.astype(np.float64))
        rb = pipeline.process(b.samples.astype(np.float64), b.background.astype(np.float64))
        if ra.position_mm is not None and rb.position_mm is not None:
            fixes += 1
            diffs.append(np.linalg.norm(np.asarray(ra.position_mm) - np.asarray(rb.position_mm)))
        else:
            assert ra.position_mm is None and rb.position_mm is None
    assert fixes >= 25 and max(diffs) < 0.1, (fixes, max(diffs))
    # the phase is the carrier's: it differs from channel to channel at the echo
    assert np.ptp(iq[0].phase) > 1.0


def test_iq_needs_protocol_2_and_the_model_scene(sim_url):
    from spiel_edge.errors import DeviceRequestError

    for query in ("protocol=1&scene=model", "scene=replay"):
        with DeviceSession(sim_url(query)) as dev:
            try:
                dev.start_stream(rate_hz=10, sample_format=SampleFormat.I16_IQ)
            except DeviceRequestError as exc:
                assert exc.code == 8  # UNSUPPORTED
            else:
                raise AssertionError(query)


def test_a_version_1_board_runs_configs_and_calibrates(sim_url, tmp_path, capsys):
    url = sim_url("protocol=1&scene=model&seed=3")
    out = tmp_path / "run.ndjson"
    assert main(["run", "--port", url, "--frames", "30", "-o", str(out)]) == 0
    records = [json.loads(line) for line in out.read_text().splitlines()]
    assert len(records) == 30 and not any("stamp_host" in r for r in records)
    assert sum(r["position_mm"] is not None for r in records) > 20
    cal = tmp_path / "cal.toml"
    cal.write_text("[geometry]\ndelay_samples = [2.0, 1.5, 1.9, 1.7]\n")
    assert main(["config", "push", "--port", url, "--name", "v1-board", str(cal)]) == 0
    assert main(["config", "commit", "--port", url]) == 0
    pulled = tmp_path / "board.toml"
    assert main(["config", "pull", "--port", url, str(pulled)]) == 0
    assert "v1-board" in pulled.read_text()
    board = device_for_url(url).board
    assert board.version == 1 and all(t < 0x30 for t in board.stats.executed)
    positions = tmp_path / "positions.csv"
    positions.write_text(
        "x,y,z\n0,0,150\n40,30,170\n-40,20,140\n30,-40,160\n-20,-30,180\n50,0,130\n"
    )
    from spiel_edge.calibrate import capture
    from spiel_edge.sim.protocol_sim import place_target

    original = capture.capture_positions

    def robot(session, profile, where, *, before_position, **kwargs):
        def step(i, p):
            before_position(i, p)
            place_target(url, p)

        return original(session, profile, where, before_position=step, **kwargs)

    capture.capture_positions = robot
    try:
        code = main(
            [
                "calibrate",
                "--port",
                url,
                "--positions",
                str(positions),
                "--captures",
                "2",
                "--no-prompt",
                "--force",  # the capture is under test, not whether its fit beats the profile
                "-o",
                str(tmp_path / "cal-out.toml"),
            ]
        )
    finally:
        capture.capture_positions = original
    assert code == 0 and (tmp_path / "cal-out.toml").exists()


def test_mcap_log_times_and_ros_stamps_are_the_synced_board_times(sim_url, tmp_path):
    from mcap.reader import make_reader

    url = sim_url("scene=model&drift_ppm=200&seed=6")
    out, rec = tmp_path / "run.ndjson", tmp_path / "run.mcap"
    assert main(["run", "--port", url, "--frames", "40", "-o", str(out), "--record", str(rec)]) == 0
    records = [json.loads(line) for line in out.read_text().splitlines()]
    stamps = {round(r["stamp_host"] * 1e9) for r in records}
    with rec.open("rb") as fh:
        positions = [
            (m.log_time, json.loads(m.data))
            for _, channel, m in make_reader(fh).iter_messages()
            if channel.topic == "/spiel/position"
        ]
    assert len(positions) == 40
    for log_time, record in positions:
        assert abs(log_time - record["stamp_host"] * 1e9) < 1000  # the record's own stamp
        assert round(record["stamp_host"] * 1e9) in stamps
