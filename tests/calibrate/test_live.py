"""Live guided calibration through a fake board session (a robot moves the target)."""

from __future__ import annotations

import dataclasses
from types import SimpleNamespace

import numpy as np
import pytest

from spiel_edge.calibrate.capture import capture_positions
from spiel_edge.cli import calibrate as cli_calibrate
from spiel_edge.cli import main
from spiel_edge.compat import tomllib
from spiel_edge.errors import DeviceError
from spiel_edge.profile.schema import dump_toml, profile_to_dict
from tests.calibrate.synth import nominal, perturbed_truth, render, target_grid

FS = 22000.0


class FakeSession:
    """Streams synthetic envelopes of a target wherever ``target`` is (None: empty scene)."""

    def __init__(self, truth, send_background: bool, seed: int = 0, n_samples: int = 64):
        self.truth, self.send_background, self.n_samples = truth, send_background, n_samples
        self.rng = np.random.default_rng(seed)
        self.target = None
        self.streams = 0
        self.asks: list[int] = []  # n_acquisitions of each STREAM_START
        self.closed = False

    def start_stream(self, *, rate_hz: float, n_samples: int, n_acquisitions: int = 0):
        assert n_samples == self.n_samples
        self.streams += 1
        self.asked = n_acquisitions  # a board sends exactly this many, then stops (0: endless)
        self.asks.append(n_acquisitions)

    def stop_stream(self):
        pass

    def close(self):
        self.closed = True

    def acquisitions(self, stop):
        sent = 0
        while not self.asked or sent < self.asked:
            sent += 1
            far = np.array([[0.0, 0.0, 5000.0]])  # beyond the frame: an empty scene
            p = far if self.target is None else np.asarray(self.target)[None]
            frames, bg = render(self.truth, p, FS, self.n_samples, self.rng, noise=4.0)
            yield SimpleNamespace(
                samples=frames[0], background=bg[0] if self.send_background else None
            )


@pytest.mark.parametrize("send_background", [True, False])
def test_capture_positions_follows_the_robot(send_background):
    truth = nominal().geometry
    session = FakeSession(truth, send_background)
    positions = np.array([[0.0, 0, 120], [40, -40, 180]])
    calls = []

    def robot(i, p):
        calls.append(i)
        session.target = p

    progressed = []
    frames, bgs, where = capture_positions(
        session, nominal(), positions, captures=3, before_position=robot, progress=progressed.append
    )
    assert frames.shape == bgs.shape == (6, 4, 64)
    assert np.array_equal(where, np.repeat(positions, 3, axis=0))
    assert calls == ([0, 1] if send_background else [-1, 0, 1])
    assert sum(progressed) == 6
    # each stream asks for exactly what it keeps: none is left in flight to slip into the next
    assert session.asks == ([1, 3, 3] if send_background else [1, 3, 3, 3])
    if not send_background:  # the background is the mean of the empty-scene captures
        assert np.all(bgs[:, :, 30:].std(axis=0) == 0) and abs(bgs[0, 0, 30:].mean() - 40.0) < 2.0


def test_wrong_sample_count_is_a_device_error():
    session = FakeSession(nominal().geometry, True, n_samples=64)
    profile = nominal()
    short = profile.replace(acquisition=dataclasses.replace(profile.acquisition, n_samples=32))
    session.n_samples = 32
    session.acquisitions = lambda stop: iter(
        [SimpleNamespace(samples=np.zeros((4, 64)), background=None)] * 5
    )
    with pytest.raises(DeviceError, match="shape"):
        capture_positions(
            session, short, np.zeros((1, 3)), captures=2, before_position=lambda i, p: None
        )


def test_cli_live_no_prompt_calibrates(tmp_path, monkeypatch):
    rng = np.random.default_rng(7)
    start = nominal()
    truth = perturbed_truth(start.geometry, rng)
    positions = target_grid(rng, 40)
    csv = tmp_path / "positions.csv"
    csv.write_text("x,y,z\n" + "\n".join(",".join(f"{v:g}" for v in p) for p in positions) + "\n")
    session = FakeSession(truth, send_background=True, seed=1)
    original_start = session.start_stream

    def robot_start(
        **kw,
    ):  # the robot is synchronised with the procedure: probe, then each position
        original_start(**kw)
        session.target = positions[session.streams - 2] if session.streams >= 2 else None

    session.start_stream = robot_start
    monkeypatch.setattr(cli_calibrate, "open_session", lambda port: session)
    out = tmp_path / "cal.toml"
    memg_toa = tmp_path / "memg-toa.toml"  # the fake board puts its delays at the MEMG mode
    data = profile_to_dict(start)
    data["echo_timing"]["estimator"] = "none"
    memg_toa.write_text(dump_toml(data))
    rc = main(
        [
            "calibrate",
            "--profile",
            str(memg_toa),
            "--port",
            "sim://",
            "--positions",
            str(csv),
            "--captures",
            "4",
            "--no-prompt",
            "-o",
            str(out),
        ]
    )
    assert rc == 0 and session.closed
    geometry = tomllib.loads(out.read_text())["geometry"]
    assert np.max(np.abs(np.array(geometry["channels_mm"]) - truth.channels_mm)) < 1.5
    assert np.max(np.abs(np.array(geometry["delay_samples"]) - truth.delays())) < 0.1
