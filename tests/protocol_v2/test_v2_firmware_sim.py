"""Firmware update with rollback on the virtual board: the host killed at every chunk, power cut
at every flash operation (uploads, the boot record, the bootloader), refusals before the switch."""

from __future__ import annotations

import contextlib
import hashlib
import time

import pytest
from crc32c import crc32c

from spiel_edge.cli import main
from spiel_edge.device import DeviceSession
from spiel_edge.device.firmware import firmware_info, update_firmware
from spiel_edge.errors import DeviceError, DeviceRequestError
from spiel_edge.protocol.link_messages import BootState, FwBegin, FwVerify
from spiel_edge.sim.protocol_sim import device_for_url
from tests.fwsign import signed_image

NEW = signed_image(b"SIM:OK " + bytes(range(256)) * 12, version="sim-0.2.0", target="sim")


class Killed(Exception):
    """The host died here."""


def hello_version(url: str, timeout_s: float = 5.0) -> str:
    """The firmware version the board answers HELLO with (waiting while it reboots)."""
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            with DeviceSession(url, reconnect=False) as dev:
                return dev.hello.firmware_version
        except DeviceError:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.05)


def reset(url: str) -> None:
    device = device_for_url(url)
    device.unplug(device.clock(), 0.05)


def test_update_confirms_a_firmware_that_answers(sim_url) -> None:
    url = sim_url("max_payload=512")
    result = update_firmware(url, NEW, boot_wait_s=10)
    assert result.confirmed and not result.rolled_back and result.version == "sim-0.2.0"
    with DeviceSession(url, reconnect=False) as dev:
        info = firmware_info(dev)
        assert dev.hello.firmware_version == "sim-0.2.0"
        assert info.boot_state == BootState.CONFIRMED and info.confirmed_slot == 1
    reset(url)  # a reset keeps it
    assert hello_version(url) == "sim-0.2.0"


def test_a_reboot_that_repeats_the_boot_id_is_seen_by_the_clock(sim_url, caplog) -> None:
    """A port with a weak random source can draw the same boot_id at the next boot (the mps2
    target did, one boot in hundreds): the host then sees the reboot by the board's clock,
    us since boot, behind where it stood at FW_TEST."""
    url = sim_url()
    board = device_for_url(url).board
    board._rng.getrandbits = lambda bits: 0x5EED  # every boot draws the same id
    board.boot_id = 0x5EED
    board._boot_time -= 5.0  # up for 5 s: its clock after the reboot is behind FW_TEST's
    with caplog.at_level("WARNING", logger="spiel_edge.device.firmware_outcome"):
        result = update_firmware(url, NEW, boot_wait_s=5)
    assert result.confirmed and result.version == "sim-0.2.0"
    assert "same boot_id" in caplog.text


def test_a_firmware_that_never_answers_is_rolled_back(sim_url) -> None:
    url = sim_url("watchdog_ms=500")
    silent = signed_image(b"SIM:SILENT", version="sim-bad", target="sim")
    result = update_firmware(url, silent, boot_wait_s=10)
    assert result.rolled_back and not result.confirmed and result.version == "sim-0.1.0"
    assert hello_version(url) == "sim-0.1.0"


