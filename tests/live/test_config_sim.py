"""``spiel-edge config`` and ``run`` against the virtual board: its two-slot flash, power cuts
at every flash operation of a commit, diff, the progress bar, and the board's geometry in run."""

from __future__ import annotations

import dataclasses
import json
import time

import numpy as np
import pytest
from crc32c import crc32c
from mcap.reader import make_reader

from spiel_edge.board_config import schema as bc
from spiel_edge.cli import main
from spiel_edge.compat import tomllib
from spiel_edge.device import DeviceSession
from spiel_edge.profile.schema import dump_toml, load_profile, profile_to_dict
from spiel_edge.sim.protocol_sim import device_for_url

UNPLUG_MS = 10  # how long a power cut keeps the virtual board away


def board_file(path, name: str, gain_db: float = 20.0, source_len: int = 0):
    """A full board config; a long calibration source makes it span several transfer chunks."""
    config = bc.from_profile(load_profile(), name, gain_db=gain_db)
    if source_len:
        config["calibration"] = {"source": "x" * source_len, "residual_samples": 0.4}
    path.write_text(bc.to_toml(bc.validate(config)))
    return path


def pulled(port: str, capsys) -> dict:
    capsys.readouterr()
    assert main(["config", "pull", "--port", port]) == 0
    return tomllib.loads(capsys.readouterr().out)


def test_push_commit_pull_show_round_trip(sim_url, tmp_path, capsys, monkeypatch):
    port = sim_url("scene=model")
    assert main(["config", "pull", "--port", port]) == 2
    assert "holds no config" in capsys.readouterr().err
    cal = tmp_path / "cal.toml"
    cal.write_text(
        "[geometry]\nchannels_mm = [[0,0,0],[-37,-65,0],[75,0,0],[-37,65,0]]\n"
        "delay_samples = [2.0, 1.5, 1.9, 1.7]\n"
    )
    assert main(["config", "push", "--port", port, "--name", "proto-7", str(cal)]) == 0
    out = capsys.readouterr()
    assert out.out == "" and "+ board.name = 'proto-7'" in out.err and "staged" in out.err
    assert device_for_url(port).board.flash.active() is None  # staged only
    assert main(["config", "commit", "--port", port]) == 0
    config = pulled(port, capsys)
    assert config["board"]["name"] == "proto-7" and config["geometry"]["delay_samples"] == [
        2.0,
        1.5,
        1.9,
        1.7,
    ]
    # "-" is stdout, as for every other output of the tool: no file named "-"
    monkeypatch.chdir(tmp_path)
    capsys.readouterr()
    assert main(["config", "pull", "--port", port, "-"]) == 0
    assert tomllib.loads(capsys.readouterr().out) == config and not (tmp_path / "-").exists()
    assert bc.validate(config) == config
    assert (
        main(
            [
                "config",
                "push",
                "--port",
                port,
                "--commit",
                str(board_file(tmp_path / "b.toml", "proto-8")),
            ]
        )
        == 0
    )
    capsys.readouterr()
    assert main(["config", "show", "--port", port]) == 0
    shown = capsys.readouterr().out
    assert (
        "# active slot: 1" in shown
        and "slot 0: generation 1" in shown
        and "slot 1: generation 2" in shown
    )
    assert 'name = "proto-8"' in shown


def test_diff_against_the_board(sim_url, tmp_path, capsys):
    port = sim_url("scene=model")
    old = board_file(tmp_path / "old.toml", "old")
    assert main(["config", "diff", "--port", port, str(old)]) == 0
    assert "+ board.name = 'old'" in capsys.readouterr().out  # nothing stored: everything is new
    assert main(["config", "push", "--port", port, "--commit", str(old)]) == 0
    capsys.readouterr()
    assert main(["config", "diff", "--port", port, str(old)]) == 0
    assert capsys.readouterr().out == "no changes\n"
    assert (
        main(
            [
                "config",
                "diff",
                "--port",
                port,
                str(board_file(tmp_path / "new.toml", "new", gain_db=30)),
            ]
        )
        == 0
    )
    assert capsys.readouterr().out.splitlines() == [
        "~ acquisition.gain_db: 20.0 -> 30.0",
        "~ board.name: 'old' -> 'new'",
    ]
    partial = tmp_path / "cal.toml"
    partial.write_text("[geometry]\nspeed_of_sound_m_s = 340\n")
    assert main(["config", "diff", "--port", port, str(partial)]) == 0
    assert capsys.readouterr().out == "~ geometry.speed_of_sound_m_s: 343.0 -> 340.0\n"


def test_progress_bar_keeps_non_tty_output_clean(sim_url, tmp_path, capsys):
    port = sim_url("scene=model")
    big = board_file(tmp_path / "big.toml", "big", source_len=2500)
    size = len(bc.encode(bc.validate(tomllib.loads(big.read_text()))))
    assert size > 2 * 1024  # three CONFIG_WRITE chunks
    assert main(["config", "push", "--port", port, "--commit", str(big)]) == 0
    out = capsys.readouterr()
    assert out.out == ""
    assert "\r" not in out.err and "\x1b" not in out.err and out.err.count("writing") == 1
    assert f"staged {size} bytes" in out.err
    assert main(["config", "pull", "--port", port]) == 0
    text = capsys.readouterr().out
    assert tomllib.loads(text) == tomllib.loads(big.read_text())  # stdout is the TOML alone


