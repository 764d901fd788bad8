"""The reference firmware on the Raspberry Pi Pico target (targets/rp2040: TinyUSB CDC-ACM over
the Pico SDK's hardware layers) in the rp2040js emulator, its USB CDC host bridged to a pty by
run-emulated.sh: USB enumeration and HELLO, ``run`` giving the records the posix target gives
for the same recordings, config push/commit/pull kept across a REBOOT through the watchdog, a
firmware update through the boot stage (flash to flash install) and a hung trial image rolled
back by the watchdog the boot stage armed, with no power cycle; signed images (PROTOCOL.md
14.6): the boot stage and FW_VERIFY take only images signed by the development key (the build's
FW_KEY), every forgery, an unsigned and an older (lower security counter) image are refused;
power cuts during an update (the emulator's flash kept, the chip restarted) boot a complete
image.

Few and short on purpose: the emulator keeps a core busy while it runs, so each test starts
one and stops it the moment it ends. Skipped, naming what is missing, without make,
arm-none-eabi-gcc, node, socat or rp2040js (.ci/run installs them)."""

from __future__ import annotations

import contextlib
import itertools
import json
import os
import re
import struct
import subprocess
import sys
import time
from pathlib import Path

import pytest
import serial

from spiel_edge.board_config import schema as bc
from spiel_edge.compat import tomllib
from spiel_edge.device import DeviceSession
from spiel_edge.device.firmware import firmware_info, update_firmware
from spiel_edge.errors import DeviceError, SpielError
from spiel_edge.link.usb_ids import BOARD_USB_IDS
from spiel_edge.profile.schema import load_profile
from spiel_edge.protocol import Reboot, encode_message
from spiel_edge.protocol.image import parse_image
from spiel_edge.protocol.link_messages import BootState
from tests.firmware.rp2040_board import Rp2040Board, Unavailable, build_rp2040, missing_tools
from tests.fwsign import DEV_KEY, signed_image
from tests.protocol_v2.signing_cases import forged_images, other_signer, raw_upload

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


@pytest.fixture(scope="session")
def small_image(rp2040_image, tmp_path_factory) -> Path:
    """A build that embeds two recordings (a 38 KB application): the emulated M0+ hashes its
    slots (FW_INFO, FW_VERIFY, the boot stage) within the host's timeouts; the full build's
    154 KB take it seconds, the real chip about 0.1 s."""
    import numpy as np

    from spiel_edge.data import load_subset

    d = tmp_path_factory.mktemp("rp2040-small")
    np.savez(d / "two.npz", frames=np.round(load_subset().frames[:2]).astype(np.uint16))
    return build_rp2040(d, extra=(f"SUBSET={d / 'two.npz'}",))


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
    """firmware.uf2: 512-byte UF2 blocks of 256 bytes for the RP2040 family. At 0x10000000
    boot2 with the CRC-32 the bootrom checks (pad_checksum's, over its first 252 bytes), then
    the boot stage's vector table; slot 0 holds app.bin packed as pack_image packs it (the
    build's own packer agrees with the host's) and the execution region the same image
    installed (its header, then the body at 0x10011000, where the application is linked);
    the image is signed by the development key (Ed25519 is deterministic: the same bytes)."""
    build = rp2040_image.parent
    data = (build / "firmware.uf2").read_bytes()
    assert len(data) % 512 == 0 and len(data) > 0
    n, flash = len(data) // 512, {}
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
        assert struct.unpack_from("<I", block, 508)[0] == 0x0AB16F30 and addr % 256 == 0
        flash[addr] = block[32 : 32 + 256]

    def read(addr: int, size: int) -> bytes:
        base = addr - addr % 256
        raw = b"".join(flash[a] for a in range(base, addr + size, 256))
        return raw[addr - base : addr - base + size]

    boot2 = read(0x1000_0000, 252)
    # the bootrom's CRC-32: MSB first, polynomial 0x04C11DB7, initial 0xFFFFFFFF, no final xor
    crc = 0xFFFFFFFF
    for byte in boot2:
        crc ^= byte << 24
        for _ in range(8):
            crc = ((crc << 1) ^ 0x04C11DB7 if crc & 0x80000000 else crc << 1) & 0xFFFFFFFF
    assert struct.unpack("<I", read(0x1000_00FC, 4))[0] == crc
    sp, reset = struct.unpack("<II", read(0x1000_0100, 8))
    assert sp == 0x2004_2000 and reset & 1 and 0x1000_0100 < reset < 0x1001_0000

    body = (build / "app.bin").read_bytes()
    packed = signed_image(body, version="1.0.0+rp2040", target="rp2040")
    assert read(0x1009_0000, len(packed)) == packed  # slot 0
    assert read(0x1001_0000, 96) == packed[:96]  # installed: the header ...
    assert read(0x1001_1000, len(body)) == body  # ... and the body where it is linked
    assert parse_image(packed).target == "rp2040"


