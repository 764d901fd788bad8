"""Signed images on the C firmware (posix target): the vendored verifier against RFC 8032 and
the cryptography package, the build's key (FW_KEY, RELEASE=1 refusing the development key),
the boot stage starting only a signed slot, FW_VERIFY refusing every forged, tampered, unsigned
or downgraded image with its code, and a power cut during the security counter's update.
Always runs (needs only the system C compiler and make)."""

from __future__ import annotations

import contextlib
import os
import subprocess
from pathlib import Path

import pytest

from spiel_edge.device import DeviceSession
from spiel_edge.device.firmware import update_firmware
from spiel_edge.errors import DeviceError
from tests.firmware.firmware import FIRMWARE, PosixBoard, build_test_driver
from tests.fwsign import signed_image
from tests.protocol_v2.signing_cases import forged_images, other_signer, raw_upload
from tests.protocol_v2.test_v2_firmware_posix import hello_version, script_image
from tests.protocol_v2.test_v2_signing import RFC8032, flips


@pytest.fixture(scope="module")
def verifier(tmp_path_factory) -> Path:
    src = Path(__file__).parents[1] / "firmware" / "ed25519_driver.c"
    return build_test_driver(tmp_path_factory.mktemp("ed25519"), src, "ed25519")


def c_check(exe: Path, cases: list[tuple[bytes, bytes, bytes]]) -> list[bool]:
    lines = "".join(f"{pk.hex()} {msg.hex() or '-'} {sig.hex()}\n" for pk, msg, sig in cases)
    done = subprocess.run([str(exe)], input=lines, capture_output=True, text=True, check=True)
    return [v == "0" for v in done.stdout.split()]


def test_the_vendored_verifier_takes_rfc8032_and_refuses_bit_flips(verifier) -> None:
    cases, want = [], []
    for _, pk, msg, sig in RFC8032:
        pk, msg, sig = bytes.fromhex(pk), bytes.fromhex(msg), bytes.fromhex(sig)
        cases.append((pk, msg, sig))
        want.append(True)
        cases += [(pk, msg, s) for s in flips(sig, 3)] + [(k, msg, sig) for k in flips(pk, 3)]
        cases.append((pk, msg + b"\x00", sig))
        want += [False] * (len(cases) - len(want))
    assert c_check(verifier, cases) == want


def test_the_vendored_verifier_agrees_with_cryptography(verifier) -> None:
    from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey
    from cryptography.hazmat.primitives.serialization import Encoding, PublicFormat

    cases = []
    for n in range(40):
        key = Ed25519PrivateKey.generate()
        pk = key.public_key().public_bytes(Encoding.Raw, PublicFormat.Raw)
        msg = os.urandom(n * 13)
        cases.append((pk, msg, key.sign(msg)))
        cases.append((pk, msg + b"x", key.sign(msg)))
    assert c_check(verifier, cases) == [True, False] * 40


def make(*args: str) -> subprocess.CompletedProcess:
    cmd = ["make", "-n", "-C", str(FIRMWARE), "TARGET=posix", "BUILD=/nonexistent", *args]
    return subprocess.run(cmd, capture_output=True, text=True)


@pytest.mark.skipif(not __import__("shutil").which("make"), reason="no make")
def test_a_release_build_refuses_the_development_key(tmp_path) -> None:
    done = make("RELEASE=1")
    assert done.returncode != 0 and "refuses the development key" in done.stderr
    other_signer(tmp_path)  # other.key, other.pub
    assert make("RELEASE=1", f"FW_KEY={tmp_path / 'other.pub'}").returncode == 0
    copied = tmp_path / "copy.pub"  # the development key under another name and comment
    copied.write_text((FIRMWARE / "keys" / "dev.pub").read_text().replace("DEVELOPMENT", "x"))
    assert "refuses the development key" in make("RELEASE=1", f"FW_KEY={copied}").stderr
    assert "no such public key file" in make(f"FW_KEY={tmp_path / 'none.pub'}").stderr
    (tmp_path / "junk.pub").write_text("0x01, 0x02,\n")
    assert "not a public key file" in make(f"FW_KEY={tmp_path / 'junk.pub'}").stderr


def posix_board(posix, case: Path, factory: bytes, *extra: str) -> PosixBoard:
    exe, scans = posix
    images = case / "images"
    if not images.exists():
        images.mkdir(parents=True)
        (images / "slot0.img").write_bytes(factory)
    return PosixBoard(exe, scans, case / "flash.bin", "--images", str(images), *extra)


