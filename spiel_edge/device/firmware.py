"""Firmware update with rollback over a device session (PROTOCOL.md section 14.3).

``check_image`` refuses a damaged or foreign image before a byte is sent; ``update_firmware``
uploads it into the inactive slot in chunks sized by the link's payload, has the board verify
length, CRC-32C and SHA-256, boots it once ("test"), waits for it to answer HELLO and only then
confirms it. A board that does not come back with the new version rolled back by itself (or
will at its next reset): the host says which. The requests are in ``firmware_requests``, what
follows the test boot in ``firmware_outcome``.
"""

from __future__ import annotations

import hashlib
import logging
import time
from collections.abc import Callable

from crc32c import crc32c

from spiel_edge.device.firmware_outcome import (
    UpdateResult,
    close_quietly,
    open_board,
    roll_back_trial,
    settle,
    wait_for_board,
)
from spiel_edge.device.firmware_requests import (
    board_clock_us,
    check_image,
    confirm_firmware,
    describe_info,
    firmware_info,
    refusal,
    require_update_support,
    upload_image,
    verify_upload,
)
from spiel_edge.errors import DeviceError, DeviceRequestError
from spiel_edge.protocol.link_messages import BootState, FwTest
from spiel_edge.safety.shown import escape

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
        open_session = open_board
    started = time.monotonic()
    sha = hashlib.sha256(image).digest()
    crc = crc32c(image)
    session = open_session(url)
    try:
        require_update_support(session)
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
                return settle(
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
            session = roll_back_trial(session, url, board, open_session, boot_wait_s)
            hello = session.hello
        previous, boot_id = hello.firmware_version, hello.boot_id
        session.stop_stream(retries=1) if getattr(session, "_stream_request", None) else None
        try:
            begin = upload_image(session, url, image, crc, sha, progress)
            clock_at_test = board_clock_us(session)
            session.request(FwTest(test_delay_ms))
        except DeviceRequestError as exc:  # refused: the reason says why, again would not help
            raise refusal(exc, url, header.version, previous) from exc
        except DeviceError as exc:  # the link failed; nothing switched: the running one stays
            raise DeviceError(
                f"{exc}; the board keeps firmware {escape(previous)} (the new one was not "
                "started): run the update again"
            ) from exc
        log.info(
            "%s: firmware %s written to slot %d; booting it once", url, header.version, begin.slot
        )
    except BaseException:
        close_quietly(session)
        raise
    close_quietly(session)
    session = wait_for_board(
        url,
        open_session,
        board,
        (boot_id, clock_at_test),
        boot_wait_s,
        f"firmware {escape(header.version)} is not confirmed",
    )
    return settle(
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
