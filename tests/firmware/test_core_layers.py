"""The C core's units in layers (issue 42 item 7): each unit calls only functions of units below
it (no call circle), targets see the core only through include/ (spiel_device.h, spiel_hal.h,
spiel_boot.h), never its private core.h, and no target compile has -Icore."""

from __future__ import annotations

import re
import shutil
import subprocess

import pytest

from tests.firmware.firmware import FIRMWARE, PROTO

# the order of core/'s units: a unit may call a unit of a lower rank only
RANK = {
    "device.c": 5,  # the protocol engine, the request table, the stream
    "telemetry.c": 4,
    "update.c": 4,
    "boot.c": 3,
    "verify.c": 2,
    "config_store.c": 1,
    "sha256.c": 1,
    "link.c": 0,  # the shared link state
}


def _code(path) -> str:
    text = re.sub(r"/\*.*?\*/", "", path.read_text(), flags=re.S)
    return re.sub(r"\"(?:\\.|[^\"\\])*\"", '""', text)


def _exported() -> dict[str, str]:
    """Every function and variable a unit of core/ defines for the others: name -> unit."""
    owner = {}
    for path in (FIRMWARE / "core").glob("*.c"):
        code = _code(path)
        for m in re.finditer(r"^(?!static)[a-z][\w \*]*?\b(\w+)\([^;{]*\)\s*\{", code, re.M):
            owner[m.group(1)] = path.name
        for m in re.finditer(r"^(?!static|extern)[a-z][\w ]*?\b(\w+)(\[[^\]]*\])?;", code, re.M):
            owner[m.group(1)] = path.name
    return owner


def uses() -> dict[str, set[str]]:
    """unit -> the other units whose functions or variables it uses."""
    owner = _exported()
    found: dict[str, set[str]] = {}
    for path in (FIRMWARE / "core").glob("*.c"):
        code = _code(path)
        found[path.name] = {
            unit
            for name, unit in owner.items()
            if unit != path.name and re.search(rf"\b{name}\b", code)
        }
    return found


def test_every_unit_of_the_core_has_a_place_in_the_order():
    assert {p.name for p in (FIRMWARE / "core").glob("*.c")} == set(RANK)


def test_no_unit_of_the_core_calls_up():
    up = {
        (unit, other)
        for unit, others in uses().items()
        for other in others
        if RANK[other] >= RANK[unit]
    }
    assert not up, f"calls up or sideways (a circle waiting to happen): {sorted(up)}"


def test_the_checker_sees_calls():
    """The scan is not blind: the protocol engine uses the units below it."""
    found = uses()
    assert {"link.c", "telemetry.c", "update.c", "config_store.c"} <= found["device.c"]
    assert "link.c" in found["update.c"] and "boot.c" in found["update.c"]


def test_targets_never_include_the_cores_private_header():
    offenders = [
        str(p.relative_to(FIRMWARE))
        for p in (FIRMWARE / "targets").rglob("*.[ch]")
        if "vendor" not in p.parts and re.search(r'#include\s+"core\.h"', p.read_text())
    ]
    assert offenders == []


def test_no_target_compile_has_the_cores_folder_on_its_include_path():
    makefiles = [FIRMWARE / "Makefile", *(FIRMWARE / "targets").glob("*/target.mk")]
    for mk in makefiles:
        assert "-Icore" not in mk.read_text(), mk
    # the fuzz harness is the core's white-box test: the one place that adds it
    assert "-Icore" in (FIRMWARE / "fuzz" / "fuzz.mk").read_text()


def test_every_boot_stage_uses_the_public_boot_header():
    for rel in (
        "targets/mps2-an386/boot_mps2.c",
        "targets/rp2040/boot_rp2040.c",
        "targets/posix/image_posix.c",
    ):
        text = (FIRMWARE / rel).read_text()
        assert '#include "spiel_boot.h"' in text and "boot_start(" in text, rel


@pytest.mark.parametrize("update", [0, 1])
def test_the_boot_header_stands_alone(tmp_path, update):
    cc = shutil.which("cc") or shutil.which("gcc") or shutil.which("clang")
    if cc is None:
        pytest.skip("no C compiler")
    src = tmp_path / "boot_only.c"
    src.write_text(
        '#include "spiel_boot.h"\n'
        "int boot_stage(void);\n"
        "int boot_stage(void)\n{\n"
        + (
            "    return boot_start(SPIEL_FW_WATCHDOG_MS) + boot_is_trial(0) +"
            " image_check(0, 0, 0, 0);\n"
            if update
            else "    return (int)SPIEL_FW_WATCHDOG_MS;\n"
        )
        + "}\n"
    )
    cmd = [
        cc,
        "-std=c99",
        "-Wall",
        "-Wextra",
        "-Werror",
        "-pedantic",
        "-Wmissing-prototypes",
        "-fsyntax-only",
        f"-DSPIEL_FW_UPDATE={update}",
        f"-I{FIRMWARE / 'include'}",
        f"-I{PROTO}",
        str(src),
    ]
    done = subprocess.run(cmd, capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