def test_host_killed_at_every_chunk_leaves_the_old_firmware_running(sim_url) -> None:
    url = sim_url("max_payload=512")
    chunks = -(-len(NEW) // (512 - 6))
    assert chunks >= 6
    for k in range(1, chunks + 1):

        def progress(sent, total, k=k):
            if sent >= k * (512 - 6) or sent == total:
                raise Killed

        with pytest.raises(Killed):
            update_firmware(url, NEW, progress=progress)
        assert hello_version(url) == "sim-0.1.0", k
    assert update_firmware(url, NEW, boot_wait_s=10).confirmed


@pytest.mark.parametrize("stop_after", ["verify", "test"])
def test_host_killed_after_verify_or_test(sim_url, stop_after) -> None:
    url = sim_url()
    sha, crc = hashlib.sha256(NEW).digest(), crc32c(NEW)
    with DeviceSession(url, reconnect=False) as dev:
        dev.request(FwBegin(len(NEW), crc, sha))
        from spiel_edge.protocol.link_messages import FwTest, FwWrite

        dev.request(FwWrite(0, NEW))
        dev.request(FwVerify())
        if stop_after == "test":
            dev.request(FwTest(10))
    # the host is gone; the board runs the test image once (nobody confirms it) ...
    time.sleep(0.5)
    version = hello_version(url)
    assert version == ("sim-0.2.0" if stop_after == "test" else "sim-0.1.0")
    reset(url)  # ... and its next reset rolls back
    assert hello_version(url) == "sim-0.1.0"


def test_power_cut_at_every_flash_operation_boots_a_complete_image(sim_url) -> None:
    reference = sim_url("max_payload=1024")
    assert update_firmware(reference, NEW, boot_wait_s=6).confirmed
    ops = device_for_url(reference).board.fw.ops  # erase, chunks, records, boot, confirm
    assert ops >= 8
    outcomes = set()
    for cut in range(ops):
        url = sim_url(f"max_payload=1024&fw_power_cut={cut}")
        device = device_for_url(url)
        with contextlib.suppress(DeviceError):  # cut mid-request: the board vanishes
            update_firmware(url, NEW, boot_wait_s=6)
        version = hello_version(url)  # it answers HELLO: a complete image runs
        fw = device.board.fw
        assert version in ("sim-0.1.0", "sim-0.2.0") and fw.header(fw.running) is not None, cut
        assert fw.cut_at == -1, cut  # the cut did happen
        outcomes.add(version)
    assert outcomes == {"sim-0.1.0", "sim-0.2.0"}


def test_refused_before_the_switch(sim_url, tmp_path, capsys) -> None:
    url = sim_url()
    sha, crc = hashlib.sha256(NEW).digest(), crc32c(NEW)
    with DeviceSession(url, reconnect=False) as dev:
        with pytest.raises(DeviceRequestError, match="does not fit") as exc:
            dev.request(FwBegin(1 << 20, crc, sha))
        assert exc.value.code == 7  # TOO_LARGE
        dev.request(FwBegin(len(NEW), crc, hashlib.sha256(b"other").digest()))
        from spiel_edge.protocol.link_messages import FwTest, FwWrite

        dev.request(FwWrite(0, NEW))
        with pytest.raises(DeviceRequestError, match="SHA-256") as exc:
            dev.request(FwVerify())
        assert exc.value.code == 9  # CORRUPT
        with pytest.raises(DeviceRequestError) as exc:
            dev.request(FwTest(10))
        assert exc.value.code == 6  # BAD_STATE: nothing verified, nothing switched
    # the CLI refuses damaged, foreign and incompatible images before the port is touched
    cases = {
        "truncated": (NEW[:-10], "truncated"),
        "hash": (NEW[:200] + bytes([NEW[200] ^ 1]) + NEW[201:], "corrupt"),
        "protocol": (
            signed_image(b"SIM:OK", version="v9", target="sim", min_protocol=3, max_protocol=4),
            "protocol 3-4",
        ),
        "target": (signed_image(b"SIM:OK", version="v9", target="mps2-an386"), "target"),
        "large": (signed_image(b"SIM:OK" * 20000, version="big", target="sim"), "larger than"),
    }
    for name, (image, message) in cases.items():
        path = tmp_path / f"{name}.img"
        path.write_bytes(image)
        assert main(["firmware", "update", "--port", url, str(path)]) == 2, name
        assert message in capsys.readouterr().err, name
    assert hello_version(url) == "sim-0.1.0"
    assert device_for_url(url).board.fw.lengths[1] in (0, len(NEW))  # never switched to it


def test_the_cli_says_what_a_failed_upload_leaves(sim_url, tmp_path, capsys) -> None:
    """A power cut while the image is uploaded: one error on a line of its own (not after
    the progress), saying the running firmware stays and to run the update again; a bad
    --wait is refused before the board is touched; pack names the value at fault."""
    path = tmp_path / "new.img"
    path.write_bytes(signed_image(bytes(range(256)) * 200, version="sim-0.2.0", target="sim"))
    url = sim_url("max_payload=1024&fw_power_cut=3")
    capsys.readouterr()
    assert main(["firmware", "update", "--port", url, str(path)]) == 2
    err = capsys.readouterr().err
    last = err.rstrip("\n").splitlines()[-1]
    assert last.startswith("error:") and "keeps firmware sim-0.1.0" in last, err
    assert "run the update again" in last
    assert hello_version(url) == "sim-0.1.0"
    quiet = sim_url()
    assert main(["firmware", "update", "--port", quiet, str(path), "--wait", "-5"]) == 2
    assert "--wait" in capsys.readouterr().err and device_for_url(quiet).board.fw.ops == 0
    body = tmp_path / "body.bin"
    body.write_bytes(b"SIM:OK")
    base = ["firmware", "pack", str(body), "-o", str(tmp_path / "x.img")]
    for extra, words in (
        (["--version", "1" * 17, "--target", "sim"], "version must be 1 to 16 bytes"),
        (["--version", "1", "--target", ""], "target must be 1 to 16 bytes"),
        (["--version", "1", "--target", "sim", "--protocol", "x"], "--protocol must be LOW-HIGH"),
    ):
        assert main([*base, *extra]) == 2
        err = capsys.readouterr().err
        assert words in err and ("--protocol" in err) == ("--protocol" in extra), err


def test_firmware_info_and_a_version_1_board(sim_url, capsys) -> None:
    url = sim_url()
    assert main(["firmware", "info", "--port", url]) == 0
    out = capsys.readouterr().out
    assert "target sim" in out and "slot 0: verified, version sim-0.1.0" in out
    assert main(["firmware", "info", "--port", sim_url("protocol=1")]) == 2
    assert "does not offer firmware update (protocol 1)" in capsys.readouterr().err


def test_virtual_board_sensorless_trial_fails_its_self_test_and_rolls_back(sim_url) -> None:
    """The virtual board runs the C core's self-test: with no sensor the trial refuses
    FW_CONFIRM, resets itself and rolls back; the host reports the state it reports after."""
    url = sim_url("no_sensor=1")
    result = update_firmware(url, NEW, boot_wait_s=10)
    assert (result.outcome, result.version) == ("rolled back", "sim-0.1.0")
    assert "self-test failed" in result.reason
    with DeviceSession(url, reconnect=False) as dev:
        info = firmware_info(dev)
        assert (info.boot_state, info.selftest, info.running_slot) == (0, 0, info.confirmed_slot)


def test_virtual_board_trial_nobody_confirms_rolls_back_after_its_window(sim_url) -> None:
    """A host killed after FW_TEST: the trial passes its self-test, FW_INFO says so, and with
    nobody confirming it the watchdog resets it after the trial window: rolled back."""
    from spiel_edge.protocol.link_messages import FwConfirm, FwTest, SelfTest

    url = sim_url("trial_window_ms=1500")
    with DeviceSession(url, reconnect=False) as dev:
        dev.request(FwBegin(len(NEW), crc32c(NEW), hashlib.sha256(NEW).digest()))
        from spiel_edge.protocol.link_messages import FwWrite

        for off in range(0, len(NEW), 1000):
            dev.request(FwWrite(off, NEW[off : off + 1000]))
        dev.request(FwVerify())
        dev.request(FwTest(50))
    deadline = time.monotonic() + 5
    while hello_version(url) != "sim-0.2.0":  # the test boot
        assert time.monotonic() < deadline
        time.sleep(0.05)
    with DeviceSession(url, reconnect=False) as dev:
        info = firmware_info(dev)
        assert info.boot_state == BootState.TRIAL
        if info.selftest != SelfTest.PASSED:  # before the first acquisition: refused
            with pytest.raises(DeviceRequestError, match="self-test"):
                dev.request(FwConfirm())
    deadline = time.monotonic() + 10
    while hello_version(url) != "sim-0.1.0":
        assert time.monotonic() < deadline
        time.sleep(0.1)


def test_a_silent_image_of_the_same_version_is_reported_rolled_back(sim_url) -> None:
    """Issue 43: an image with the running image's own version that never answers: the
    watchdog rolls it back, and the host must not take the old image's HELLO (same version)
    for the new one: the outcome comes from the slot the board reports."""
    from spiel_edge.sim.firmware_slots import FACTORY_VERSION, SILENT_MARK

    url = sim_url("watchdog_ms=500")
    same = signed_image(SILENT_MARK + bytes(300), version=FACTORY_VERSION, target="sim")
    result = update_firmware(url, same, boot_wait_s=10)
    assert (result.outcome, result.version, result.confirmed) == (
        "rolled back",
        FACTORY_VERSION,
        False,
    )
    with DeviceSession(url, reconnect=False) as dev:
        info = firmware_info(dev)
        assert (info.running_slot, info.boot_state) == (result.slot, BootState.CONFIRMED)
        assert info.running_slot == info.confirmed_slot != 1


def test_a_self_test_that_does_not_finish_is_reported_as_the_trial_it_is(
    sim_url, monkeypatch
) -> None:
    """Issue 43: the trial runs but its self-test has not finished when the host stops
    waiting: the update is reported as "trial" (not confirmed, not rolled back, with why), and
    that is what the board reports afterwards: the new slot, on trial, unconfirmed."""
    from spiel_edge.sim.board_link_services import BoardLinkServices

    monkeypatch.setattr(BoardLinkServices, "SELFTEST_S", 30.0)  # longer than the host waits
    url = sim_url()
    image = signed_image(bytes(300), version="9.1.0", target="sim")
    result = update_firmware(url, image, boot_wait_s=2)
    assert (result.outcome, result.version, result.confirmed) == ("trial", "9.1.0", False)
    assert "self-test did not finish within 2 s" in result.reason
    with DeviceSession(url, reconnect=False) as dev:
        info = firmware_info(dev)
        assert (info.running_slot, info.boot_state) == (result.slot, BootState.TRIAL)
        assert info.confirmed_slot != result.slot


def test_a_pending_test_boot_is_explained_and_the_next_update_finishes_it(sim_url, capsys) -> None:
    """Issue 43: a host that died between FW_TEST and the test boot leaves TEST_PENDING:
    `firmware info` says what it means and what to do; `firmware update` finishes it."""
    from spiel_edge.device.firmware_requests import upload_image
    from spiel_edge.protocol.link_messages import FwTest

    url = sim_url()
    image = signed_image(bytes(300), version="9.2.0", target="sim")
    with DeviceSession(url, reconnect=False) as dev:
        upload_image(dev, url, image, crc32c(image), hashlib.sha256(image).digest(), None)
        dev.request(FwTest(60_000))  # the reset a minute away: the host dies before it
    assert main(["firmware", "info", "--port", url]) == 0
    out = capsys.readouterr().out
    assert "test pending" in out and "slot 1's image boots once, on trial" in out, out
    result = update_firmware(url, image, boot_wait_s=10)
    assert (result.outcome, result.version, result.slot) == ("confirmed", "9.2.0", 1)