def commit_ops(tmp_path, sim_url, old, new) -> tuple[int, int]:
    """Flash operations of the first commit (``old``) and of the next one (``new``)."""
    port = sim_url("scene=model")
    flash = device_for_url(port).board.flash
    assert main(["config", "push", "--port", port, "--commit", str(old)]) == 0
    first = flash.ops
    assert main(["config", "push", "--port", port, "--commit", str(new)]) == 0
    return first, flash.ops - first


def test_power_cut_at_every_flash_operation_of_a_commit_keeps_the_old_config(
    sim_url, tmp_path, capsys
):
    old = board_file(tmp_path / "old.toml", "old")
    new = board_file(tmp_path / "new.toml", "new", gain_db=30, source_len=1500)
    first, n_ops = commit_ops(tmp_path, sim_url, old, new)
    assert n_ops >= 2 + 7  # erase, the data pages, the header
    for k in range(n_ops):
        port = sim_url(f"scene=model&unplug_ms={UNPLUG_MS}&power_cut={first + k}")
        assert main(["config", "push", "--port", port, "--commit", str(old)]) == 0
        assert main(["config", "push", "--port", port, str(new)]) == 0
        capsys.readouterr()
        assert main(["config", "commit", "--port", port]) == 2, f"cut at operation {k}"
        assert "keeps the previous config active" in capsys.readouterr().err
        assert device_for_url(port).power_cuts == 1
        time.sleep(2 * UNPLUG_MS / 1000)  # the board comes back
        assert pulled(port, capsys)["board"]["name"] == "old", f"cut at operation {k}"
        with DeviceSession(port, reconnect=False) as session:
            assert session.config_status().staged_length == 0  # the staging was in RAM
            session.start_stream(rate_hz=200)  # and the board still streams
            assert next(session.acquisitions()).samples.shape == (4, 64)
    assert (
        main(["config", "push", "--port", port, "--commit", str(new)]) == 0
    )  # a new attempt works
    assert pulled(port, capsys)["board"]["name"] == "new"


# --- run with the board's geometry ---------------------------------------------------------


@pytest.fixture(scope="module")
def geometries(tmp_path_factory):
    """A profile whose geometry is far from the built-in one (the sim's truth), a calibration
    file of that geometry (for the board) and one of the built-in geometry."""
    root = tmp_path_factory.mktemp("geom")
    base = load_profile()
    g = base.geometry
    moved = g.channels_mm.copy()
    moved[1:] += [[6.0, -6.0, 0.0], [-8.0, 0.0, 0.0], [6.0, 6.0, 0.0]]
    truth = dataclasses.replace(
        g, channels_mm=moved, delay_samples=g.delays() + [1.5, -1.0, 1.2, -1.3]
    )
    data = profile_to_dict(base.replace(geometry=truth))
    (root / "truth.toml").write_text(dump_toml({**data, "name": "truth"}))
    (root / "board.toml").write_text(dump_toml({"geometry": data["geometry"]}))
    (root / "nominal.toml").write_text(dump_toml({"geometry": profile_to_dict(base)["geometry"]}))
    return root


def median_error(port: str, out, *args: str, verbose: bool = False) -> float:
    argv = [
        "run",
        "--port",
        port,
        "--frames",
        "10",
        "--rate",
        "500",
        "-o",
        str(out),
        "--force",
        *args,
    ]
    argv += ["--toa-correction", "none"]  # the correction fits the recorded board, not the model
    assert main(["-v", *argv] if verbose else argv) == 0
    recs = [json.loads(line) for line in out.read_text().splitlines()]
    assert len(recs) == 10
    return float(
        np.median(
            [
                np.linalg.norm(np.subtract(r["position_mm"], r["truth_mm"]))
                for r in recs
                if r["position_mm"]
            ]
        )
    )


def test_run_uses_the_geometry_stored_on_the_board(sim_url, tmp_path, geometries, capsys):
    port = sim_url(f"scene=model&profile={geometries / 'truth.toml'}&targets=30,-20,150&seed=1")
    out = tmp_path / "out.ndjson"
    without = median_error(port, out, verbose=True)
    assert "holds no config; using profile 'spiel-icra23'" in capsys.readouterr().err
    assert main(["config", "push", "--port", port, "--commit", str(geometries / "board.toml")]) == 0
    capsys.readouterr()
    rec = tmp_path / "run.mcap"
    assert (
        median_error(port, out, "--record", str(rec), verbose=True) < 8
    )  # the board's geometry is the scene's
    assert "geometry from board 'spiel-board'" in capsys.readouterr().err
    with rec.open("rb") as f:
        [meta] = [m.metadata for m in make_reader(f).iter_metadata() if m.name == "spiel-edge"]
    assert meta["geometry"] == "board 'spiel-board'"
    assert without > 25 and median_error(port, out, "--no-board-config") > 25
    calibrated = median_error(
        port, out, "--calibration", str(geometries / "nominal.toml"), verbose=True
    )
    assert calibrated > 25  # --calibration wins over the board
    assert "geometry from calibration" in capsys.readouterr().err


def test_run_with_an_unusable_board_config_warns_and_uses_the_profile(sim_url, tmp_path, capsys):
    port = sim_url("scene=model&targets=20,10,140")
    junk = b"not a spiel-edge config"
    with DeviceSession(port, reconnect=False) as session:
        session.write_config(junk)
        session.commit_config(crc32c(junk))
    assert median_error(port, tmp_path / "out.ndjson") < 8
    assert (
        "the board's config is not usable, using profile 'spiel-icra23'" in capsys.readouterr().err
    )
