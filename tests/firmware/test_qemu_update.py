"""Firmware update with rollback on the Cortex-M4 target (mps2-an386 under qemu-system-arm): the
boot stage at address 0 chooses a slot with the core's boot_choose(), copies it to the execution
region and jumps (targets/mps2-an386/boot_mps2.c); the slots and the boot record live in the
file-backed PSRAM, so a kill of qemu is a power cut.

The images are the application of a build with two embedded recordings (about 20 KB, quick to
upload) with its board_name text patched, so DEVICE_INFO shows that the copied code runs. A power
cut is sampled at the first, middle and last chunk and at every state change of the update;
``SPIEL_QEMU_UPDATE_SWEEP=1`` cuts at every flash operation and kills the host after every
chunk (docs/firmware.md gives its figures). Skipped like tests/firmware/test_qemu.py where the
Arm toolchain or qemu is missing."""

from __future__ import annotations

import contextlib
import os
import shutil
import struct
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from spiel_edge.cli import main
from spiel_edge.device import DeviceSession
from spiel_edge.device.firmware import firmware_info, update_firmware
from spiel_edge.errors import DeviceError
from spiel_edge.protocol import Reboot
from spiel_edge.protocol.link_messages import BootState, FwBegin, FwTest, FwVerify, FwWrite
from tests.firmware.qemu_board import (
    CUT,
    QemuBoard,
    Unavailable,
    app_bin,
    build_mps2,
    missing_tools,
    new_flash,
)
from tests.fwsign import DEV_KEY, signed_image

SWEEP = os.environ.get("SPIEL_QEMU_UPDATE_SWEEP") == "1"
FACTORY = "1.0.0+mps2-an386"
MARK = b"spiel-c mps2"  # hal_mps2.c: the built-in image's board_name (DEVICE_INFO)
CHUNK = 1024 - 6  # FW_WRITE data at max_payload 1024


@pytest.fixture(scope="module")
def elf(tmp_path_factory) -> Path:
    why = missing_tools()
    if why:
        pytest.skip(f"mps2-an386 target: {why}")
    from spiel_edge.data import load_subset

    d = tmp_path_factory.mktemp("mps2-update")
    np.savez(d / "two.npz", frames=np.round(load_subset().frames[:2]).astype(np.uint16))
    try:
        return build_mps2(d, extra=(f"SUBSET={d / 'two.npz'}",))
    except Unavailable as exc:
        pytest.skip(f"mps2-an386 target: {exc}")


def image(elf: Path, version: str, mark: str, **kw) -> bytes:
    body = app_bin(elf).read_bytes()
    assert body.count(MARK) == 1
    return signed_image(
        body.replace(MARK, mark.encode()), version=version, target="mps2-an386", **kw
    )


class Ident:
    """HELLO's version and boot id, and DEVICE_INFO's board_name: the text the tests patch
    into an image to see that its copied code runs (the serial is the board's: the update
    checks it stays the same)."""

    def __init__(self, dev) -> None:
        from spiel_edge.protocol.messages import DeviceInfoRequest

        self.firmware_version = dev.hello.firmware_version
        self.boot_id = dev.hello.boot_id
        self.mark = dev.request(DeviceInfoRequest()).board_name


def hello(port: str, timeout_s: float = 15.0):
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            with DeviceSession(port, reconnect=False) as dev:
                return Ident(dev)
        except DeviceError:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.1)


def steps(port: str, img: bytes, upto: str) -> None:
    """The update by hand, stopping after ``upto``: write, verify, test (FW_TEST answered),
    trial (the test image answered HELLO, not confirmed) or confirm."""
    import hashlib

    from crc32c import crc32c

    with DeviceSession(port, reconnect=False) as dev:
        dev.request(FwBegin(len(img), crc32c(img), hashlib.sha256(img).digest()))
        for off in range(0, len(img), CHUNK):
            dev.request(FwWrite(off, img[off : off + CHUNK]))
        if upto == "write":
            return
        dev.request(FwVerify())
    if upto != "verify":
        steps_from_test(port, upto)


def steps_from_test(port: str, upto: str = "confirm") -> None:
    """FW_TEST of the upload verified before; then (trial) wait for the test image to answer,
    and (confirm) for its self-test to pass (FW_CONFIRM is refused before), and confirm it."""
    with DeviceSession(port, reconnect=False) as dev:
        boot_id = dev.hello.boot_id
        dev.request(FwTest(50))
    if upto == "test":
        return
    deadline = time.monotonic() + 15
    while hello(port).boot_id == boot_id:
        assert time.monotonic() < deadline
        time.sleep(0.1)
    if upto != "confirm":
        return
    while True:
        with DeviceSession(port, reconnect=False) as dev:
            if firmware_info(dev).selftest == 3:
                break
        assert time.monotonic() < deadline
        time.sleep(0.05)
    assert main(["firmware", "confirm", "--port", port]) == 0


