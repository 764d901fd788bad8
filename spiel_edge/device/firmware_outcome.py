"""After the test boot: the same board found again (serial number and target checked at every
reconnection, a reboot told by its boot_id or its clock), its trial's self-test awaited, the
image confirmed only when it passed, and the outcome the board itself reports afterwards."""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass

from spiel_edge.device.firmware_requests import (
    board_clock_us,
    confirm_firmware,
    firmware_info,
)
from spiel_edge.errors import DeviceError, DeviceRequestError
from spiel_edge.protocol.link_messages import BootState, FwInfo, SelfTest
from spiel_edge.protocol.messages import Reboot, RebootMode
from spiel_edge.safety.shown import escape

log = logging.getLogger(__name__)

RETRY_OPEN_S = 0.2


@dataclass(frozen=True)
class UpdateResult:
    """What the board reports after the update (FW_INFO and HELLO of the same board)."""

    previous: str  # firmware version before
    version: str  # the version the board runs now
    confirmed: bool  # it runs the new image, confirmed (the state it reports)
    rolled_back: bool  # it runs the old image again
    bytes_sent: int
    seconds: float
    serial: str = ""  # the board (checked: the one the update started with)
    slot: int = 0xFF  # the running slot it reports
    boot_state: int = BootState.CONFIRMED
    reason: str = ""  # why it rolled back, or why it is still on trial

    @property
    def outcome(self) -> str:
        if self.confirmed:
            return "confirmed"
        return "rolled back" if self.rolled_back else "trial"


def _other_board(url: str, board: tuple[str, str], hello, target: str | None) -> str | None:
    serial, want_target = board
    if hello.serial != serial:
        return f"serial {escape(hello.serial)}"
    if target is not None and want_target and target != want_target:
        return f"target {escape(target)}"
    return None


def wait_for_board(url, open_session, board, before, wait_s, what):
    """The session of the same board once it rebooted (new boot_id, or its clock restarted);
    DeviceError in one line when another board answers at ``url`` or none does in time."""
    boot_id, clock_at_test = before
    deadline = time.monotonic() + wait_s
    last_error = "no answer"
    time.sleep(0.05)
    while time.monotonic() < deadline:
        try:
            session = open_session(url)
        except DeviceError as exc:
            last_error = str(exc)
            time.sleep(RETRY_OPEN_S)
            continue
        try:
            other = _other_board(url, board, session.hello, None)
            if other is None and _rebooted(session, boot_id, clock_at_test):
                info = firmware_info(session)
                other = _other_board(url, board, session.hello, info.target)
                if other is None:
                    return session
            if other is not None:
                raise DeviceError(
                    f"{url}: another board answers ({other}), not board {escape(board[0])} "
                    f"(target {escape(board[1])}) that was updated: {what} and nothing was "
                    f"confirmed; find board {escape(board[0])} and run `spiel-edge firmware "
                    "info` on it"
                )
        except DeviceRequestError as exc:
            last_error = str(exc)
        except DeviceError:
            close_quietly(session)
            raise
        close_quietly(session)
        time.sleep(RETRY_OPEN_S)
    raise DeviceError(
        f"{url}: no board answered within {wait_s:g} s ({last_error}): {what}; board "
        f"{escape(board[0])} rolls an unconfirmed trial back by itself (its watchdog), "
        "`spiel-edge firmware info` shows where it stands"
    )


class _TrialReset(Exception):
    """The trial resets itself (its self-test failed): wait for the board again."""


def _await_selftest(session, deadline: float) -> tuple[FwInfo, int]:
    """FW_INFO polled until the trial's self-test passed or failed (or ``deadline``)."""
    while True:
        info = firmware_info(session)
        if info.selftest in (SelfTest.PASSED, SelfTest.FAILED, SelfTest.NONE):
            return info, info.selftest
        if time.monotonic() >= deadline:
            return info, info.selftest
        time.sleep(0.05)