def test_a_release_build_signs_with_its_own_key(rp2040_image, tmp_path):
    """make TARGET=rp2040 FW_KEY=k.pub RELEASE=1: the slot-0 image of firmware.uf2 is signed by
    k.key (FW_SIGN_KEY's default) and verifies with k.pub only; without the private half, or
    with a private key of another pair, the build stops in one line naming FW_SIGN_KEY."""
    from spiel_edge.device.fwkeys import generate_key
    from spiel_edge.protocol.image import ImageRefused, verify_image
    from spiel_edge.protocol.signing import DEV_PUBLIC_KEY, parse_public_key_text

    generate_key(tmp_path / "k.key", tmp_path / "k.pub")
    generate_key(tmp_path / "other.key", tmp_path / "other.pub")
    key = parse_public_key_text((tmp_path / "k.pub").read_text())
    build = build_rp2040(tmp_path / "rel", extra=(f"FW_KEY={tmp_path / 'k.pub'}", "RELEASE=1"))
    image = build.with_name("app.img").read_bytes()
    assert verify_image(image, key).signed
    with pytest.raises(ImageRefused):
        verify_image(image, DEV_PUBLIC_KEY)
    (tmp_path / "k.key").unlink()
    for extra, why in (
        ((), "no " + str(tmp_path / "k.key")),
        ((f"FW_SIGN_KEY={tmp_path / 'other.key'}",), "not the private half"),
    ):
        with pytest.raises(RuntimeError, match=why):
            build_rp2040(tmp_path / "no-key", extra=(f"FW_KEY={tmp_path / 'k.pub'}", *extra))


def test_enumerates_and_answers_hello(pico):
    started = time.monotonic()
    with DeviceSession(pico.port, reconnect=False) as session:
        hello = session.hello
    took = time.monotonic() - started
    assert "USB configured: CDC data IN endpoint 2, OUT 2" in pico.messages()
    assert hello.firmware_version == "1.0.0+rp2040"
    assert (hello.usb_vid, hello.usb_pid) == BOARD_USB_IDS[0]  # what discovery looks for
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
    with serial.Serial(pico.port, timeout=0.2, write_timeout=1) as port:
        port.write(encode_message(Reboot(0, 10), seq=7))
        # a host keeps writing through the reset (a reconnecting session's HELLOs): the bytes
        # that come between the old chip and the new one ended the emulator (rp2040js crashed
        # in its OUT pump, the pty vanished), and with it an update's test boot under load
        until = time.monotonic() + 60
        while "rp2040js: boot 2" not in pico.messages() and time.monotonic() < until:
            port.write(b"\x00not a frame\x00")
            time.sleep(0.002)
        for _ in range(250):
            port.write(b"\x00not a frame\x00")
            time.sleep(0.002)
    assert pico.alive(), pico.messages()[-2000:]
    pico.wait_message("USB configured", count=2)  # enumerated again (seconds at load 12)
    with DeviceSession(pico.port, reconnect=False) as again:
        assert again.hello.boot_id != first
    assert pulled(pico.port)["board"]["name"] == "pico-one"


def test_the_emulator_stops_with_its_script_or_its_caller(rp2040_image, tmp_path):
    """SIGTERM to run-emulated.sh ends socat and node too; so does the end of the process that
    started it (here a shell that exits after 2 s): nothing keeps a core busy."""
    from tests.firmware.rp2040_board import RUN

    def left() -> list[str]:
        found = subprocess.run(
            ["pgrep", "-f", f"run.mjs {rp2040_image}"], capture_output=True, text=True
        )
        return found.stdout.split()

    board = Rp2040Board(rp2040_image, tmp_path / "log").start()
    board.stop()
    time.sleep(0.5)
    assert left() == []
    shell = f"{RUN} {rp2040_image} >/dev/null 2>&1 & sleep 2"
    subprocess.run(["bash", "-c", shell], timeout=30, check=True)
    deadline = time.monotonic() + 10
    while left() and time.monotonic() < deadline:
        time.sleep(0.2)
    assert left() == []


def hello_when_up(port: str, timeout_s: float = 30.0):
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            with DeviceSession(port, reconnect=False) as dev:
                return dev.hello, firmware_info(dev)
        except DeviceError:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.2)


