"""Firmware update with rollback over a device session (PROTOCOL.md section 14.3).

``check_image`` refuses a damaged or foreign image before a byte is sent; ``update_firmware``
uploads it into the inactive slot in chunks sized by the link's payload, has the board verify
length, CRC-32C and SHA-256, boots it once ("test"), waits for it to answer HELLO and only then
confirms it. A board that does not come back with the new version rolled back by itself (or
will at its next reset): the host says which.
"""

from __future__ import annotations

import hashlib
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass

from crc32c import crc32c

from firmware_protocol import MAX_PAYLOAD, Capability, ErrorCode, Message
from firmware_protocol.image import ImageError, ImageHeader, parse_image
from firmware_protocol.messages import (
    MAX_PROTOCOL_VERSION,
    MIN_PROTOCOL_VERSION,
    Reboot,
    RebootMode,
)
from firmware_protocol.v2_messages import (
    BootState,
    FwBegin,
    FwBeginResponse,
    FwConfirm,
    FwConfirmResponse,
    FwInfo,
    FwInfoRequest,
    FwTest,
    FwVerify,
    FwVerifyFlag,
    FwVerifyResponse,
    FwWrite,
    FwWriteResponse,
    SelfTest,
    SlotState,
    TimeSync,
    TimeSyncResponse,
)
from spiel_edge.errors import DeviceError, DeviceRequestError, DeviceTimeoutError
from spiel_edge.io.shown import escape

log = logging.getLogger(__name__)

__all__ = [
    "UpdateResult",
    "check_image",
    "confirm_firmware",
    "describe_info",
    "firmware_info",
    "update_firmware",
    "verify_upload",
]

BOOT_WAIT_S = 20.0  # how long the host waits for the test image to answer HELLO
RETRY_OPEN_S = 0.2
WRITE_OVERHEAD = 6  # FW_WRITE's fixed part


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


def check_image(image: bytes) -> ImageHeader:
    """The image header, or DeviceError naming what is wrong (damaged, truncated, a protocol
    range this host cannot talk to once it runs)."""
    try:
        header = parse_image(image)
    except ImageError as exc:
        raise DeviceError(f"refused: {exc}") from exc
    if not header.signed:
        raise DeviceError(
            "refused: the image is not signed; boards boot only signed images "
            "(spiel-edge firmware pack --key KEY)"
        )
    if not header.speaks(MIN_PROTOCOL_VERSION, MAX_PROTOCOL_VERSION):
        raise DeviceError(
            f"refused: firmware {header.version} speaks protocol {header.min_protocol}-"
            f"{header.max_protocol}, this host {MIN_PROTOCOL_VERSION}-{MAX_PROTOCOL_VERSION}: "
            "it could never be confirmed"
        )
    return header


def _need_update_support(session) -> None:
    hello = session.hello
    if (
        hello is None
        or hello.protocol_version < 2
        or not hello.capabilities & Capability.FIRMWARE_UPDATE
    ):
        version = hello.protocol_version if hello is not None else "?"
        raise DeviceError(
            f"{session.url}: the board does not offer firmware update (protocol {version}); "
            "use the vendor's tool"
        )


def _ask(session, msg: Message, cls: type) -> Message:
    answer = session.request(msg)
    if not isinstance(answer, cls):
        raise DeviceError(f"{session.url}: {type(msg).__name__} answered {type(answer).__name__}")
    return answer


def firmware_info(session) -> FwInfo:
    _need_update_support(session)
    return _ask(session, FwInfoRequest(), FwInfo)  # type: ignore[return-value]


def describe_info(info: FwInfo, hello=None) -> list[str]:
    states = {s.value: s.name.lower() for s in SlotState}
    boot = {s.value: s.name.lower().replace("_", " ") for s in BootState}
    lines = []
    if hello is not None:
        lines.append(
            f"board {hello.serial}: firmware {hello.firmware_version}, protocol {hello.protocol_version}"
        )
    lines.append(
        f"target {info.target}, slot size {info.slot_size} bytes, running slot "
        f"{info.running_slot if info.running_slot != 0xFF else 'none (recovery)'}, "
        f"{boot.get(info.boot_state, info.boot_state)}, confirmed slot "
        f"{info.confirmed_slot if info.confirmed_slot != 0xFF else 'none (built-in image)'}"
    )
    for slot in (0, 1):
        state = getattr(info, f"slot{slot}_state")
        version = getattr(info, f"slot{slot}_version") or "-"
        size = getattr(info, f"slot{slot}_size")
        crc = getattr(info, f"slot{slot}_crc")
        lines.append(
            f"  slot {slot}: {states.get(state, state)}, version {version}, {size} bytes, "
            f"crc32c {crc:08x}"
        )
    if info.boot_state == BootState.TRIAL:
        tests = {
            SelfTest.NONE: "no self-test reported",
            SelfTest.PENDING: "self-test pending",
            SelfTest.RUNNING: "self-test running",
            SelfTest.PASSED: "self-test passed",
            SelfTest.FAILED: "self-test FAILED: it resets and rolls back by itself",
        }
        lines.append(
            f"  the running image is on trial ({tests.get(info.selftest, info.selftest)}), left "
            "by an update that did not finish: `spiel-edge firmware update` with the same image "
            "finishes it, `spiel-edge firmware confirm` keeps it, a reset (or its watchdog, "
            "when nobody confirms it) rolls back"
        )
    return lines