def settle(session, url, header, board, slot, previous, open_session, wait_s, sent, started):
    """After the test boot: wait for the trial's self-test, confirm it only when it passed,
    and report the state the board reports afterwards."""
    reason = ""
    try:
        info = firmware_info(session)
        hello = session.hello
        on_trial = (
            info.running_slot == slot
            and info.boot_state == BootState.TRIAL
            and hello.firmware_version == header.version
        )
        if on_trial:
            try:
                info, test = _await_selftest(session, time.monotonic() + wait_s)
                if test in (SelfTest.PASSED, SelfTest.NONE):  # NONE: a board without one
                    try:
                        confirm_firmware(session)
                    except DeviceRequestError as exc:
                        reason = f"FW_CONFIRM refused: {exc}"
                elif test == SelfTest.FAILED:
                    reason = (
                        "its self-test failed (the sensor did not answer or no acquisition "
                        "completed)"
                    )
                    raise _TrialReset
                else:
                    reason = f"its self-test did not finish within {wait_s:g} s"
            except (_TrialReset, DeviceError) as exc:
                if isinstance(exc, DeviceRequestError):
                    raise
                if not reason:  # the link went: the trial reset (crashed, or its watchdog)
                    reason = "the trial image reset before it was confirmed"
                boot_id = hello.boot_id
                close_quietly(session)
                session = wait_for_board(
                    url,
                    open_session,
                    board,
                    (boot_id, None),
                    wait_s,
                    f"firmware {escape(header.version)} is not confirmed",
                )
        elif hello.firmware_version != header.version or info.running_slot != slot:
            reason = (
                "the new firmware did not start or did not answer in time (its watchdog or a "
                "reset rolled it back, or the power went before its confirmation was stored)"
            )
        info = firmware_info(session)
        hello = session.hello
    finally:
        close_quietly(session)
    new = info.running_slot == slot and hello.firmware_version == header.version
    confirmed = new and info.boot_state == BootState.CONFIRMED and info.confirmed_slot == slot
    if new and not confirmed and not reason:
        reason = "it runs unconfirmed"
    result = UpdateResult(
        previous,
        hello.firmware_version,
        confirmed,
        not new,
        sent,
        time.monotonic() - started,
        hello.serial,
        info.running_slot,
        info.boot_state,
        reason,
    )
    log.info(
        "%s: board %s reports firmware %s, %s",
        url,
        escape(hello.serial),
        escape(hello.firmware_version),
        result.outcome,
    )
    return result


def roll_back_trial(session, url, board, open_session, wait_s):
    """A trial of another image (a host that died mid-update left it): reset the board so
    that its boot stage rolls it back, and return the session of the same board after."""
    hello = session.hello
    info = firmware_info(session)
    log.warning(
        "%s: board %s runs firmware %s on trial (an update that did not finish): rolling it "
        "back first",
        url,
        escape(hello.serial),
        escape(hello.firmware_version),
    )
    clock = board_clock_us(session)
    try:
        session.request(Reboot(RebootMode.NORMAL, 100))
    finally:
        close_quietly(session)
    session = wait_for_board(
        url,
        open_session,
        board,
        (hello.boot_id, clock),
        wait_s,
        "the unfinished trial was not rolled back",
    )
    info = firmware_info(session)
    if info.boot_state == BootState.TRIAL:
        close_quietly(session)
        raise DeviceError(f"{url}: the board stays on its trial image after a reset")
    return session


def _rebooted(session, boot_id: int, clock_at_test: int | None) -> bool:
    """A new boot_id, or (a board whose entropy gave the same one again) its clock, us since
    boot, behind where it stood at FW_TEST."""
    if session.hello.boot_id != boot_id:
        return True
    if clock_at_test is None:
        return False
    now = board_clock_us(session)
    if now is None or now >= clock_at_test:
        return False
    log.warning(
        "the board rebooted with the same boot_id %08x (its clock restarted): its random "
        "source is weak; boot_id should differ at every boot",
        boot_id,
    )
    return True


def open_board(url: str):
    from spiel_edge.device import DeviceSession

    session = DeviceSession(url, reconnect=False)
    session.open()
    return session


def close_quietly(session) -> None:
    try:
        session.close()
    except DeviceError as exc:
        log.debug("close: %s", exc)