def test_the_boot_stage_starts_only_a_signed_slot(posix, tmp_path) -> None:
    """slot 0 holds the only image: unsigned, tampered or signed by another key, the boot stage
    does not start it (the recovery loader answers); signed by the build's key, it runs."""
    good = signed_image(posix[0].read_bytes(), version="posix-1.0.0", target="posix")
    forged = forged_images(good, other_signer(tmp_path))
    for name in ("unsigned", "tampered body", "wrong key", "truncated signature"):
        with posix_board(posix, tmp_path / name.replace(" ", "-"), forged[name][0]) as b:
            assert hello_version(b.port) == "recovery", name
    with posix_board(posix, tmp_path / "good", good) as b:
        # installing a 1.5 MB sanitizer build unit by unit takes ~13 s (SPIEL_FW_SANITIZE=1)
        assert hello_version(b.port, 60) == "posix-1.0.0"


def test_fw_verify_refuses_forged_images(posix, tmp_path) -> None:
    factory = signed_image(posix[0].read_bytes(), version="posix-1.0.0", target="posix")
    good = script_image(posix, "posix-1.1.0")
    with posix_board(posix, tmp_path, factory) as b:
        for name, (bad, code) in forged_images(good, other_signer(tmp_path)).items():
            assert raw_upload(b.port, bad) == code, name
        assert raw_upload(b.port, good) is None
        with DeviceSession(b.port, reconnect=False) as dev:
            assert dev.hello.firmware_version == "posix-1.0.0"


def counter_image(posix, version: str, counter: int) -> bytes:
    body = f'#!/bin/sh\nexec "{posix[0]}" "$@"\n# {version}\n'.encode()
    return signed_image(body, version=version, target="posix", security_counter=counter)


def test_a_downgrade_is_refused_and_the_host_says_why(posix, tmp_path) -> None:
    factory = signed_image(posix[0].read_bytes(), version="posix-1.0.0", target="posix")
    with posix_board(posix, tmp_path, factory) as b:
        assert update_firmware(
            b.port, counter_image(posix, "posix-1.5.0", 5), boot_wait_s=15
        ).confirmed
        with pytest.raises(DeviceError) as err:
            update_firmware(b.port, counter_image(posix, "posix-1.3.0", 3), boot_wait_s=15)
        line = str(err.value)
        assert "\n" not in line and "FW_ROLLBACK" in line and "keeps firmware posix-1.5.0" in line
        assert update_firmware(
            b.port, counter_image(posix, "posix-1.5.1", 5), boot_wait_s=15
        ).confirmed


def test_a_power_cut_during_the_counters_update_keeps_old_or_new(posix, tmp_path) -> None:
    """The counter rises with FW_CONFIRM's boot record (the last two image operations of an
    update: the record sector's erase and its write). SIGKILL in either, or none: the board
    comes back with the old image and counter 0 (a counter-3 image accepted) or the new one
    and counter 5 (refused as FW_ROLLBACK), never the new image with the old counter."""
    factory = signed_image(posix[0].read_bytes(), version="posix-1.0.0", target="posix")
    v5, v3 = counter_image(posix, "posix-1.5.0", 5), counter_image(posix, "posix-1.3.0", 3)
    count = tmp_path / "count"
    with posix_board(posix, count, factory) as b:
        assert update_firmware(b.port, v5, boot_wait_s=15).confirmed
    ops = int.from_bytes((count / "images" / ".image_ops").read_bytes()[:8], "little")
    seen = set()
    for cut in (ops - 2, ops - 1, ops):
        case = tmp_path / f"cut{cut}"
        b = posix_board(posix, case, factory, "--image-cut", str(cut))
        b.start()
        try:
            with contextlib.suppress(DeviceError):
                update_firmware(b.port, v5, boot_wait_s=4)
        finally:
            b.stop()
        with posix_board(posix, case, factory) as again:
            version = hello_version(again.port)
            seen.add(version)
            answer = raw_upload(again.port, v3)
            if version == "posix-1.5.0":
                assert answer == "FW_ROLLBACK", cut
            else:
                assert version == "posix-1.0.0" and answer is None, (cut, version, answer)
    assert seen == {"posix-1.0.0", "posix-1.5.0"}


def test_the_fuzz_harness_image_is_signed_by_the_development_key() -> None:
    """fuzz_request.c's slot-0 image carries a stored trailer: the one keys/dev.key makes."""
    import re

    src = (FIRMWARE / "fuzz" / "fuzz_request.c").read_text()
    block = src.split("image0_trailer[SP_SIG_TRAILER_SIZE] = {", 1)[1].split("}", 1)[0]
    stored = bytes(int(h, 16) for h in re.findall(r"0x([0-9a-f]{2})", block))
    body = bytes((i * 7 + 1) & 0xFF for i in range(160))
    assert signed_image(body, version="1.0.0+fuzz", target="posix")[-80:] == stored
