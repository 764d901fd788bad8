"""`firmware update` reports what the board did (issue 43 item 2, issue 37 item 6): the outcome
is the state the same board reports afterwards; another board at the same port is never
confirmed; a host killed after the test boot leaves a trial that `firmware info` explains and
the next `firmware update` resolves; a sensorless trial fails its self-test and rolls back."""

from __future__ import annotations

import pytest

from spiel_edge.cli import main
from spiel_edge.device import DeviceSession
from spiel_edge.device.firmware import firmware_info, update_firmware
from spiel_edge.device.firmware_requests import upload_image
from spiel_edge.errors import DeviceError
from spiel_edge.protocol.link_messages import FwTest, SelfTest
from tests.fwsign import signed_image
from tests.protocol_v2.test_v2_firmware_posix import board, script_image


def killed_after_test_boot(port: str, image: bytes) -> None:
    """A host that uploaded, sent FW_TEST and died before it confirmed."""
    import hashlib

    from crc32c import crc32c

    with DeviceSession(port, reconnect=False) as dev:
        upload_image(dev, port, image, crc32c(image), hashlib.sha256(image).digest(), None)
        dev.request(FwTest(100))


def wait_trial(port: str) -> None:
    import time

    deadline = time.monotonic() + 10
    while time.monotonic() < deadline:
        try:
            with DeviceSession(port, reconnect=False) as dev:
                info = firmware_info(dev)
                if info.boot_state == 1 and info.selftest == SelfTest.PASSED:
                    return
        except DeviceError:
            pass
        time.sleep(0.1)
    raise AssertionError("the board did not come back on trial")


def test_another_board_at_the_same_port_is_never_confirmed(posix, tmp_path) -> None:
    link = tmp_path / "ttyBOARD"
    image = script_image(posix, "posix-1.1.0")
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    a = board(posix, tmp_path / "a", "--link", str(link))
    other = board(posix, tmp_path / "b", "--link", str(link), "--serial", "POSIX0002")
    with a:

        def progress(sent, total):
            if sent == total:  # the cable goes to another board while this one tests
                other.start()

        try:
            with pytest.raises(DeviceError) as err:
                update_firmware(str(link), image, progress=progress, boot_wait_s=10)
            text = str(err.value)
            assert "another board answers (serial POSIX0002)" in text and "\n" not in text
            assert "nothing was confirmed" in text
            with DeviceSession(str(link), reconnect=False) as dev:  # the other one: untouched
                info = firmware_info(dev)
                assert (dev.hello.serial, info.boot_state, info.running_slot) == ("POSIX0002", 0, 0)
            with DeviceSession(a.port, reconnect=False) as dev:  # the updated one: its trial
                info = firmware_info(dev)  # not confirmed by anyone: pending or on trial
                assert info.boot_state in (1, 2) and info.confirmed_slot == 0
        finally:
            other.stop()


def test_host_killed_after_the_test_boot_info_explains_update_finishes(
    posix, tmp_path, capsys
) -> None:
    image = script_image(posix, "posix-1.1.0")
    with board(posix, tmp_path) as b:
        killed_after_test_boot(b.port, image)
        wait_trial(b.port)
        assert main(["firmware", "info", "--port", b.port]) == 0
        out = capsys.readouterr().out
        assert "on trial (self-test passed), left by an update that did not finish" in out
        result = update_firmware(b.port, image, boot_wait_s=10)  # the same image: finished
        assert (result.outcome, result.version, result.slot) == ("confirmed", "posix-1.1.0", 1)
        with DeviceSession(b.port, reconnect=False) as dev:
            info = firmware_info(dev)
            assert (info.running_slot, info.boot_state, info.confirmed_slot) == (1, 0, 1)


def test_host_killed_then_another_image_rolls_the_trial_back_first(posix, tmp_path) -> None:
    with board(posix, tmp_path) as b:
        killed_after_test_boot(b.port, script_image(posix, "posix-1.1.0"))
        wait_trial(b.port)
        result = update_firmware(b.port, script_image(posix, "posix-1.2.0"), boot_wait_s=10)
        # 1.1.0 rolled back to 1.0.0 in slot 0, then 1.2.0 written to slot 1 and confirmed
        assert (result.outcome, result.previous, result.version) == (
            "confirmed",
            "posix-1.0.0",
            "posix-1.2.0",
        )


def test_a_sensorless_trial_fails_its_self_test_and_rolls_back(posix, tmp_path) -> None:
    body = f'#!/bin/sh\nexec "{posix[0]}" "$@" --no-sensor\n'.encode()
    nosensor = signed_image(body, version="posix-nosensor", target="posix")
    with board(posix, tmp_path) as b:
        result = update_firmware(b.port, nosensor, boot_wait_s=10)
        assert (result.outcome, result.version, result.slot) == ("rolled back", "posix-1.0.0", 0)
        assert "self-test failed" in result.reason
        assert b.proc.poll() is None  # by itself: no power cycle
    out_line = result  # the CLI prints it in one line
    from spiel_edge.cli.firmware import update_outcome_line

    line = update_outcome_line(out_line, "posix-nosensor")
    assert "rolled back" in line and "\n" not in line and "runs posix-1.0.0 in slot 0" in line


def test_a_trial_that_crashes_at_start_is_rolled_back_and_reported_so(posix, tmp_path) -> None:
    """A trial that ends at once (a fault): the board resets (the posix boot stage takes an
    image that ends as a reset, as a fault handler would) and rolls back; the host reports the
    state the board reports: rolled back, the old slot, confirmed, never "confirmed"."""
    crash = signed_image(b"#!/bin/sh\nexit 1\n", version="posix-crash", target="posix")
    with board(posix, tmp_path) as b:
        result = update_firmware(b.port, crash, boot_wait_s=10)
        assert (result.outcome, result.version, result.slot, result.boot_state) == (
            "rolled back",
            "posix-1.0.0",
            0,
            0,
        )
        assert b.proc.poll() is None  # no power cycle
        with DeviceSession(b.port, reconnect=False) as dev:  # what it reports now: the same
            info = firmware_info(dev)
            assert (dev.hello.firmware_version, info.running_slot, info.boot_state) == (
                result.version,
                result.slot,
                result.boot_state,
            )
