"""The reference firmware on the Raspberry Pi Pico target (targets/rp2040: TinyUSB CDC-ACM over
the Pico SDK's hardware layers) in the rp2040js emulator, its USB CDC host bridged to a pty by
run-emulated.sh: USB enumeration and HELLO, ``run`` giving the records the posix target gives
for the same recordings, config push/commit/pull kept across a REBOOT through the watchdog.

Few and short on purpose: the emulator keeps a core busy while it runs, so each test starts
one and stops it the moment it ends. Skipped, naming what is missing, without make,
arm-none-eabi-gcc, node, socat or rp2040js (.ci/run installs them)."""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

import pytest
import serial

from firmware_protocol import Reboot, encode_message
from spiel_edge.board import schema as bc
from spiel_edge.compat import tomllib
from spiel_edge.device import DeviceSession
from spiel_edge.profile.schema import load_profile
from tests.firmware.rp2040_board import Rp2040Board, Unavailable, build_rp2040, missing_tools

SPIEL_EDGE = [sys.executable, "-m", "spiel_edge.cli"]
N_FRAMES = 30


@pytest.fixture(scope="session")
def rp2040_image(tmp_path_factory) -> Path:
    why = missing_tools()
    if why:
        pytest.skip(f"rp2040 target: {why}")
    try:
        return build_rp2040(tmp_path_factory.mktemp("rp2040-build"))
    except Unavailable as exc:
        pytest.skip(f"rp2040 target: {exc}")


@pytest.fixture
def pico(rp2040_image, tmp_path):
    with Rp2040Board(rp2040_image, tmp_path / "emulator.log") as board:
        yield board.start()


def cli(*args: object, timeout: float = 120) -> subprocess.CompletedProcess:
    return subprocess.run(
        [*SPIEL_EDGE, *map(str, args)], capture_output=True, text=True, timeout=timeout
    )


def records(path: Path) -> list[dict]:
    return [json.loads(line) for line in path.read_text().splitlines()]


def test_the_build_makes_a_uf2_for_bootsel(rp2040_image):
    """firmware.uf2: 512-byte UF2 blocks of 256 bytes for the RP2040 family, from 0x10000000,
    boot2 first with the CRC-32 the bootrom checks (pad_checksum's, over its first 252 bytes)."""
    import struct

    data = (rp2040_image.parent / "firmware.uf2").read_bytes()
    assert len(data) % 512 == 0 and len(data) > 0
    n = len(data) // 512
    flash = bytearray()
    for i in range(n):
        block = data[512 * i : 512 * (i + 1)]
        m0, m1, flags, addr, size, no, total, family = struct.unpack_from("<8I", block)
        assert (m0, m1, flags, size, no, total, family) == (
            0x0A324655,
            0x9E5D5157,
            0x2000,
            256,
            i,
            n,
            0xE48BFF56,
        )
        assert addr == 0x10000000 + 256 * i
        assert struct.unpack_from("<I", block, 508)[0] == 0x0AB16F30
        flash += block[32 : 32 + 256]
    boot2 = bytes(flash[:252])
    # the bootrom's CRC-32: MSB first, polynomial 0x04C11DB7, initial 0xFFFFFFFF, no final xor
    crc = 0xFFFFFFFF
    for byte in boot2:
        crc ^= byte << 24
        for _ in range(8):
            crc = ((crc << 1) ^ 0x04C11DB7 if crc & 0x80000000 else crc << 1) & 0xFFFFFFFF
    assert struct.unpack_from("<I", flash, 252)[0] == crc
    # the vector table right after boot2: the stack top and a Thumb reset handler in flash
    sp, reset = struct.unpack_from("<II", flash, 256)
    assert sp == 0x20042000 and reset & 1 and 0x10000100 < reset < 0x10000000 + len(flash)


def test_enumerates_and_answers_hello(pico):
    started = time.monotonic()
    with DeviceSession(pico.port, reconnect=False) as session:
        hello = session.hello
    took = time.monotonic() - started
    assert "USB configured: CDC data IN endpoint 2, OUT 2" in pico.messages()
    assert hello.firmware_version == "1.0.0+rp2040"
    assert (hello.usb_vid, hello.usb_pid) == (0x2E8A, 0x000A)
    assert hello.serial == "RP2040-EMU-0001" and hello.n_channels == 4
    assert hello.max_samples == 64 and hello.max_payload == 1024
    assert took < 30, took


def test_run_gives_the_posix_targets_records(pico, posix_board, tmp_path):
    """The same recordings in the same order on both targets: record k of one is record k of
    the other (positions, echoes, association), over the emulated USB and over the posix pty."""
    got = {}
    for name, port in (("rp2040", pico.port), ("posix", posix_board().port)):
        out = tmp_path / f"{name}.ndjson"
        ran = cli("run", "--port", port, "--frames", N_FRAMES, "-o", out)
        assert ran.returncode == 0, ran.stderr
        assert "Traceback" not in ran.stderr
        got[name] = records(out)
    assert len(got["rp2040"]) == len(got["posix"]) == N_FRAMES
    fixes = 0
    for k, (a, b) in enumerate(zip(got["rp2040"], got["posix"], strict=True)):
        assert a["position_mm"] == b["position_mm"], k
        assert a["echoes"] == b["echoes"], k
        assert (a["matched"], a["reason"]) == (b["matched"], b["reason"]), k
        fixes += a["position_mm"] is not None
    assert fixes > N_FRAMES // 2


def pulled(port: str) -> dict | None:
    ran = cli("config", "pull", "--port", port)
    if ran.returncode != 0:
        assert "holds no config" in ran.stderr, ran.stderr
        return None
    return tomllib.loads(ran.stdout)


def test_config_is_kept_across_a_watchdog_reboot(pico, tmp_path):
    """config push --commit writes the flash (the emulator's path of flash_rp2040.c); REBOOT
    resets the chip through the watchdog (a new chip in the emulator, same flash), which comes
    back on the same port with a new boot id and the committed config."""
    assert pulled(pico.port) is None  # an erased flash: factory defaults
    config = tmp_path / "board.toml"
    config.write_text(bc.to_toml(bc.validate(bc.from_profile(load_profile(), "pico-one"))))
    ran = cli("config", "push", "--port", pico.port, "--commit", config)
    assert ran.returncode == 0, ran.stderr
    assert pulled(pico.port)["board"]["name"] == "pico-one"

    with DeviceSession(pico.port, reconnect=False) as session:
        first = session.hello.boot_id
    with serial.Serial(pico.port, timeout=0.2) as port:
        port.write(encode_message(Reboot(0, 10), seq=7))
        pico.wait_message("rp2040js: boot 2")
    with DeviceSession(pico.port, reconnect=False) as again:
        assert again.hello.boot_id != first
    assert pulled(pico.port)["board"]["name"] == "pico-one"


def test_the_emulator_stops_with_its_script(rp2040_image, tmp_path):
    """SIGTERM to run-emulated.sh ends socat and node too: nothing keeps a core busy."""
    board = Rp2040Board(rp2040_image, tmp_path / "log").start()
    pid = board.proc.pid
    board.stop()
    time.sleep(0.5)
    left = subprocess.run(
        ["pgrep", "-f", f"run.mjs {rp2040_image}"], capture_output=True, text=True
    ).stdout.split()
    assert left == [], (pid, left)
