"""doctor's checks with made-up environments, and the command's output and exit status."""

from __future__ import annotations

import json
import os
from pathlib import Path
from types import SimpleNamespace

import pytest

from spiel_edge.cli import main
from spiel_edge.cli.doctor import service_rejects
from spiel_edge.service import doctor
from spiel_edge.service.doctor import Check

IDS = ((0x1209, 0x0001),)


def test_board_found_or_not():
    board = SimpleNamespace(url="/dev/ttyACM0", vid=0x1209, pid=1, serial="A1")
    assert doctor.check_board([board], IDS).ok
    missing = doctor.check_board([], IDS)
    assert not missing.ok and "1209:0001" in missing.detail and missing.fix


def test_device_access_names_the_denied_node():
    allowed = {"/dev/ttyACM0"}
    check = doctor.check_device_access(
        ["/dev/ttyACM0", "/dev/ttyACM1"], access=lambda p, mode: p in allowed
    )
    assert not check.ok and "/dev/ttyACM1" in check.detail and "/dev/ttyACM0" not in check.detail
    assert "dialout" in check.fix
    assert doctor.check_device_access(["/dev/ttyACM0"], access=lambda p, mode: True).ok


def test_symlinks(tmp_path):
    assert not doctor.check_symlinks(tmp_path).ok
    (tmp_path / "ttyACM3").touch()
    (tmp_path / "spiel-0").symlink_to(tmp_path / "ttyACM3")
    good = doctor.check_symlinks(tmp_path)
    assert good.ok and "ttyACM3" in good.detail
    (tmp_path / "spiel-X").symlink_to(tmp_path / "gone")
    assert not doctor.check_symlinks(tmp_path).ok


def test_groups():
    assert doctor.check_groups("pi", {"pi", "dialout", "plugdev"}, set()).ok
    missing = doctor.check_groups("pi", {"pi"}, set())
    assert not missing.ok and "usermod -aG dialout,plugdev pi" in missing.fix
    stale = doctor.check_groups("pi", {"pi"}, {"dialout", "plugdev"})
    assert not stale.ok and "log out" in stale.fix
    assert doctor.check_groups("root", set(), set(), is_root=True).ok


def _proc(tmp_path, names):
    for pid, name in enumerate(names, start=1):
        (tmp_path / str(pid)).mkdir(parents=True)
        (tmp_path / str(pid) / "comm").write_text(name + "\n")
    return tmp_path


def test_modemmanager_scan_and_rule(tmp_path):
    assert doctor.modemmanager_running(_proc(tmp_path / "a", ["systemd", "ModemManager"]))
    assert not doctor.modemmanager_running(_proc(tmp_path / "b", ["systemd", "sshd"]))
    rules = tmp_path / "rules"
    rules.mkdir()
    assert doctor.installed_udev_rule(IDS, [rules]) is None
    (rules / "50-other.rules").write_text('ATTRS{idVendor}=="1209", ENV{ID_MM_DEVICE_IGNORE}="1"\n')
    rule = doctor.installed_udev_rule(IDS, [rules])
    assert rule == rules / "50-other.rules"
    assert doctor.check_modemmanager(True, rule).ok
    bad = doctor.check_modemmanager(True, None)
    assert not bad.ok and "ModemManager" in bad.fix
    assert doctor.check_modemmanager(False, None).ok


def test_config_from_env_file(tmp_path):
    assert doctor.check_config(config_dir=tmp_path).ok  # nothing installed: defaults
    calibration = tmp_path / "calibration.toml"
    calibration.write_text("[geometry]\ndelay_samples = [2.0, 2.0, 2.0, 2.0]\n")
    env = tmp_path / "spiel-edge.env"
    env.write_text(
        f'# comment\nSPIEL_RUN_OPTIONS="--profile spiel-icra23 --calibration {calibration}"\n'
    )
    good = doctor.check_config(config_dir=tmp_path)
    assert good.ok and str(calibration) in good.detail and str(env) in good.detail
    calibration.write_text("[geometry]\ndelay_samples = [2.0]\n")
    bad = doctor.check_config(config_dir=tmp_path)
    assert not bad.ok and "delay_samples" in bad.detail
    env.write_text("SPIEL_RUN_OPTIONS=--profile=no-such-profile\n")
    assert (
        "unknown profile"
        in doctor.check_config(config_dir=tmp_path, rejects=service_rejects).detail
    )


def test_explicit_profile_wins_over_env_file(tmp_path):
    (tmp_path / "spiel-edge.env").write_text("SPIEL_RUN_OPTIONS=--profile no-such-profile\n")
    assert doctor.check_config("spiel-icra23", None, tmp_path).ok


def test_model_missing_or_corrupt(tmp_path):
    check = doctor.check_model(tmp_path / "none.onnx")
    assert not check.ok and "geometric" in check.detail
    junk = tmp_path / "junk.onnx"
    junk.write_bytes(b"not a model")
    assert not doctor.check_model(junk).ok
    assert doctor.check_model(tmp_path / "none.onnx", method="geometric").ok


def test_numba_cache_dir(tmp_path):
    assert doctor.check_numba_cache_dir(tmp_path / "numba").ok
    assert not doctor.check_numba_cache_dir(None).ok
    if os.geteuid() != 0:  # root writes anywhere
        ro = tmp_path / "ro"
        ro.mkdir(mode=0o500)
        assert not doctor.check_numba_cache_dir(ro).ok


def test_numba_kernel_counts():
    def kernel(hits, misses):
        return SimpleNamespace(
            stats=SimpleNamespace(cache_hits={"sig": hits}, cache_misses={"sig": misses})
        )

    assert doctor.kernel_cache_counts([kernel(1, 0), kernel(2, 1)]) == (3, 1)
    warm = doctor.check_numba_kernels(lambda: 0.01, lambda: (9, 0))
    assert warm.ok and "9 kernel(s) loaded from the cache" in warm.detail
    cold = doctor.check_numba_kernels(lambda: 12.0, lambda: (0, 9))
    assert cold.ok and "compiled 9" in cold.detail

    def broken():
        raise TypeError("no matching definition")

    assert not doctor.check_numba_kernels(broken, lambda: (0, 0)).ok


def test_real_pipeline_dispatchers_are_found():
    kernels = doctor.pipeline_dispatchers()
    assert len(kernels) >= 5 and all(hasattr(k, "stats") for k in kernels)


@pytest.mark.parametrize("all_ok", [True, False])
def test_doctor_command_exit_status_and_json(monkeypatch, capsys, all_ok):
    checks = [
        Check("board", True, "found"),
        Check("model", all_ok, "x", None if all_ok else "do this"),
    ]
    monkeypatch.setattr("spiel_edge.cli.doctor.run_checks", lambda *a, **k: checks)
    assert main(["doctor", "--json"]) == (0 if all_ok else 1)
    report = json.loads(capsys.readouterr().out)
    assert report["ok"] is all_ok and [c["name"] for c in report["checks"]] == ["board", "model"]
    assert main(["doctor"]) == (0 if all_ok else 1)
    text = capsys.readouterr().out
    assert ("fix: do this" in text) is (not all_ok)


def test_run_checks_on_this_machine_returns_every_check(tmp_path):
    names = [c.name for c in doctor.run_checks(config_dir=tmp_path, skip_numba=True)]
    assert names == [
        "board",
        "device access",
        "stable names",
        "groups",
        "ModemManager",
        "config",
        "model",
        "unit",
    ]
    assert Path("/proc").is_dir()
