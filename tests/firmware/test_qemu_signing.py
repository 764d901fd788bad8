"""Signed images on the Cortex-M4 (qemu mps2-an386): FW_VERIFY refuses every forged, tampered,
unsigned or truncated image with its code, the boot stage never starts a slot below the
record's security counter, a downgrade is refused with a one-line reason, and a power cut in
the security counter's update (FW_CONFIRM's record) leaves the old image with the old counter
or the new image with the new one. Skipped, naming the Debian package, where the Arm
toolchain or qemu is missing."""

from __future__ import annotations

import pytest

from spiel_edge.device.firmware import update_firmware
from spiel_edge.errors import DeviceError
from tests.firmware.qemu_board import CUT, QemuBoard, new_flash
from tests.firmware.test_qemu_update import (  # noqa: F401  (elf: the fixture)
    FACTORY,
    _update_until_cut,
    elf,
    hello,
    image,
    power_cycle,
)
from tests.protocol_v2.signing_cases import forged_images, other_signer, raw_upload

NEVER = 1 << 30  # an armed cut that never fires: the mailbox counts the operations


def test_forged_images_and_a_downgrade_are_refused(elf, tmp_path) -> None:  # noqa: F811
    good = image(elf, "mps2-1.2.0", "spiel-c m120", security_counter=2)
    low = image(elf, "mps2-1.1.9", "spiel-c m119", security_counter=1)
    with QemuBoard(elf, new_flash(tmp_path / "flash.bin")) as b:
        for name, (bad, code) in forged_images(good, other_signer(tmp_path)).items():
            assert raw_upload(b.port, bad) == code, name
        assert hello(b.port).firmware_version == FACTORY
        assert update_firmware(b.port, good, boot_wait_s=20).confirmed
        with pytest.raises(DeviceError) as err:
            update_firmware(b.port, low, boot_wait_s=20)
        line = str(err.value)
        assert "\n" not in line and "FW_ROLLBACK" in line and "keeps firmware mps2-1.2.0" in line
        h = power_cycle(b)
        assert h.firmware_version == "mps2-1.2.0"


def test_a_power_cut_during_the_counters_update_keeps_old_or_new(elf, tmp_path) -> None:  # noqa: F811
    """From the built-in image (counter 0) to a counter-5 image: SIGKILL-like stops in the
    middle of FW_CONFIRM's record erase and write (the update's last two flash operations),
    then qemu started again on the same flash: the built-in image with counter 0 (a counter-3
    image is accepted), or, with no cut, the new one with counter 5 (refused: FW_ROLLBACK)."""
    v5 = image(elf, "mps2-1.5.0", "spiel-c m150", security_counter=5)
    v3 = image(elf, "mps2-1.3.0", "spiel-c m130", security_counter=3)
    count = QemuBoard(elf, new_flash(tmp_path / "count.bin"))
    count.arm(CUT, NEVER)
    with count:
        assert update_firmware(count.port, v5, boot_wait_s=20).confirmed
        ops = count.mailbox()["ops"]
        assert raw_upload(count.port, v3) == "FW_ROLLBACK"
    seen = set()
    for op in (ops - 2, ops - 1):
        b = QemuBoard(elf, new_flash(tmp_path / f"cut{op}.bin"))
        b.arm(CUT, op)
        b.start()
        try:
            assert _update_until_cut(b, v5), op
            h = power_cycle(b)
            seen.add(h.firmware_version)
            assert h.firmware_version == FACTORY, op  # the trial was not confirmed: rolled back
            assert raw_upload(b.port, v3) is None, op  # the counter stayed 0
        finally:
            b.kill()
    assert seen == {FACTORY}