def test_update_refusals_and_a_hung_trial_rolled_back_by_the_watchdog(small_image, tmp_path):
    """firmware pack --key + update: the board checks the signature (FW_VERIFY answers BUSY and
    the host asks again: one Ed25519 check is seconds of the emulated M0+), the boot stage
    installs slot 1 into the execution region (flash to flash) and runs it as a trial; the host
    confirms it, which raises the board's security counter to the image's 2. Then the forged
    images of signing_cases (header, counter or body changed with their digests recomputed,
    wrong key, truncated signature, unsigned), uploaded past the host's own checks, are refused
    by FW_VERIFY, and an older image (counter 1) by `firmware update` in one line. Then an
    image that hangs (its reset handler is `b .`): it never kicks the watchdog the boot stage
    armed, the watchdog resets the chip and the boot stage rolls back to the confirmed image,
    with no power cycle."""
    with Rp2040Board(small_image, tmp_path / "emulator.log") as pico:
        update_and_roll_back(pico.start(), small_image.with_name("app-emu.bin"), tmp_path)


def update_and_roll_back(pico: Rp2040Board, app: Path, tmp_path: Path) -> None:
    h, info = hello_when_up(pico.port)
    assert (h.firmware_version, info.running_slot, info.confirmed_slot) == ("1.0.0+rp2040", 0, 0)
    body = app.read_bytes()
    # the same body under another version: the host confirms only the board it started with
    # (its serial, which is in the body, must stay); the version HELLO gives is the installed
    # header's (image_rp2040.c)
    (tmp_path / "app.bin").write_bytes(body)
    packed = tmp_path / "fw.img"
    ran = cli(
        "firmware",
        "pack",
        "--version",
        "rp2040-1.1.0",
        "--target",
        "rp2040",
        "--key",
        DEV_KEY,
        "--security-counter",
        2,
        "-o",
        packed,
        tmp_path / "app.bin",
    )
    assert ran.returncode == 0, ran.stderr
    started = time.monotonic()
    ran = cli("firmware", "update", "--port", pico.port, "--wait", 60, packed, timeout=300)
    took = time.monotonic() - started
    assert ran.returncode == 0, ran.stderr + ran.stdout
    h, info = hello_when_up(pico.port)
    assert (h.firmware_version, h.serial) == ("rp2040-1.1.0", "RP2040-EMU-0001")
    assert (info.running_slot, info.confirmed_slot, info.boot_state) == (1, 1, BootState.CONFIRMED)
    print(f"update of {packed.stat().st_size} bytes: {took:.1f} s")

    refused(pico, packed.read_bytes(), tmp_path)
    hang = struct.pack("<II", 0x2004_2000, 0x1001_1009) + b"\xfe\xe7" + bytes(6)
    boots = pico.messages().count("rp2040js: boot ")
    result = update_firmware(
        pico.port,
        signed_image(hang, version="rp2040-hang", target="rp2040", security_counter=2),
        boot_wait_s=60,
    )
    assert result.rolled_back and not result.confirmed
    assert (result.previous, result.version) == ("rp2040-1.1.0", "rp2040-1.1.0")
    pico.wait_message("rp2040js: boot ", count=boots + 2)  # the trial, then the watchdog's
    h, info = hello_when_up(pico.port)
    assert (h.firmware_version, h.serial) == ("rp2040-1.1.0", "RP2040-EMU-0001")
    assert (info.running_slot, info.confirmed_slot) == (1, 1)


def refused(pico: Rp2040Board, good: bytes, tmp_path: Path) -> None:
    """FW_VERIFY of the emulated Pico refuses every forgery the other targets refuse (tampered
    header, counter or body, wrong key, truncated signature, unsigned) and an older image; the
    board keeps what it runs."""
    for name, (image, code) in forged_images(good, other_signer(tmp_path)).items():
        started = time.monotonic()
        assert raw_upload(pico.port, image) == code, name
        print(f"{name}: refused ({code}) in {time.monotonic() - started:.1f} s")
    body = good[96 : 96 + parse_image(good).body_size]
    older = tmp_path / "older.img"
    older.write_bytes(
        signed_image(body, version="rp2040-1.0.9", target="rp2040", security_counter=1)
    )
    ran = cli("firmware", "update", "--port", pico.port, older, timeout=300)
    assert ran.returncode != 0
    line = ran.stderr.strip().splitlines()[-1]
    assert "FW_ROLLBACK" in line and "keeps firmware rp2040-1.1.0" in line, ran.stderr
    h, info = hello_when_up(pico.port)
    assert (h.firmware_version, info.running_slot, info.boot_state) == (
        "rp2040-1.1.0",
        1,
        BootState.CONFIRMED,
    )