def reboot(port: str):
    """REBOOT (a reset through the SCB, the boot stage runs); the HELLO of the next boot."""
    with DeviceSession(port, reconnect=False) as dev:
        boot_id = dev.hello.boot_id
        dev.request(Reboot(0))
    deadline = time.monotonic() + 15
    while (h := hello(port)).boot_id == boot_id:
        assert time.monotonic() < deadline
        time.sleep(0.1)
    return h


def power_cycle(b: QemuBoard):
    b.kill()
    b.disarm()
    b.start()
    return hello(b.port)


def test_pack_update_confirm_and_roll_back(elf, tmp_path, capsys) -> None:
    packed = tmp_path / "fw.img"
    body = tmp_path / "app.bin"
    body.write_bytes(app_bin(elf).read_bytes().replace(MARK, b"spiel-c m002"))
    pack = ["firmware", "pack", "--version", "mps2-1.1.0", "--target", "mps2-an386"]
    pack += ["--key", str(DEV_KEY), "-o"]
    assert main([*pack, str(tmp_path / "elf.img"), str(elf)]) != 0  # the ELF, not the body
    assert "app.bin" in capsys.readouterr().err
    assert main([*pack, str(packed), str(body)]) == 0
    with QemuBoard(elf, new_flash(tmp_path / "flash.bin")) as b:
        assert hello(b.port).firmware_version == FACTORY
        # a trial that never confirms: a reset (REBOOT, through the SCB) rolls it back to the
        # built-in image, whole again (its own board_name)
        steps(b.port, image(elf, "mps2-1.0.9", "spiel-c m009"), "trial")
        with DeviceSession(b.port, reconnect=False) as dev:
            assert (Ident(dev).firmware_version, Ident(dev).mark) == (
                "mps2-1.0.9",
                "spiel-c m009",
            )
            assert firmware_info(dev).boot_state == BootState.TRIAL
        h = reboot(b.port)
        assert (h.firmware_version, h.mark) == (FACTORY, MARK.decode())

        assert main(["firmware", "update", "--port", b.port, "--wait", "60", str(packed)]) == 0
        h = hello(b.port)  # the copied application runs: its patched board_name answers
        assert (h.firmware_version, h.mark) == ("mps2-1.1.0", "spiel-c m002")
        h = power_cycle(b)
        assert (h.firmware_version, h.mark) == ("mps2-1.1.0", "spiel-c m002")
        with DeviceSession(b.port, reconnect=False) as dev:
            info = firmware_info(dev)
        assert (info.running_slot, info.confirmed_slot, info.boot_state) == (0, 0, 0)

        # an image that hangs (its reset handler is `b .`): the watchdog the boot stage started
        # before the trial resets the board (CMSDK watchdog, no power cycle: the same qemu) and
        # the boot stage rolls it back; the host reports the state the board reports after
        hang = struct.pack("<II", 0x2000_1000, 0x0001_0009) + b"\xfe\xe7" + bytes(6)
        hang_img = signed_image(hang, version="mps2-hang", target="mps2-an386")
        qemu = b.proc.pid
        t0 = time.monotonic()
        result = update_firmware(b.port, hang_img, boot_wait_s=20)
        print(f"hung trial rolled back by the watchdog after {time.monotonic() - t0:.1f} s")
        assert (result.outcome, result.version, result.slot) == ("rolled back", "mps2-1.1.0", 0)
        assert b.proc.pid == qemu and b.proc.poll() is None
        with DeviceSession(b.port, reconnect=False) as dev:
            info = firmware_info(dev)
        assert (info.running_slot, info.confirmed_slot, info.boot_state) == (0, 0, 0)


def test_a_bad_image_is_refused_before_the_switch(elf, tmp_path, capsys) -> None:
    good = image(elf, "mps2-1.1.0", "spiel-c m002")
    flipped = bytearray(good)
    flipped[-100] ^= 0xFF
    bad = {
        "hash": bytes(flipped),
        "protocol": image(elf, "mps2-9", "spiel-c m009", min_protocol=3, max_protocol=3),
        "truncated": good[:-200],
    }
    with QemuBoard(elf, new_flash(tmp_path / "flash.bin")) as b:
        for name, img in bad.items():  # the host refuses the file
            path = tmp_path / f"{name}.img"
            path.write_bytes(img)
            assert main(["firmware", "update", "--port", b.port, str(path)]) != 0, name
            assert "refused" in capsys.readouterr().err, name
        # the board refuses them too, sent past the host's check: FW_VERIFY fails, FW_TEST
        # has nothing to boot
        said = {"hash": "not a valid image", "protocol": "no protocol version of ours"}
        for name, img in bad.items():
            with pytest.raises(DeviceError, match=said.get(name, "not a valid image")):
                steps(b.port, img, "verify")
            dev = DeviceSession(b.port, reconnect=False)
            with dev, pytest.raises(DeviceError, match="FW_VERIFY first"):
                dev.request(FwTest(0))
        h = power_cycle(b)
        assert (h.firmware_version, h.mark) == (FACTORY, MARK.decode())


