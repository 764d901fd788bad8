"""Firmware update timing on the C reference firmware (posix target, and mps2-an386 under qemu
when its tools are installed): the whole `update_firmware` (upload, verify, test boot with the
boot stage's flash-to-flash install, self-test, confirm), the upload alone, the longest single
FW_WRITE (where a sector erase falls), the first chunk with FW_BEGIN and the image operations
(erases and writes, the boot stage's included) the update took.

    python -m tools.bench.fw_update_time [--json] [--no-qemu] [--rp2040]

--rp2040 adds the full RP2040 application in the rp2040js emulator (opt-in: the emulator keeps a
core busy for about a minute): FW_VERIFY alone (BUSY, then the result; the board hashes the slot
and checks the Ed25519 signature), then the whole update.

Run from the repository's root (it uses the tests' board helpers). Prints one line per case.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

from spiel_edge.device.firmware import update_firmware
from spiel_edge.protocol.image import pack_image as _pack


def _signed(body: bytes, **kw) -> bytes:
    """An image signed with the development key (what boards built from this tree trust)."""
    from spiel_edge.device.fwkeys import load_private_key

    key = Path(__file__).resolve().parents[2] / "firmware_protocol/firmware/keys/dev.key"
    return _pack(body, signer=load_private_key(key), **kw)


def _timed(port: str, image: bytes) -> dict:
    marks: list[float] = []
    t0 = time.monotonic()

    def progress(sent: int, total: int) -> None:
        marks.append(time.monotonic())

    result = update_firmware(port, image, progress=progress, boot_wait_s=60)
    gaps = [b - a for a, b in zip([t0, *marks[:-1]], marks, strict=True)]
    return {
        "outcome": result.outcome,
        "bytes": len(image),
        "chunks": len(marks),
        "seconds": round(result.seconds, 2),
        "upload_s": round(marks[-1] - t0, 2),
        "after_upload_s": round(result.seconds - (marks[-1] - t0), 2),
        # the first: connect, HELLO, FW_INFO, FW_BEGIN (its one sector erase), the first chunk
        "first_chunk_ms": round(1000 * gaps[0], 1),
        # the rest: one FW_WRITE each, with the sector erase where the upload reaches one
        "longest_write_ms": round(1000 * max(gaps[1:]), 1),
    }


def posix_case(tmp: Path) -> dict:
    from spiel_edge.data import load_subset
    from tests.firmware.firmware import PosixBoard, build_posix
    from tools.release.firmware_scans import write_scans

    exe = build_posix(tmp / "build")
    scans = write_scans(tmp / "scans.spas", load_subset().frames[:20], 22000)
    images = tmp / "images"
    images.mkdir()
    (images / "slot0.img").write_bytes(_signed(exe.read_bytes(), version="p-1.0", target="posix"))
    image = _signed(exe.read_bytes(), version="p-1.1", target="posix")
    with PosixBoard(exe, scans, tmp / "flash.bin", "--images", str(images)) as b:
        row = _timed(b.port, image)
        row["image_ops"] = int.from_bytes((images / ".image_ops").read_bytes()[:8], "little")
    return {"case": "posix: the firmware binary as image, slot 0 -> 1", **row}


def qemu_cases(tmp: Path) -> list[dict]:
    from tests.firmware.qemu_board import (
        QemuBoard,
        app_bin,
        build_mps2,
        missing_tools,
        new_flash,
    )

    why = missing_tools()
    if why:
        return [{"case": "mps2-an386", "skipped": why}]
    elf = build_mps2(tmp)
    body = app_bin(elf).read_bytes()
    rows = []
    board = QemuBoard(elf, new_flash(tmp / "psram.bin"))
    board.arm(1, 1 << 30)  # the mailbox counts the flash operations, never cuts
    with board as b:
        for version, what in (("m-1.1", "built-in -> slot 0"), ("m-1.2", "slot 0 -> 1")):
            before = b.mailbox()["ops"]
            row = _timed(b.port, _signed(body, version=version, target="mps2-an386"))
            row["flash_ops"] = b.mailbox()["ops"] - before
            rows.append({"case": f"mps2-an386 (qemu): the full application, {what}", **row})
    return rows


def rp2040_case(tmp: Path) -> dict:
    import hashlib

    from crc32c import crc32c

    from spiel_edge.device import DeviceSession
    from spiel_edge.device.firmware import verify_upload
    from spiel_edge.protocol.link_messages import FwBegin, FwWrite
    from tests.firmware.rp2040_board import Rp2040Board, build_rp2040, missing_tools

    why = missing_tools()
    if why:
        return {"case": "rp2040", "skipped": why}
    uf2 = build_rp2040(tmp)
    body = uf2.with_name("app-emu.bin").read_bytes()
    image = _signed(body, version="r-1.1", target="rp2040")
    with Rp2040Board(uf2, tmp / "emulator.log") as pico:
        pico.start()
        with DeviceSession(pico.port, reconnect=False) as dev:
            dev.request(FwBegin(len(image), crc32c(image), hashlib.sha256(image).digest()))
            step = min(dev.max_payload, 1024) - 6
            for off in range(0, len(image), step):
                dev.request(FwWrite(off, image[off : off + step]))
            t0 = time.monotonic()
            verify_upload(dev)
            verify_s = time.monotonic() - t0
        row = _timed(pico.port, image)
    return {
        "case": "rp2040 (rp2040js): the full application, slot 0 -> 1",
        "verify_s": round(verify_s, 2),
        **row,
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--no-qemu", action="store_true")
    ap.add_argument("--rp2040", action="store_true")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as d:
        rows = [posix_case(Path(d) / "posix")]
        if not args.no_qemu:
            rows += qemu_cases(Path(d) / "qemu")
        if args.rp2040:
            rows.append(rp2040_case(Path(d) / "rp2040"))
    for row in rows:
        print(json.dumps(row) if args.json else "  ".join(f"{k}={v}" for k, v in row.items()))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
