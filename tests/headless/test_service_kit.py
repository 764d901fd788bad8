"""The service kit: packaging/ copies, install and dry run, systemd-analyze verify."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest

from spiel_edge.cli import main
from spiel_edge.service import doctor
from spiel_edge.service import kit as service_kit

REPO = Path(__file__).resolve().parents[2]


def test_packaging_folder_matches_the_code():
    for rel, text in service_kit.packaging_files().items():
        assert (REPO / "packaging" / rel).read_text() == text, (
            f"packaging/{rel} is stale: run write_packaging()"
        )


def test_unit_essentials():
    unit = service_kit.render_unit("/opt/spiel/bin/spiel-edge")
    for line in (
        "Type=notify",
        "Restart=on-failure",
        f"WatchdogSec={service_kit.WATCHDOG_SEC}",
        "User=spiel-edge",
        "SupplementaryGroups=dialout plugdev",
        "CacheDirectory=spiel-edge",
        "Environment=NUMBA_CACHE_DIR=/var/cache/spiel-edge/numba",
        "EnvironmentFile=-/etc/spiel-edge/spiel-edge.env",
    ):
        assert line in unit.splitlines()
    assert "ExecStart=/opt/spiel/bin/spiel-edge " in unit


def test_udev_rule_covers_every_board_id(tmp_path):
    rule = service_kit.render_udev(((0x1209, 0x0001), (0xCAFE, 0x00AB)))
    for vid, pid in (("1209", "0001"), ("cafe", "00ab")):
        lines = [line for line in rule.splitlines() if f'"{vid}"' in line and f'"{pid}"' in line]
        assert len(lines) == 3
        assert sum('ENV{ID_MM_DEVICE_IGNORE}="1"' in line for line in lines) == 2
    assert 'SYMLINK+="spiel-%s{serial}"' in rule and 'SYMLINK+="spiel-0"' in rule
    # doctor recognises the rule the kit ships (its ModemManager check relies on it)
    (tmp_path / "99-spiel-edge.rules").write_text(service_kit.render_udev())
    assert (
        doctor.installed_udev_rule(service_kit.usb_ids(), [tmp_path])
        == tmp_path / "99-spiel-edge.rules"
    )


def test_env_file_is_what_doctor_and_run_read(tmp_path):
    env = tmp_path / "spiel-edge.env"
    env.write_text(service_kit.render_env())
    values = doctor.read_env_file(env)
    assert values["SPIEL_PORT"] == "/dev/spiel-0"
    assert doctor.run_options(values) == ("spiel-icra23", None)
    from spiel_edge.cli.doctor import service_rejects

    assert doctor.check_config(config_dir=tmp_path, rejects=service_rejects).ok


def test_dry_run_writes_nothing(tmp_path, capsys):
    assert (
        main(
            [
                "service",
                "install",
                "--prefix",
                str(tmp_path),
                "--dry-run",
                "--exec",
                "/usr/bin/spiel-edge",
            ]
        )
        == 0
    )
    out = capsys.readouterr().out
    assert list(tmp_path.iterdir()) == []
    for kit_file in service_kit.plan():
        assert f"would write {tmp_path}/{kit_file.path}" in out
    assert "ExecStart=/usr/bin/spiel-edge" in out and "systemctl enable --now spiel-edge" in out


def test_install_writes_and_keeps_the_users_config(tmp_path, capsys):
    assert (
        main(["service", "install", "--prefix", str(tmp_path), "--exec", "/usr/bin/spiel-edge"])
        == 0
    )
    env = tmp_path / service_kit.ENV_PATH
    unit = tmp_path / service_kit.UNIT_PATH
    assert env.is_file() and unit.read_text() == service_kit.render_unit("/usr/bin/spiel-edge")
    assert (tmp_path / service_kit.UDEV_PATH).is_file() and (
        tmp_path / service_kit.SYSUSERS_PATH
    ).is_file()
    env.write_text("SPIEL_PORT=/dev/spiel-ABC\n")
    capsys.readouterr()
    assert (
        main(["service", "install", "--prefix", str(tmp_path), "--exec", "/usr/bin/spiel-edge"])
        == 0
    )
    out = capsys.readouterr().out
    assert env.read_text() == "SPIEL_PORT=/dev/spiel-ABC\n" and "kept" in out
    assert "copy them to / first" in out


def test_show_prints_one_file(capsys):
    assert main(["service", "show", "udev"]) == 0
    assert capsys.readouterr().out == service_kit.render_udev()


@pytest.mark.skipif(
    shutil.which("systemd-analyze") is None, reason="systemd-analyze is not installed here"
)
def test_systemd_analyze_verify(tmp_path):
    unit = tmp_path / "spiel-edge.service"
    unit.write_text(service_kit.render_unit(service_kit.default_exec()))
    proc = subprocess.run(
        ["systemd-analyze", "verify", str(unit)], capture_output=True, text=True, timeout=60
    )
    # verify exits 0 on unknown keys too: any line about our file is a finding
    findings = [line for line in (proc.stdout + proc.stderr).splitlines() if "spiel-edge" in line]
    assert proc.returncode == 0 and findings == [], proc.stdout + proc.stderr