class Killed(Exception):
    """The host died here."""


def _update_until_cut(b: QemuBoard, img: bytes) -> bool:
    """The whole update from a thread until the armed cut stops the board (then qemu is killed,
    the power cut) or the update ends; whether the cut fired."""
    stop = threading.Event()

    class Stopped(Exception):
        pass

    def opener(url: str):
        if stop.is_set():
            raise Stopped
        s = DeviceSession(url, reconnect=False)
        s.open()
        return s

    def run() -> None:
        with contextlib.suppress(DeviceError, Stopped):
            update_firmware(b.port, img, open_session=opener, boot_wait_s=10)

    host = threading.Thread(target=run, daemon=True)
    host.start()
    while host.is_alive() and not b.mailbox()["fired"]:
        time.sleep(0.02)
    fired = bool(b.mailbox()["fired"])
    stop.set()
    b.kill()
    host.join(60)
    assert not host.is_alive()
    return fired


def test_power_cut_at_chunks_and_state_changes_boots_a_complete_image(elf, tmp_path) -> None:
    old = ("mps2-1.1.0", "spiel-c m002")
    new = ("mps2-1.2.0", "spiel-c m003")
    img = image(elf, *new)
    n = -(-len(img) // CHUNK)
    base = new_flash(tmp_path / "base.bin")
    with QemuBoard(elf, base) as b:  # slot 0 confirmed: the old image
        assert update_firmware(b.port, image(elf, *old), boot_wait_s=15).confirmed
        # the host killed after chunk k: the board goes on running the old image
        for k in range(1, n + 1) if SWEEP else (n // 2,):

            def progress(sent, total, k=k):
                if sent >= min(k * CHUNK, total):
                    raise Killed

            with pytest.raises(Killed):
                update_firmware(b.port, img, progress=progress)
            assert hello(b.port).firmware_version == old[0], k

    def case(name: str) -> QemuBoard:
        flash = tmp_path / f"{name}.bin"
        shutil.copyfile(base, flash)
        return QemuBoard(elf, flash)

    # SPIEL_QEMU_UPDATE_SWEEP=1: qemu killed (or the board reset by REBOOT) between operations
    # too, after each state change (the flash then holds what a cut at the next operation below
    # leaves; "test": during the test boot, either image)
    expect = {"write": {old}, "verify": {old}, "test": {old, new}, "trial": {old}, "confirm": {new}}
    stops = [(s, how) for s in expect for how in ("kill", "reset") if how == "kill" or s != "test"]
    for stage, how in stops if SWEEP else ():
        b = case(f"{stage}-{how}")
        b.start()
        try:
            steps(b.port, img, stage)
            h = power_cycle(b) if how == "kill" else reboot(b.port)
            assert (h.firmware_version, h.mark) in expect[stage], (stage, how)
        finally:
            b.kill()

    # where the update's flash operations fall (counted by the mailbox, armed past the end;
    # from power-on, so first the boot stage's install of slot 0: qemu's loader puts the
    # built-in image back in the execution region at every start, a board's would stay): the upload (sector erases as it goes, unit-aligned writes, the last unit at FW_VERIFY) up
    # to w; FW_TEST's record erase + write (w, w+1); the boot stage's trial record (t, t+1),
    # its install of the trial into the execution region (t+2 .. r); FW_CONFIRM's record (r,
    # r+1); r+2 is past the end
    count = case("count")
    count.arm(CUT, 1 << 30)
    with count:
        hello(count.port)
        p0 = count.mailbox()["ops"]  # the power-on install
        steps(count.port, img, "verify")
        w = count.mailbox()["ops"]
        steps_from_test(count.port)
        r = count.mailbox()["ops"] - 2  # before the confirm record
    t = w + 2
    assert w >= n and r > t + 2 + len(img) // 256, (w, r)

    # a cut in FW_TEST's record keeps the older copy (pending test lost: old); in the boot
    # stage's trial record keeps the pending test (the trial boots again: new); in the install
    # the record already says TRIAL (rolled back: old); in the confirm record: old
    def outcome(op: int) -> tuple[str, str]:
        return new if op in (t, t + 1) or op >= r + 2 else old

    # by default (the suite's time): the power-on install, the upload, the test record, the trial's
    # record, the middle of the install, the confirm record; the sweep every operation
    samples = (p0 // 2, (p0 + w) // 2, w + 1, t + 1, (t + 2 + r) // 2, r + 1)
    for op in range(r + 3) if SWEEP else samples:
        b = case(f"cut{op}")
        b.arm(CUT, op)
        b.start()
        try:
            assert _update_until_cut(b, img) == (op < r + 2), op
            h = power_cycle(b)
            assert (h.firmware_version, h.mark) == outcome(op), op
        finally:
            b.kill()
