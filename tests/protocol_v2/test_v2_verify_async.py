"""FW_VERIFY's ASYNC flag (PROTOCOL.md § 14.3): the board answers BUSY and checks in its main
loop; the host asks again, waiting through the silence of the check itself, only once the board
said BUSY. On the virtual board (a check that takes time) and against scripted answers."""

from __future__ import annotations

import hashlib

import pytest
from crc32c import crc32c

from spiel_edge.device import DeviceSession
from spiel_edge.device import firmware_requests as fw
from spiel_edge.device.firmware import update_firmware, verify_upload
from spiel_edge.errors import DeviceRequestError, DeviceTimeoutError
from spiel_edge.protocol import ErrorCode
from spiel_edge.protocol.link_messages import (
    FwBegin,
    FwTest,
    FwVerify,
    FwVerifyFlag,
    FwVerifyResponse,
    FwWrite,
)
from spiel_edge.sim.protocol_sim import device_for_url
from tests.fwsign import signed_image

NEW = signed_image(b"SIM:" + bytes(range(256)) * 8, version="sim-0.2.0", target="sim")
OK = FwVerifyResponse(1, 100, 0, b"\0" * 32)


class Scripted:
    """A session whose FW_VERIFY answers follow a script: an exception class or an answer."""

    url = "scripted://"

    def __init__(self, *script) -> None:
        self.script, self.asked = list(script), []

    def request(self, msg, **options):
        assert options == {"retry_busy": False}  # BUSY must come back to verify_upload
        self.asked.append(msg)
        step = self.script.pop(0)
        if step is DeviceTimeoutError:
            raise DeviceTimeoutError("no answer")
        if step is DeviceRequestError:
            raise DeviceRequestError("busy", ErrorCode.BUSY, msg.MSG_TYPE)
        return step


@pytest.fixture(autouse=True)
def fast_poll(monkeypatch) -> None:
    monkeypatch.setattr(fw, "VERIFY_POLL_S", 0.0)


def test_the_host_asks_again_through_busy_and_the_checks_silence() -> None:
    s = Scripted(DeviceRequestError, DeviceTimeoutError, DeviceTimeoutError, DeviceRequestError, OK)
    assert verify_upload(s) == OK
    assert all(m == FwVerify(FwVerifyFlag.ASYNC) for m in s.asked) and len(s.asked) == 5


def test_a_silent_board_that_never_said_busy_is_not_waited_for() -> None:
    s = Scripted(DeviceTimeoutError, OK)
    with pytest.raises(DeviceTimeoutError):
        verify_upload(s)
    assert len(s.asked) == 1


def test_a_board_busy_past_the_wait_is_an_error(monkeypatch) -> None:
    monkeypatch.setattr(fw, "VERIFY_WAIT_S", 0.0)
    s = Scripted(DeviceRequestError, DeviceRequestError, OK)
    with pytest.raises(DeviceRequestError) as err:
        verify_upload(s)
    assert err.value.code == ErrorCode.BUSY


def upload(dev) -> None:
    dev.request(FwBegin(len(NEW), crc32c(NEW), hashlib.sha256(NEW).digest()))
    step = min(dev.max_payload, 1024) - 6
    for off in range(0, len(NEW), step):
        dev.request(FwWrite(off, NEW[off : off + step]))


def test_the_virtual_board_answers_busy_until_its_check_is_done(sim_url) -> None:
    url = sim_url()
    device_for_url(url).board.verify_s = 0.3
    with DeviceSession(url, reconnect=False) as dev:
        upload(dev)
        with pytest.raises(DeviceRequestError) as err:  # BUSY, asked again 3 times in 0.15 s
            dev.request(FwVerify(FwVerifyFlag.ASYNC))
        assert err.value.code == ErrorCode.BUSY
        with pytest.raises(DeviceRequestError) as err:  # FW_TEST only after the result
            dev.request(FwTest(10))
        assert err.value.code == ErrorCode.BAD_STATE
        answer = verify_upload(dev)
        assert (answer.image_size, answer.sha256) == (len(NEW), hashlib.sha256(NEW).digest())
        assert dev.request(FwVerify(FwVerifyFlag.ASYNC)) == answer  # kept until the upload changes
        assert dev.request(FwVerify()) == answer  # without the flag: within the request


def test_an_update_waits_for_a_slow_check(sim_url) -> None:
    url = sim_url()
    device_for_url(url).board.verify_s = 1.0
    result = update_firmware(url, NEW, boot_wait_s=10)
    assert result.confirmed and result.version == "sim-0.2.0"


def test_an_update_waits_through_a_check_that_blocks_the_board(sim_url) -> None:
    """As the C core: BUSY, then nothing read for longer than four tries of a request (the
    emulated Pico at load 8-12); the host knows the board is checking and waits it through."""
    url = sim_url()
    board = device_for_url(url).board
    board.verify_s, board.verify_blocks = 2.5, True
    result = update_firmware(url, NEW, boot_wait_s=10)
    assert result.confirmed and result.version == "sim-0.2.0"
