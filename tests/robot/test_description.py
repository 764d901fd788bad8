"""The robot file: the built-in virtual robot loads; every bad input is one ConfigError line."""

from __future__ import annotations

import numpy as np
import pytest

from spiel_edge.errors import ConfigError
from spiel_edge.robot.description import load_robot, rotation_from_rpy_deg


def test_virtual_robot_boards_face_out_90_degrees_apart():
    robot = load_robot("virtual-4")
    facing = {b.name: b.mount.facing for b in robot.boards}
    np.testing.assert_allclose(facing["front"], [1, 0, 0], atol=1e-12)
    np.testing.assert_allclose(facing["left"], [0, 1, 0], atol=1e-12)
    np.testing.assert_allclose(facing["back"], [-1, 0, 0], atol=1e-12)
    np.testing.assert_allclose(facing["right"], [0, -1, 0], atol=1e-12)
    for b in robot.boards:  # the board sits on the robot's rim, 0.1 m out, facing out
        np.testing.assert_allclose(b.mount.translation_mm, 100.0 * b.mount.facing, atol=1e-9)
        assert (b.field_of_view_deg, b.detection_deg) == (65.0, 55.0)
    spec = robot.track_spec()  # the fused tracker: constant velocity alone
    assert spec.imm_switch_probability == spec.imm_static_share == 0.0


def test_mount_round_trip_and_covariance_rotation():
    robot = load_robot("virtual-4")
    m = robot.board("left").mount
    p = np.array([10.0, -20.0, 200.0])
    np.testing.assert_allclose(m.to_board(m.to_base(p)), p, atol=1e-9)
    # 200 mm in front of the left board: 200 mm further along +y from its position
    np.testing.assert_allclose(m.to_base([0, 0, 200.0]), [0, 300.0, 0], atol=1e-9)
    c = np.diag([1.0, 4.0, 9.0])
    rc = m.covariance_to_base(c)
    samples = np.random.default_rng(0).multivariate_normal(np.zeros(3), c, 200000)
    np.testing.assert_allclose(np.cov((samples @ m.rotation.T).T), rc, atol=0.1)


def test_rpy_matches_tf2_convention():
    # yaw 90: x -> y; pitch 90: z -> x (fixed axes, X then Y then Z)
    np.testing.assert_allclose(rotation_from_rpy_deg([0, 0, 90]) @ [1, 0, 0], [0, 1, 0], atol=1e-12)
    np.testing.assert_allclose(rotation_from_rpy_deg([0, 90, 0]) @ [0, 0, 1], [1, 0, 0], atol=1e-12)


def _one_line(exc: pytest.ExceptionInfo) -> str:
    text = str(exc.value)
    assert "\n" not in text
    return text


def test_two_boards_on_one_port(write_robot):
    path = write_robot(
        [{"name": "a", "port": "/dev/ttyACM0"}, {"name": "b", "port": "serial:///dev/ttyACM0"}]
    )
    with pytest.raises(ConfigError) as exc:
        load_robot(path)
    assert "'a' and 'b' are both on port" in _one_line(exc)


def test_a_transform_that_is_not_a_rotation(write_robot):
    skew = "rotation_matrix = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.3], [0.0, 0.0, 1.0]]"
    mirror = "rotation_matrix = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, -1.0]]"
    quat = "rotation_xyzw = [0.0, 0.0, 0.5, 0.5]"
    for rotation, words in ((skew, "not a rotation"), (mirror, "reflection"), (quat, "norm")):
        path = write_robot([{"name": "a", "rotation": rotation}])
        with pytest.raises(ConfigError) as exc:
            load_robot(path)
        text = _one_line(exc)
        assert "board 'a'" in text and words in text


def test_a_rotation_matrix_that_is_one_is_taken(write_robot):
    rot = "rotation_matrix = [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]"
    robot = load_robot(write_robot([{"name": "a", "rotation": rot}]))
    np.testing.assert_allclose(robot.boards[0].mount.rotation @ [1, 0, 0], [0, 1, 0], atol=1e-12)


def test_overlapping_trigger_slots(write_robot):
    boards = [
        {"name": "a", "slot": "slot_ms = 0.0"},
        {"name": "b", "port": "sim://b", "slot": "slot_ms = 3.0"},
    ]
    with pytest.raises(ConfigError) as exc:
        load_robot(write_robot(boards))
    assert "slots of boards 'a' (0.00 ms) and 'b' (3.00 ms) overlap" in _one_line(exc)
    same = [{"name": "a", "slot": "slot = 1"}, {"name": "b", "port": "sim://b", "slot": "slot = 1"}]
    with pytest.raises(ConfigError, match="overlap"):
        load_robot(write_robot(same))


def test_a_period_too_short_for_the_boards(write_robot):
    boards = [{"name": n, "port": f"sim://{n}"} for n in "abcde"]
    with pytest.raises(ConfigError) as exc:
        load_robot(write_robot(boards))
    assert "too short for 5 boards" in _one_line(exc)


_A = '[[board]]\nname = "a"\n'