# The flash operations of one update of the small image, as run.mjs counts them (stores to one
# 256-byte page; a sector erase is 16): the upload into slot 1, the boot record's FW_TEST write,
# the boot stage's flash-to-flash install into the execution region, and the record written as
# the trial is confirmed (the security counter with it). Counted by the sweep's first run.
CUT_REGIONS = {  # name -> (first, end) flash offsets (rp2040_board.h)
    "upload": (0x110000, 0x190000),
    "record": (0x190000, 0x1F0000),
    "install": (0x010000, 0x090000),
}


def _flash_ops(log: str) -> list[tuple[int, str]]:
    """(operation number, region name) of every flash operation an emulator log reports."""
    out = []
    for n, at in re.findall(r"flash op (\d+) at 0x([0-9a-f]+)", log):
        where = int(at, 16)
        name = next((k for k, (a, b) in CUT_REGIONS.items() if a <= where < b), "other")
        out.append((int(n), name))
    return out


def _cut_points(ops: list[tuple[int, str]], sweep: int) -> list[int]:
    """Default: the middle of the install and the first operation of the confirm's record
    write (the security counter's); SPIEL_RP2040_CUT_SWEEP=N: every record operation and every
    Nth of the others (1: every operation)."""
    runs = [list(run) for _, run in itertools.groupby(ops, key=lambda op: op[1])]
    names = [r[0][1] for r in runs]
    assert names == ["upload", "record", "install", "record"], names
    if sweep:
        return [n for n, name in ops if name == "record" or n % sweep == 0]
    install, confirm = runs[2], runs[3]
    return [install[len(install) // 2][0], confirm[0][0]]


def test_a_power_cut_during_an_update_boots_a_complete_image(small_image, tmp_path):
    """The RP2040 boot decision under power cuts (issue 37 item 3; issue 38's counter): the
    emulator loses power at a chosen flash operation of `firmware update` (run.mjs
    RP2040_EMU_CUT_AT, the store lost, the watchdog's scratch registers cleared). The board
    must come back running a complete image, the old or the new one, the same update must
    then succeed, confirmed, and its counter hold: an older image is refused."""
    app = small_image.with_name("app-emu.bin").read_bytes()
    image = signed_image(app, version="rp2040-1.1.0", target="rp2040", security_counter=2)
    older = signed_image(app, version="rp2040-1.0.9", target="rp2040", security_counter=1)
    counted = tmp_path / "count.log"
    with Rp2040Board(small_image, counted, env={"RP2040_EMU_FLASH_OPS": "1"}) as pico:
        assert update_firmware(pico.start().port, image, boot_wait_s=60).confirmed
    ops = _flash_ops(counted.read_text())
    region = dict(ops)
    cuts = _cut_points(ops, int(os.environ.get("SPIEL_RP2040_CUT_SWEEP", "0")))
    outcomes = []
    for cut in cuts:
        log = tmp_path / f"cut{cut}.log"
        with Rp2040Board(small_image, log, env={"RP2040_EMU_CUT_AT": str(cut)}) as pico:
            pico.start()
            with contextlib.suppress(SpielError):  # the cut ends it; a later one finishes it
                update_firmware(pico.port, image, boot_wait_s=60)
            pico.wait_message(f"power cut at flash op {cut}")
            booted = pico.messages().count("USB configured")
            pico.wait_message("USB configured", count=max(booted, 2), timeout_s=60)
            h, info = hello_when_up(pico.port, timeout_s=60)
            assert h.serial == "RP2040-EMU-0001", cut
            assert h.firmware_version in ("1.0.0+rp2040", "rp2040-1.1.0"), (cut, h)
            on_new = h.firmware_version == "rp2040-1.1.0"
            if on_new and info.boot_state == BootState.CONFIRMED:  # then its counter too
                assert raw_upload(pico.port, older) == "FW_ROLLBACK", cut
            outcomes.append((region[cut], on_new))
            done = update_firmware(pico.port, image, boot_wait_s=60)
            assert done.confirmed and done.version == "rp2040-1.1.0", (cut, done)
            h, info = hello_when_up(pico.port, timeout_s=60)
            assert (h.firmware_version, info.confirmed_slot) == ("rp2040-1.1.0", info.running_slot)
            assert raw_upload(pico.port, older) == "FW_ROLLBACK", cut
    for name in CUT_REGIONS:  # the figure of docs/measurements.md (-s shows it)
        new = [on_new for where, on_new in outcomes if where == name]
        print(f"cuts in the {name}: {len(new)}, {sum(new)} came back on the new image")
