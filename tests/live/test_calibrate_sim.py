"""Live guided calibration end to end on the virtual board: the test plays the robot that moves
the target of the board's physical scene (``place_target``) before each position."""

from __future__ import annotations

import numpy as np
import pytest

from spiel_edge.calibrate import capture, predict_toa
from spiel_edge.cli import main
from spiel_edge.errors import ConfigError
from spiel_edge.profile.schema import apply_calibration, dump_toml, profile_to_dict
from spiel_edge.sim.protocol_sim import place_target
from tests.calibrate.synth import nominal, perturbed_truth, target_grid


def toa_rms(geometry, truth, positions) -> float:
    """RMS (samples) of the echo times ``geometry`` predicts against the true ones."""
    n = truth.n_channels
    flat, ch = np.repeat(positions, n, axis=0), np.tile(np.arange(n), len(positions))
    fs = nominal().acquisition.sample_rate_hz
    return float(
        np.sqrt(
            np.mean((predict_toa(geometry, flat, ch, fs) - predict_toa(truth, flat, ch, fs)) ** 2)
        )
    )


def test_live_calibration_on_the_virtual_board(sim_url, tmp_path, monkeypatch, capsys):
    rng = np.random.default_rng(1)
    start = nominal()
    truth = perturbed_truth(start.geometry, rng)
    (tmp_path / "truth.toml").write_text(
        dump_toml({**profile_to_dict(start.replace(geometry=truth)), "name": "truth"})
    )
    positions = target_grid(rng, 30)
    csv = tmp_path / "positions.csv"
    csv.write_text("x,y,z\n" + "\n".join(",".join(f"{v:g}" for v in p) for p in positions) + "\n")
    port = sim_url(f"scene=model&profile={tmp_path / 'truth.toml'}&seed=2")
    placed = []
    capture_positions = capture.capture_positions

    def with_robot(session, profile, where, *, before_position, **kwargs):
        def robot(i, p):
            before_position(i, p)  # the CLI's own step (prints the position with --no-prompt)
            place_target(port, p)
            placed.append(i)

        return capture_positions(session, profile, where, before_position=robot, **kwargs)

    monkeypatch.setattr(capture, "capture_positions", with_robot)
    out = tmp_path / "cal.toml"
    assert (
        main(
            [
                "calibrate",
                "--port",
                port,
                "--positions",
                str(csv),
                "--captures",
                "3",
                "--no-prompt",
                "-o",
                str(out),
            ]
        )
        == 0
    )
    assert placed == list(range(30))
    assert "Place the target at position 30/30" in capsys.readouterr().err
    calibrated = apply_calibration(start, out).geometry
    before, after = toa_rms(start.geometry, truth, positions), toa_rms(calibrated, truth, positions)
    assert after < 0.1 and after < before / 4, (before, after)
    assert abs(calibrated.speed_of_sound_m_s / truth.speed_of_sound_m_s - 1) < 0.005


def test_place_target_needs_the_model_scene(sim_url):
    with pytest.raises(ConfigError, match="scene=model"):
        place_target(sim_url(), [0, 0, 100])
    with pytest.raises(ConfigError, match="z > 0"):
        place_target(sim_url("scene=model"), [0, 0, -5])