def confirm_firmware(session) -> FwConfirmResponse:
    _need_update_support(session)
    return _ask(session, FwConfirm(), FwConfirmResponse)  # type: ignore[return-value]


def update_firmware(
    url: str,
    image: bytes,
    *,
    open_session: Callable[[str], object] | None = None,
    progress: Callable[[int, int], None] | None = None,
    boot_wait_s: float = BOOT_WAIT_S,
    test_delay_ms: int = 100,
) -> UpdateResult:
    """The whole update; DeviceError with a one-line reason when it is refused or fails.
    ``progress(sent, total)`` after every chunk (tests interrupt the host there).

    The outcome is the state the same board (serial number and target checked after every
    reconnection) reports at the end: slot, version, confirmed or trial. A trial left by a
    host that died is resolved first: the same image is finished, another one rolled back."""
    header = check_image(image)
    if open_session is None:
        open_session = _default_open
    started = time.monotonic()
    sha = hashlib.sha256(image).digest()
    crc = crc32c(image)
    session = open_session(url)
    try:
        _need_update_support(session)
        hello = session.hello
        board = (hello.serial, "")
        info = firmware_info(session)
        board = (hello.serial, info.target)
        if info.target != header.target:
            raise DeviceError(
                f"refused: the image is for target {escape(header.target)!r}, the board runs "
                f"{escape(info.target)!r}"
            )
        if len(image) > info.slot_size:
            raise DeviceError(
                f"refused: the image of {len(image)} bytes is larger than the board's "
                f"{info.slot_size}-byte slot"
            )
        if info.boot_state == BootState.TRIAL:
            running = info.running_slot
            # the version too: a whole image's CRC-32C depends on its body only (the header
            # ends with its own CRC)
            same = running in (0, 1) and (
                hello.firmware_version == header.version
                and getattr(info, f"slot{running}_version") == header.version
                and getattr(info, f"slot{running}_crc") == crc
                and getattr(info, f"slot{running}_size") == len(image)
            )
            if same:  # an update whose host died after the test boot: finish it
                log.warning(
                    "%s: board %s runs this image on trial (an update that did not finish): "
                    "finishing it",
                    url,
                    escape(hello.serial),
                )
                return _settle(
                    session,
                    url,
                    header,
                    board,
                    running,
                    hello.firmware_version,
                    open_session,
                    boot_wait_s,
                    len(image),
                    started,
                )
            session = _roll_back_trial(session, url, board, open_session, boot_wait_s)
            hello = session.hello
        previous, boot_id = hello.firmware_version, hello.boot_id
        session.stop_stream(retries=1) if getattr(session, "_stream_request", None) else None
        try:
            begin = _upload(session, url, image, crc, sha, progress)
            clock_at_test = _board_clock_us(session)
            session.request(FwTest(test_delay_ms))
        except DeviceRequestError as exc:  # refused: the reason says why, again would not help
            raise _refusal(exc, url, header.version, previous) from exc
        except DeviceError as exc:  # the link failed; nothing switched: the running one stays
            raise DeviceError(
                f"{exc}; the board keeps firmware {escape(previous)} (the new one was not "
                "started): run the update again"
            ) from exc
        log.info(
            "%s: firmware %s written to slot %d; booting it once", url, header.version, begin.slot
        )
    except BaseException:
        _close(session)
        raise
    _close(session)
    session = _wait_board(
        url,
        open_session,
        board,
        (boot_id, clock_at_test),
        boot_wait_s,
        f"firmware {escape(header.version)} is not confirmed",
    )
    return _settle(
        session,
        url,
        header,
        board,
        begin.slot,
        previous,
        open_session,
        boot_wait_s,
        len(image),
        started,
    )


def _other_board(url: str, board: tuple[str, str], hello, target: str | None) -> str | None:
    serial, want_target = board
    if hello.serial != serial:
        return f"serial {escape(hello.serial)}"
    if target is not None and want_target and target != want_target:
        return f"target {escape(target)}"
    return None


def _wait_board(url, open_session, board, before, wait_s, what):
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
            _close(session)
            raise
        _close(session)
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


