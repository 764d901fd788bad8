"""A confined service (issue 38, item 4) and a kit that installs a unit that can start (issue
41, item 4): the unit's `systemd-analyze security` exposure is at most 2.5, `service install`
refuses or fixes an ExecStart its sandbox hides, `doctor` checks the installed unit."""

from __future__ import annotations

import re
import shutil
import subprocess
from pathlib import Path

import pytest

from spiel_edge.cli import main
from spiel_edge.errors import ConfigError
from spiel_edge.service import kit as service_kit
from spiel_edge.service import sandbox

ANALYZE = shutil.which("systemd-analyze")
MAX_EXPOSURE = 2.5


def exposure(unit: Path) -> float:
    """`systemd-analyze security --offline=yes FILE` (no running systemd needed)."""
    proc = subprocess.run(
        [ANALYZE, "security", "--offline=yes", "--no-pager", str(unit)],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=unit.parent,
    )
    m = re.search(r"Overall exposure level for \S+: (\d+\.\d+)", proc.stdout + proc.stderr)
    if m is None:
        pytest.skip(f"this systemd-analyze cannot score a unit file offline: {proc.stderr[:200]}")
    return float(m[1])


@pytest.mark.skipif(ANALYZE is None, reason="systemd-analyze is not installed here")
@pytest.mark.parametrize(
    "kw",
    [{}, {"protect_home": "read-only"}, {"allow_ip": ("192.168.1.0/24",)}],
    ids=["default", "under-home", "lan"],
)
def test_the_unit_scores_ok(tmp_path, kw):
    unit = tmp_path / "spiel-edge.service"
    unit.write_text(service_kit.render_unit("/opt/spiel-edge/bin/spiel-edge", **kw))
    assert exposure(unit) <= MAX_EXPOSURE
    # the shipped unit was 7.8 "EXPOSED" before (issue 38): the score moves with the settings
    loose = tmp_path / "loose.service"
    loose.write_text(
        "\n".join(
            line
            for line in unit.read_text().splitlines()
            if not line.startswith(
                ("SystemCallFilter", "IPAddress", "CapabilityBounding", "Device")
            )
        )
    )
    assert exposure(loose) > exposure(unit) + 1.0


def test_what_the_service_needs_stays_allowed():
    lines = service_kit.render_unit().splitlines()
    for needed in (
        "DeviceAllow=char-ttyACM rw",  # CDC-ACM boards
        "DeviceAllow=char-ttyUSB rw",  # USB-serial adapters
        "DeviceAllow=char-usb_device rw",  # pyusb bulk boards (/dev/bus/usb)
        "SupplementaryGroups=dialout plugdev",
        "CacheDirectory=spiel-edge",  # numba's cache
        "StateDirectory=spiel-edge",  # recordings
        "RestrictAddressFamilies=AF_UNIX AF_INET AF_INET6 AF_NETLINK",  # sd_notify, journal, IP, udev
        "IPAddressDeny=any",
        "IPAddressAllow=localhost",
        "LimitRTPRIO=10",
    ):
        assert needed in lines, needed
    assert not any(line.startswith("MemoryDenyWriteExecute=yes") for line in lines)  # numba JIT
    assert not any(line.startswith("PrivateDevices=yes") for line in lines)  # would hide the board
    assert not any(line.startswith("RestrictRealtime=yes") for line in lines)  # --realtime
    wide = service_kit.render_unit(allow_ip=("10.0.0.0/8", "multicast"))
    assert "IPAddressAllow=localhost 10.0.0.0/8 multicast" in wide.splitlines()


def test_allow_ip_is_checked():
    assert service_kit.check_allow_ip("192.168.1.7/24") == "192.168.1.0/24"
    with pytest.raises(ConfigError, match="--allow-ip"):
        service_kit.check_allow_ip("everyone")


def test_install_refuses_a_program_under_tmp(tmp_path, capsys):
    args = ["service", "install", "--prefix", "/", "--no-warmup", "--dry-run"]
    assert main([*args, "--exec", "/tmp/venv/bin/spiel-edge"]) == 2
    out, err = capsys.readouterr()
    assert "PrivateTmp=yes" in err and len(err.strip().splitlines()) == 1
    assert "would write" not in out


def test_a_staging_install_of_a_program_under_tmp_warns_and_writes(tmp_path, capsys):
    # a checkout under /tmp still follows the README's staging quick start; the kit says why
    # it would not start as installed
    args = ["service", "install", "--prefix", str(tmp_path / "root"), "--no-warmup"]
    assert main([*args, "--exec", "/tmp/venv/bin/spiel-edge"]) == 0
    err = capsys.readouterr().err
    assert err.startswith("warning: ") and "PrivateTmp=yes" in err
    assert (tmp_path / "root" / "etc/systemd/system/spiel-edge.service").is_file()


def test_install_under_home_sets_protect_home_read_only(tmp_path, capsys):
    args = ["service", "install", "--prefix", str(tmp_path), "--no-warmup"]
    assert (
        main([*args, "--exec", "/home/robot/venv/bin/spiel-edge", "--allow-ip", "10.1.0.0/16"]) == 0
    )
    assert "ProtectHome=read-only" in capsys.readouterr().out
    unit = (tmp_path / service_kit.UNIT_PATH).read_text().splitlines()
    assert "ProtectHome=read-only" in unit and "IPAddressAllow=localhost 10.1.0.0/16" in unit
    assert sandbox.protect_home_for("/opt/spiel-edge/bin/spiel-edge") == "yes"


def test_a_scripts_interpreter_counts(tmp_path):
    script = tmp_path / "spiel-edge"
    script.write_text("#!/home/robot/venv/bin/python3\nimport sys\n")
    found = sandbox.hidden(sandbox.needed_paths(str(script)))
    assert found is not None  # tmp_path lies under /tmp: PrivateTmp hides it first
    assert sandbox.hidden(["/opt/x/bin/spiel-edge", "/home/robot/venv/bin/python3"])[0].startswith(
        "/home"
    )


def test_doctor_fails_a_unit_whose_program_its_sandbox_hides(tmp_path):
    unit = tmp_path / "spiel-edge.service"
    unit.write_text(service_kit.render_unit("/home/robot/venv/bin/spiel-edge"))  # ProtectHome=yes
    check = sandbox.check_unit(unit, analyze=None)
    assert not check.ok and "ProtectHome=yes" in check.detail and check.fix
    unit.write_text(
        service_kit.render_unit("/home/robot/venv/bin/spiel-edge", protect_home="read-only")
    )
    assert sandbox.check_unit(unit, analyze=None).ok
    assert sandbox.check_unit(tmp_path / "none.service").ok  # not installed: nothing to check


@pytest.mark.skipif(ANALYZE is None, reason="systemd-analyze is not installed here")
def test_doctor_runs_systemd_analyze_verify(tmp_path):
    unit = tmp_path / "spiel-edge.service"
    # a program the sandbox can see (this checkout may lie under /tmp, which PrivateTmp hides)
    unit.write_text(service_kit.render_unit(shutil.which("true") or "/bin/true"))
    check = sandbox.check_unit(unit)
    assert check.ok, check.detail
    assert "verify finds nothing" in check.detail
    unit.write_text(service_kit.render_unit("/opt/nowhere/bin/spiel-edge"))  # not there
    check = sandbox.check_unit(unit)
    assert not check.ok and "verify" in check.detail
