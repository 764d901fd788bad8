"""Firmware-update requests on one open session (PROTOCOL.md section 14.3): the image checked
before a byte is sent, FW_INFO and FW_CONFIRM, the upload (FW_BEGIN, FW_WRITE chunks, FW_VERIFY
asked asynchronously) and the board's reasons for refusing an image, in one line."""

from __future__ import annotations

import logging
import time

from spiel_edge.errors import DeviceError, DeviceRequestError, DeviceTimeoutError
from spiel_edge.protocol import MAX_PAYLOAD, Capability, ErrorCode, Message
from spiel_edge.protocol.image import ImageError, ImageHeader, parse_image
from spiel_edge.protocol.link_messages import (
    BootState,
    FwBegin,
    FwBeginResponse,
    FwConfirm,
    FwConfirmResponse,
    FwInfo,
    FwInfoRequest,
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
from spiel_edge.protocol.messages import MAX_PROTOCOL_VERSION, MIN_PROTOCOL_VERSION

log = logging.getLogger(__name__)

WRITE_OVERHEAD = 6  # FW_WRITE's fixed part


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


def require_update_support(session) -> None:
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


def _ask(session, msg: Message, cls: type, **options) -> Message:
    answer = session.request(msg, **options)
    if not isinstance(answer, cls):
        raise DeviceError(f"{session.url}: {type(msg).__name__} answered {type(answer).__name__}")
    return answer


def firmware_info(session) -> FwInfo:
    require_update_support(session)
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
    if info.boot_state == BootState.TEST_PENDING:
        other = 1 - info.running_slot if info.running_slot in (0, 1) else "?"
        lines.append(
            f"  FW_TEST was accepted: slot {other}'s image boots once, on trial, at the next "
            "reset (an update that did not reach its test boot left it): `spiel-edge firmware "
            "update` with that image finishes it"
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
    require_update_support(session)
    return _ask(session, FwConfirm(), FwConfirmResponse)  # type: ignore[return-value]


def upload_image(
    session, url: str, image: bytes, crc: int, sha: bytes, progress
) -> FwBeginResponse:
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
            # BUSY comes back here (not retried inside the request): the silence that follows,
            # while the board checks, is then waited through (at load 12 the emulated Pico's
            # check outlasted four tries of the retried request)
            answer = _ask(session, FwVerify(FwVerifyFlag.ASYNC), FwVerifyResponse, retry_busy=False)
            return answer  # type: ignore[return-value]
        except DeviceRequestError as exc:
            if exc.code != ErrorCode.BUSY or time.monotonic() > deadline:
                raise
            checking = True
        except DeviceTimeoutError:
            if not checking or time.monotonic() > deadline:
                raise
        time.sleep(VERIFY_POLL_S)


def board_clock_us(session) -> int | None:
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


# the board's FW_VERIFY answers for an image it does not trust (PROTOCOL.md § 14.6)
_AUTH_CODES = (
    ErrorCode.FW_UNSIGNED,
    ErrorCode.FW_BAD_SIGNATURE,
    ErrorCode.FW_WRONG_KEY,
    ErrorCode.FW_ROLLBACK,
)


def refusal(exc: DeviceRequestError, url: str, version: str, previous: str) -> DeviceError:
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