def _settle(session, url, header, board, slot, previous, open_session, wait_s, sent, started):
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
                _close(session)
                session = _wait_board(
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
        _close(session)
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


def _roll_back_trial(session, url, board, open_session, wait_s):
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
    clock = _board_clock_us(session)
    try:
        session.request(Reboot(RebootMode.NORMAL, 100))
    finally:
        _close(session)
    session = _wait_board(
        url,
        open_session,
        board,
        (hello.boot_id, clock),
        wait_s,
        "the unfinished trial was not rolled back",
    )
    info = firmware_info(session)
    if info.boot_state == BootState.TRIAL:
        _close(session)
        raise DeviceError(f"{url}: the board stays on its trial image after a reset")
    return session


def _upload(session, url: str, image: bytes, crc: int, sha: bytes, progress) -> FwBeginResponse:
    """FW_BEGIN, the image in FW_WRITE chunks, FW_VERIFY: the inactive slot holds the image."""
    begin = _ask(session, FwBegin(len(image), crc, sha), FwBeginResponse)
    assert isinstance(begin, FwBeginResponse)
    chunk = min(getattr(session, "max_payload", MAX_PAYLOAD), MAX_PAYLOAD) - WRITE_OVERHEAD
    offset = 0
    while offset < len(image):
        piece = image[offset : offset + chunk]
        answer = _ask(session, FwWrite(offset, piece), FwWriteResponse)
        assert isinstance(answer, FwWriteResponse)
        if answer.written != offset + len(piece):
            raise DeviceError(
                f"{url}: the board holds {answer.written} bytes, {offset + len(piece)} were sent"
            )
        offset += len(piece)
        if progress is not None:
            progress(offset, len(image))
    verify = verify_upload(session)
    if verify.sha256 != sha or verify.image_size != len(image):
        raise DeviceError(f"{url}: the board's copy differs from the image (SHA-256)")
    return begin


# how long a board may take to check an image (hash the slot, verify the Ed25519 signature): a
# Cortex-M0+ at 125 MHz takes ~0.2-0.3 s for 170 KB, its emulator 10 to 20 times that
VERIFY_WAIT_S = 60.0
VERIFY_POLL_S = 0.1


def verify_upload(session) -> FwVerifyResponse:
    """FW_VERIFY with the ASYNC flag (PROTOCOL.md § 14.3): the board answers BUSY and checks in
    its main loop, and is asked again until it gives the result. While it checks it may answer
    nothing for longer than a request waits (one signature check is a single step): once it
    said BUSY, that silence is waited through, up to VERIFY_WAIT_S. A board from before the
    flag ignores it and answers within the request."""
    deadline, checking = time.monotonic() + VERIFY_WAIT_S, False
    while True:
        try:
            return _ask(session, FwVerify(FwVerifyFlag.ASYNC), FwVerifyResponse)  # type: ignore[return-value]
        except DeviceRequestError as exc:
            if exc.code != ErrorCode.BUSY or time.monotonic() > deadline:
                raise
            checking = True
        except DeviceTimeoutError:
            if not checking or time.monotonic() > deadline:
                raise
        time.sleep(VERIFY_POLL_S)


def _board_clock_us(session) -> int | None:
    """The board's clock (us since boot) by TIME_SYNC, None where it has none to offer."""
    hello = session.hello
    if not (hello.protocol_version >= 2 and hello.capabilities & Capability.TIME_SYNC):
        return None
    try:
        answer = session.request(TimeSync(time.perf_counter_ns() // 1000))
    except DeviceError as exc:
        log.debug("time sync: %s", exc)
        return None
    return answer.board_time_us if isinstance(answer, TimeSyncResponse) else None


def _rebooted(session, boot_id: int, clock_at_test: int | None) -> bool:
    """A new boot_id, or (a board whose entropy gave the same one again) its clock, us since
    boot, behind where it stood at FW_TEST."""
    if session.hello.boot_id != boot_id:
        return True
    if clock_at_test is None:
        return False
    now = _board_clock_us(session)
    if now is None or now >= clock_at_test:
        return False
    log.warning(
        "the board rebooted with the same boot_id %08x (its clock restarted): its random "
        "source is weak; boot_id should differ at every boot",
        boot_id,
    )
    return True


def _default_open(url: str):
    from spiel_edge.device import DeviceSession

    session = DeviceSession(url, reconnect=False)
    session.open()
    return session


def _close(session) -> None:
    try:
        session.close()
    except DeviceError as exc:
        log.debug("close: %s", exc)


# the board's FW_VERIFY answers for an image it does not trust (PROTOCOL.md § 14.6)
_AUTH_CODES = (
    ErrorCode.FW_UNSIGNED,
    ErrorCode.FW_BAD_SIGNATURE,
    ErrorCode.FW_WRONG_KEY,
    ErrorCode.FW_ROLLBACK,
)


def _refusal(exc: DeviceRequestError, url: str, version: str, previous: str) -> DeviceError:
    """One line: why the board refused the image, and that it keeps what it runs."""
    if exc.code not in _AUTH_CODES:
        return exc
    code = ErrorCode(exc.code)
    detail = str(exc).split("): ", 1)[-1] if "): " in str(exc) else ""
    return DeviceRequestError(
        f"{url}: the board refused firmware {version}: {code.text} ({code.name}"
        f"{': ' + detail if detail else ''}); it keeps firmware {previous}",
        exc.code,
        exc.request_type,
    )
