"""Bad geometry and config: degenerate layouts and absurd values are refused with the key the
user wrote, for profiles, calibrations and board configs; `config commit` with nothing staged;
the service kit never writes a broken or injected unit, and doctor agrees with `run`."""

from __future__ import annotations

import pytest

from spiel_edge.board_config import schema as bc
from spiel_edge.cli.doctor import service_rejects
from spiel_edge.errors import ConfigError
from spiel_edge.profile.schema import apply_calibration, load_profile, profile_to_dict
from spiel_edge.service.kit import render_unit

GOOD = [[0.0, 0.0, 0.0], [-37.5, -64.95, 0.0], [75.0, 0.0, 0.0], [-37.5, 64.95, 0.0]]

GEOMETRY = {
    "collinear": ({"channels_mm": [[0, 0, 0], [10, 0, 0], [20, 0, 0], [30, 0, 0]]}, "one line"),
    "coincident": (
        {"channels_mm": [[0, 0, 0], [10, 0, 0], [10, 0, 0], [0, 10, 0]]},
        "channels 1 and 2 coincide",
    ),
    "all-same": ({"channels_mm": [[5, 5, 5]] * 4}, "coincide"),
    "no-channels": ({"channels_mm": [], "delay_samples": []}, "channels_mm"),
    "facing-in-plane": ({"facing": [1.0, 0.0, 0.0]}, "geometry.facing"),
    "facing-zero": ({"facing": [0.0, 0.0, 0.0]}, "geometry.facing"),
    "delay-absurd": ({"delay_samples": [0, 0, 1e6, 0]}, "geometry.delay_samples"),
    "size-absurd": ({"channels_mm": [*GOOD[:3], [1e7, 0, 0]]}, "geometry.channels_mm"),
    "emitter-absurd": ({"emitter_mm": [0, 0, 1e9]}, "geometry.emitter_mm"),
    "nan": ({"channels_mm": [*GOOD[:3], ["nan", 0, 0]]}, "geometry.channels_mm"),
    "speed-zero": ({"speed_of_sound_m_s": 0}, "geometry.speed_of_sound_m_s"),
    "too-many": ({"channels_mm": [[i, i * i % 7, 0] for i in range(100)]}, "at most 64"),
}


def _toml_geometry(tmp_path, geometry: dict, kind: str):
    from spiel_edge.profile.schema import dump_toml

    data = profile_to_dict(load_profile("spiel-icra23"))
    if kind == "profile":
        data["geometry"].update(geometry)
        if "channels_mm" in geometry and "delay_samples" not in geometry:
            data["geometry"]["delay_samples"] = [0.0] * len(geometry["channels_mm"])
        if "channels_mm" in geometry:
            data["geometry"]["listening"] = [True] * len(geometry["channels_mm"])
        text = dump_toml(data)
    else:
        text = dump_toml({"geometry": geometry})
    text = text.replace("'nan'", "nan").replace('"nan"', "nan")
    path = tmp_path / f"{kind}.toml"
    path.write_text(text)
    return path


@pytest.mark.parametrize("case", sorted(GEOMETRY))
def test_bad_geometry_in_a_profile_names_the_key(tmp_path, case):
    geometry, needle = GEOMETRY[case]
    path = _toml_geometry(tmp_path, geometry, "profile")
    with pytest.raises(ConfigError, match=needle.replace("(", r"\(")) as caught:
        load_profile(path)
    assert str(path) in str(caught.value)


@pytest.mark.parametrize(
    "case", ["collinear", "coincident", "facing-in-plane", "delay-absurd", "size-absurd"]
)
def test_bad_geometry_in_a_calibration_names_the_calibration(tmp_path, case):
    geometry, needle = GEOMETRY[case]
    path = _toml_geometry(tmp_path, geometry, "calibration")
    with pytest.raises(ConfigError, match=needle) as caught:
        apply_calibration(load_profile("spiel-icra23"), path)
    assert str(path) in str(caught.value)


