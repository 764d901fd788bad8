"""``spiel-edge calibrate`` offline on a spiel-csv folder written from the vendored subset."""

from __future__ import annotations

import json

import numpy as np
import pytest

from spiel_edge.calibrate import read_positions
from spiel_edge.cli import main
from spiel_edge.compat import tomllib
from spiel_edge.data import load_subset
from spiel_edge.errors import InputError
from spiel_edge.profile.schema import apply_calibration, load_profile


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    data = load_subset()
    root = tmp_path_factory.mktemp("rec")
    (root / "fr").mkdir()
    (root / "bg").mkdir()
    for i in range(0, len(data), 2):
        name = data.names[i]
        np.savetxt(root / "fr" / name, data.frames[i], fmt="%d")
        np.savetxt(root / "bg" / name, data.backgrounds[i], fmt="%d")
        labels = np.column_stack(
            [np.arange(4), -np.ones(4), -np.ones(4), np.tile(data.truth_mm[i], (4, 1))]
        )
        np.savetxt(root / "fr" / name.replace("_frames.csv", "_labels.csv"), labels)
    return root


def test_offline_writes_a_calibration_that_replay_accepts(folder, tmp_path, capsys):
    out = tmp_path / "cal.toml"
    rc = main(
        [
            "calibrate",
            "--recordings",
            str(folder / "fr"),
            "--background",
            str(folder / "bg"),
            "--exclude-z",
            "90",
            "--fix",
            "speed",
            "--force",  # worse than the tuned profile on unseen positions: written anyway
            "-o",
            str(out),
        ]
    )
    assert rc == 0
    text = out.read_text()
    data = tomllib.loads(text)
    assert set(data) == {"geometry"}
    assert "+-1 sigma" in text and "residuals per channel" in text
    assert data["geometry"]["speed_of_sound_m_s"] == load_profile().geometry.speed_of_sound_m_s
    profile = apply_calibration(load_profile(), out)
    assert np.allclose(profile.geometry.channels_mm, data["geometry"]["channels_mm"])
    capsys.readouterr()
    rc = main(
        [
            "replay",
            str(folder / "fr"),
            "--background",
            str(folder / "bg"),
            "--calibration",
            str(out),
            "--association",
            "geometric",
        ]
    )
    assert rc == 0
    records = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    assert sum(r["position_mm"] is not None for r in records) > 0.9 * len(records)


def test_plot_is_written(folder, tmp_path):
    pytest.importorskip("matplotlib")
    png = tmp_path / "cal.png"
    assert (
        main(
            [
                "calibrate",
                "--recordings",
                str(folder / "fr"),
                "--background",
                str(folder / "bg"),
                "--exclude-z",
                "90",
                "--plot",
                str(png),
            ]
        )
        == 0
    )
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_needs_exactly_one_source(folder, tmp_path, capsys):
    assert main(["calibrate"]) == 2
    assert "--recordings" in capsys.readouterr().err
    positions = tmp_path / "p.csv"
    positions.write_text("0,0,100\n")
    both = ["--positions", str(positions), "--recordings", str(folder / "fr")]
    assert main(["calibrate", "--port", "sim://", *both]) == 2
    assert main(["calibrate", "--port", "sim://"]) == 2  # live needs the target positions
    assert "--positions" in capsys.readouterr().err


def test_read_positions(tmp_path):
    path = tmp_path / "p.csv"
    path.write_text("# jig\nx,y,z\n0, 0, 100\n40,-40,180\n")
    assert np.array_equal(read_positions(path), [[0, 0, 100], [40, -40, 180]])
    path.write_text("0,0,100\n1,2\n")
    with pytest.raises(InputError, match=":2: expected 3"):
        read_positions(path)
    path.write_text("x,y,z\n")
    with pytest.raises(InputError, match="no positions"):
        read_positions(path)
