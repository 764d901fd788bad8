from types import SimpleNamespace

import numpy as np
import pytest

from spiel_edge.cli import main
from spiel_edge.errors import InputError
from spiel_edge.runtime.background_capture import median_background, save_background
from spiel_edge.runtime.loop import load_background


def test_median_ignores_a_passing_reflection(rng):
    scene = rng.uniform(0, 500, (4, 64))
    frames = [scene + rng.normal(0, 2, scene.shape) for _ in range(9)]
    frames[3] = frames[3] + 4000  # something passed through once
    got = median_background((SimpleNamespace(samples=f) for f in frames), 9)
    assert np.abs(got - scene).max() < 6


def test_capture_errors():
    with pytest.raises(InputError, match="stopped after 2 of 5"):
        median_background([SimpleNamespace(samples=np.zeros((4, 64)))] * 2, 5)
    with pytest.raises(InputError, match="shape changed"):
        median_background(
            [
                SimpleNamespace(samples=np.zeros((4, 64))),
                SimpleNamespace(samples=np.zeros((4, 32))),
            ],
            2,
        )


@pytest.mark.parametrize("suffix", [".npy", "_frames.csv"])
def test_saved_background_loads_for_run(tmp_path, rng, suffix):
    bg = np.round(rng.uniform(0, 900, (4, 64)), 1)
    path = save_background(tmp_path / f"bg{suffix}", bg)
    np.testing.assert_allclose(load_background(path), bg)


def test_background_command_on_the_virtual_board(tmp_path):
    out = tmp_path / "bg.npy"
    assert (
        main(
            [
                "background",
                "--port",
                "sim://bgtest?scene=model",
                "--frames",
                "5",
                "--rate",
                "500",
                "-o",
                str(out),
            ]
        )
        == 0
    )
    bg = np.load(out)
    assert bg.shape == (4, 64) and np.all(np.isfinite(bg)) and bg.max() > 0