@pytest.mark.parametrize("case", ["collinear", "coincident", "delay-absurd"])
def test_bad_geometry_in_a_board_config(case):
    geometry, needle = GEOMETRY[case]
    config = bc.from_profile(load_profile("spiel-icra23"), "b")
    config["geometry"].update(geometry)
    with pytest.raises(ConfigError, match=needle):
        bc.validate(config)


def test_the_cli_reports_bad_geometry_in_one_line(cli, tmp_path, csv_folder):
    path = _toml_geometry(tmp_path, GEOMETRY["collinear"][0], "profile")
    ran = cli("replay", csv_folder[0], "--profile", path, "-o", tmp_path / "o.ndjson")
    assert ran.status == 2 and "geometry.channels_mm" in ran.err and ran.err.count("\n") == 1


class _NothingStaged:
    def config_status(self):
        from types import SimpleNamespace

        return SimpleNamespace(staged_length=0)


def test_commit_with_nothing_staged_is_a_clear_error():
    from spiel_edge.board_config.flash import commit

    with pytest.raises(ConfigError, match="nothing is staged"):
        commit(_NothingStaged())


EXEC_PATHS = {
    "space": ("/opt/my tools/spiel-edge", 'ExecStart="/opt/my tools/spiel-edge" '),
    "percent": ("/opt/100%/spiel-edge", "ExecStart=/opt/100%%/spiel-edge "),
    "dollar": ("/opt/$HOME/spiel-edge", "ExecStart=/opt/$$HOME/spiel-edge "),
    "quote": ('/opt/a"b/spiel-edge', 'ExecStart="/opt/a\\"b/spiel-edge" '),
}


@pytest.mark.parametrize("case", sorted(EXEC_PATHS))
def test_exec_paths_are_escaped_per_systemd(case):
    path, expected = EXEC_PATHS[case]
    unit = render_unit(path)
    lines = [line for line in unit.splitlines() if line.startswith("ExecStart=")]
    assert len(lines) == 1 and lines[0].startswith(expected), lines


@pytest.mark.parametrize(
    "path",
    ["/opt/x\nExecStartPre=/bin/rm -rf /", "/opt/x\rY", "relative/spiel-edge", "/opt/\x00x"],
    ids=["newline-injection", "carriage-return", "relative", "nul"],
)
def test_exec_paths_that_cannot_be_quoted_are_refused(cli, tmp_path, path):
    with pytest.raises(ConfigError):
        render_unit(path)
    ran = cli("service", "install", "--prefix", tmp_path, "--exec", path)
    assert ran.status == 2 and not (tmp_path / "etc").exists()


@pytest.mark.parametrize(
    ("options", "port"),
    [
        ("--rate 1e9 --output /dev/null", "/dev/spiel-0"),
        ("--frames 0", "/dev/spiel-0"),
        ("--udp 127.0.0.1:99999", "/dev/spiel-0"),
        ("--foxglove nope", "/dev/spiel-0"),
        ("--no-such-option", "/dev/spiel-0"),
        ("--profile 'unterminated", "/dev/spiel-0"),
        ("--output /dev/null", "gopher://board"),
        ("--help", "/dev/spiel-0"),
        ("--slot virtual-4:nose", "/dev/spiel-0"),
        ("--slot no-such-robot.toml:front", "/dev/spiel-0"),
        ("--realtime 0", "/dev/spiel-0"),
    ],
)
def test_doctor_refuses_what_the_service_would(options, port):
    assert service_rejects({"SPIEL_RUN_OPTIONS": options, "SPIEL_PORT": port}) is not None


def test_doctor_accepts_the_shipped_settings():
    from spiel_edge.service.doctor import read_env_file  # noqa: F401 - same parser as doctor

    ok = "--profile spiel-icra23 --output /dev/null --udp 127.0.0.1:9870"
    assert service_rejects({"SPIEL_RUN_OPTIONS": ok, "SPIEL_PORT": "/dev/spiel-0"}) is None
    ok += " --realtime 10 --slot virtual-4:left"
    assert service_rejects({"SPIEL_RUN_OPTIONS": ok, "SPIEL_PORT": "/dev/spiel-0"}) is None