@pytest.mark.parametrize(
    ("text", "words"),
    [
        ("[robot]\n", "at least one [[board]]"),
        ('[[board]]\nname = "a"\ncolour = "red"\n', "unknown key"),
        ('[[board]]\nname = "a"\ntranslation_m = [0, 0]\n', "translation_m must be 3 numbers"),
        ('[[board]]\nname = "a"\n[[board]]\nname = "a"\n', "two boards are named 'a'"),
        ('[[board]]\nname = "a"\n[trigger]\nmax_range_m = -1\n', "max_range_m must be in"),
        ("[[board]\n", "not valid TOML"),
        ('[[board]]\nname = "a"\ndetection_deg = 120\n', "detection_deg must be in"),
        ('[[board]]\nname = "a"\n[track]\nmax_misses = inf\n', "track.max_misses must be a finite"),
        ('[[board]]\nname = "a"\n[track]\ngate_chi2 = nan\n', "track.gate_chi2 must be a finite"),
        ('[[board]]\nname = "a"\nkey = "robot/*"\n', "holds a wildcard"),
        ('[[board]]\nname = "a"\nkey = "robot/**"\n', "holds a wildcard"),
        ('[[board]]\nname = "a"\nkey = "robot//a"\n', "empty chunk"),
        ('[[board]]\nname = "a"\nkey = "a b"\n', "white space"),
        ('[[board]]\nname = "a"\nprofile = ""\n', "profile is empty"),
        ('[robot]\nname = {a = 1}\n[[board]]\nname = "a"\n', "name must be a non-empty string"),
        ("[robot]\n[wheels]\n" + _A, "unknown section(s) ['wheels']"),
        (_A + "[trigger]\nperiod = 25.0\n", "[trigger]: unknown key(s) ['period']"),
        (_A + "[trigger]\nperiod_ms = true\n", "trigger.period_ms must be a number"),
        ('[robot]\nframe_id = "base link"\n' + _A, "robot.frame_id must be letters"),
        (_A + "rotation_rpy_deg = [0, 90, 0]\nrotation_xyzw = [0, 0, 0, 1]\n", "give one of"),
        (_A + "slot = 0\nslot_ms = 0.0\n", "give slot or slot_ms, not both"),
        (_A + "slot = true\n", "slot must be an integer in [0, 15]"),
        (_A + "slot = 16\n", "slot must be an integer in [0, 15]"),
        (_A + "field_of_view_deg = 120\n", "field_of_view_deg must be in [5, 90]"),
        (_A + "translation_m = [150.0, 0, 0]\n", "translation_m must be in [-100, 100]"),
        (_A + "[track]\nmax_misses = 2.5\n", "track.max_misses must be an integer"),
        (_A + 'key = "k"\n[[board]]\nname = "b"\nkey = "k"\n', "both publish on key 'k'"),
        (_A + 'port = "sim://x"\n[[board]]\nname = "b"\nkey = "robot/a"\n', "both publish on key"),
        (
            "".join(f'[[board]]\nname = "b{i}"\nport = "sim://b{i}"\n' for i in range(17)),
            "at most 16",
        ),
    ],
)
def test_other_bad_files(tmp_path, text, words):
    path = tmp_path / "r.toml"
    path.write_text(text)
    with pytest.raises(ConfigError) as exc:
        load_robot(path)
    assert words in _one_line(exc)


def test_a_folder_or_a_missing_file_is_named_so(tmp_path):
    with pytest.raises(ConfigError, match="a folder"):
        load_robot(tmp_path)
    with pytest.raises(ConfigError, match="no such robot file"):
        load_robot(tmp_path / "none.toml")


def test_cli_refuses_a_bad_robot_file_in_one_line(write_robot, capsys):
    from spiel_edge.cli import main

    path = write_robot(
        [{"name": "a", "port": "/dev/ttyACM0"}, {"name": "b", "port": "/dev/ttyACM0"}]
    )
    assert main(["run", "--robot", str(path)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "both on port" in err and "Traceback" not in err


# --- more of the file's checks and defaults (mutation-testing round) ---------------------------


def test_rotations_within_the_tolerance_are_made_exact(write_robot):
    # rounded digits (1e-4): taken, and made an exact rotation
    rounded = "rotation_matrix = [[0.0001, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]"
    quat = "rotation_xyzw = [0.0, 0.0, 0.7075, 0.7071]"  # norm 1.0003
    for rotation in (rounded, quat):
        r = load_robot(write_robot([{"name": "a", "rotation": rotation}])).boards[0].mount.rotation
        np.testing.assert_allclose(r.T @ r, np.eye(3), atol=1e-12)
        assert np.linalg.det(r) == pytest.approx(1.0, abs=1e-12)
        np.testing.assert_allclose(r @ [1, 0, 0], [0, 1, 0], atol=1e-3)
    # 1 % off is not rounding: refused (the tolerance is 1e-3)
    skew = "rotation_matrix = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.01], [0.0, 0.0, 1.0]]"
    long = "rotation_xyzw = [0.0, 0.0, 0.0, 1.01]"
    for rotation, words in ((skew, "not a rotation"), (long, "norm 1.01")):
        with pytest.raises(ConfigError) as exc:
            load_robot(write_robot([{"name": "a", "rotation": rotation}]))
        assert words in _one_line(exc)


def test_board_defaults(write_robot):
    """Without slot the boards take slots 0, 1, ... in file order; the key is robot/<name>;
    detection_deg 55 and field_of_view_deg 90 (docs/robot.md)."""
    robot = load_robot(write_robot([{"name": "a"}, {"name": "b"}]))
    assert [(b.slot, b.slot_ms) for b in robot.boards] == [(0, None), (1, None)]
    assert [b.key for b in robot.boards] == ["robot/a", "robot/b"]
    assert {(b.detection_deg, b.field_of_view_deg) for b in robot.boards} == {(55.0, 90.0)}
    with pytest.raises(ConfigError, match="no board named 'c'"):
        robot.board("c")


def test_a_robot_file_too_large_is_refused_before_it_is_read(tmp_path):
    path = tmp_path / "r.toml"
    path.write_text('[[board]]\nname = "a"\n' + "#" * (256 * 1024))
    with pytest.raises(ConfigError) as exc:
        load_robot(path)
    assert "at most 262144 bytes" in _one_line(exc)
