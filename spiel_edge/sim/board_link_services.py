"""The virtual board's protocol version 2 requests: its clock (TIME_SYNC, with drift), telemetry
(HEARTBEAT, LOG with a rate limit) and firmware update (FW_*, over sim/firmware_slots.py).

Mixed into VirtualBoard. The board's clock runs ``drift_ppm`` fast (or slow) against the caller's
clock and starts at 0 at every boot, so it is offset from the host's by the boot time.
"""

from __future__ import annotations

import hashlib
import logging
import math
from collections import deque

from crc32c import crc32c

from spiel_edge.protocol import Capability, ErrorCode, ErrorResponse, encode_message
from spiel_edge.protocol import messages as m
from spiel_edge.protocol.image import ImageError, ImageRefused, parse_image, verify_image
from spiel_edge.protocol.link_messages import (
    KNOWN_ERROR_FLAGS,
    SHA256_SIZE,
    BoardState,
    BootState,
    ErrorFlag,
    FwVerifyFlag,
    LogLevel,
    SelfTest,
)
from spiel_edge.sim.faults import Outgoing
from spiel_edge.sim.firmware_slots import NO_SLOT, SILENT_MARK, TARGET, FirmwareFlash
from spiel_edge.sim.flash import PowerCut

log = logging.getLogger(__name__)

LOG_QUEUE = 32  # log lines the board holds before it drops (and counts) more
LOG_TEXT_MAX = 200
DEFAULT_HEARTBEAT_MS = 1000
SYNC_FAULT_EVERY = 7  # sync_fault=...: every 7th TIME_SYNC answer is wrong
MONTHS_US = 90 * 86400 * 10**6
FW_MIN_PAYLOAD = 128  # a link's max_payload below this gets no FIRMWARE_UPDATE
START_AT_AHEAD_S = 60.0  # a STREAM_START's start_at_us at most this far ahead
_MASK = 0xFFFFFFFF

__all__ = ["KNOWN_ERROR_FLAGS", "BoardLinkServices"]


class BoardLinkServices:
    """Needs from VirtualBoard: boot_id, _boot_time, streaming, negotiated, protocol, drift_ppm,
    fw (FirmwareFlash), options-like attributes set in its __init__."""

    fw: FirmwareFlash
    boot_id: int
    _boot_time: float
    version: int
    drift_ppm: float
    sync_fault: str
    heartbeat_extra_flags: int
    log_flood: float
    streaming: bool

    def _link_services_init(
        self, drift_ppm, firmware, sync_fault, heartbeat_flags, log_flood
    ) -> None:
        self.drift_ppm = drift_ppm
        self.offers_start_at = True  # STREAM_START's start_at_us (SimOptions.start_at)
        self.fw = firmware or FirmwareFlash()
        self.sync_fault = sync_fault
        self.heartbeat_extra_flags = heartbeat_flags
        self.log_flood = log_flood
        self.version = 1

    def link_service_capabilities(self) -> int:
        """HELLO capability bits of the negotiated version."""
        if self.version < 2:
            return 0
        caps = Capability.TIME_SYNC | Capability.TELEMETRY
        if self.offers_start_at:
            caps |= Capability.START_AT
        if self.max_payload >= FW_MIN_PAYLOAD:  # FW_INFO's answer needs 74 bytes
            caps |= Capability.FIRMWARE_UPDATE
        if hasattr(self.scene, "iq_supported"):
            caps |= Capability.IQ_SAMPLES
        return int(caps)

    no_sensor = False  # set by the link from its options
    trial_window_s = 60.0
    SELFTEST_S = 0.02  # one acquisition

    def selftest(self, now: float) -> int:
        """A trial's self-test (the C core's: one acquisition within 1 s), advanced to now: a
        failure resets the board 2 s later and the boot stage rolls the trial back."""
        if self.fw.boot_state != BootState.TRIAL:
            return SelfTest.NONE
        if self._selftest == SelfTest.RUNNING and now >= self._selftest_at:
            if self.no_sensor:
                self._selftest = SelfTest.FAILED
                self.board_log(
                    LogLevel.ERROR, "self-test failed: the sensor refused a trigger", now
                )
                self.reboot_at = now + 2.0
            else:
                self._selftest = SelfTest.PASSED
                self.board_log(LogLevel.NOTICE, "self-test passed", now)
        return self._selftest

    def trial_expired(self, now: float) -> bool:
        """The trial window passed unconfirmed: the watchdog is no longer kicked."""
        return (
            self.fw.boot_state == BootState.TRIAL and now - self._boot_time >= self.trial_window_s
        )

    def _link_services_boot(self, now: float) -> None:
        for _ in range(3):  # the bootloader's record writes may be cut too: boot again
            try:
                self.fw.boot()
                break
            except PowerCut as exc:
                log.info("%s: %s during boot", getattr(self, "serial", ""), exc)
        self.heartbeat_ms = DEFAULT_HEARTBEAT_MS if self.max_protocol() >= 2 else 0
        self.log_level = LogLevel.INFO
        self.log_per_s = 20
        self._next_heartbeat = now + self.heartbeat_ms / 1000.0
        self._logs: deque[tuple[int, str, float]] = deque()
        self._log_dropped = 0
        self._log_tokens = float(self.log_per_s)
        self._log_refill = now
        self._flood_next = now
        self._syncs = 0
        self._fw_expect: tuple[int, int, bytes] | None = None  # size, crc, sha of an upload
        self._fw_slot: int | None = None
        self._fw_verified = False
        self._fw_verify_at: float | None = None  # an asynchronous FW_VERIFY's result is due
        self._flags_seen = 0
        image = self.fw.header(self.fw.running) if self.fw.running != NO_SLOT else None
        self.silent = bool(
            self.fw.running != NO_SLOT
            and self.fw.image(self.fw.running)[96:].startswith(SILENT_MARK)
        )
        self.firmware_version = image.version if image is not None else "recovery"
        self._image_max_protocol = image.max_protocol if image is not None else 2
        self._selftest = SelfTest.RUNNING
        self._selftest_at = now + self.SELFTEST_S
        trial = " (trial: FW_CONFIRM keeps it)" if self.fw.boot_state == BootState.TRIAL else ""
        self.board_log(
            LogLevel.NOTICE,
            f"booted slot {self.fw.running} firmware {self.firmware_version}{trial}",
            now,
        )

    def max_protocol(self) -> int:
        return min(self.max_version, getattr(self, "_image_max_protocol", 2))

    def clock_us(self, now: float) -> int:
        """The board's clock (us since boot), drifting ``drift_ppm`` against the caller's."""
        return int((now - self._boot_time) * (1e6 + self.drift_ppm))

    def first_due(self, start_at_us: int, period_s: float, now: float) -> float | None:
        """The caller's time when acquisition 0 of a stream is due (PROTOCOL.md § 6.4,
        ``start_at_us``): at once (0, or a version-1 link), at that board time, or, past, the
        first point of its grid not yet past; None: more than 60 s ahead."""
        if self.version < 2 or not start_at_us or not self.offers_start_at:
            return now  # a board without START_AT ignores the field (bytes after its part)
        due = self._boot_time + start_at_us / (1e6 + self.drift_ppm)
        if due - now > START_AT_AHEAD_S:
            return None
        if due < now and period_s > 0:
            due += math.ceil((now - due) / period_s) * period_s
        return max(due, now)

    def _need_v2(self, req: m.Message) -> ErrorResponse | None:
        if self.version < 2:
            return ErrorResponse(
                ErrorCode.UNSUPPORTED, req.MSG_TYPE, "not a request of protocol version 1"
            )
        if 0x0040 <= req.MSG_TYPE <= 0x0045 and self.max_payload < FW_MIN_PAYLOAD:
            return ErrorResponse(
                ErrorCode.UNSUPPORTED,
                req.MSG_TYPE,
                f"firmware update needs max_payload >= {FW_MIN_PAYLOAD}",
            )
        return None

    # --- time sync -------------------------------------------------------------------------

    def _time_sync(self, req: m.TimeSync, now: float) -> m.Message:
        board = self.clock_us(now)
        self._syncs += 1
        if self.sync_fault and self._syncs % SYNC_FAULT_EVERY == 0:
            board = board + MONTHS_US if self.sync_fault == "months" else max(board - 10**7, 0)
        return m.TimeSyncResponse(req.host_time_us, board, self.boot_id)

    # --- telemetry -------------------------------------------------------------------------

    def _telemetry(self, req: m.Telemetry, now: float) -> m.Message:
        self.heartbeat_ms = min(req.heartbeat_ms, 60000)
        if self.heartbeat_ms and 0 < self.heartbeat_ms < 50:
            self.heartbeat_ms = 50
        self.log_level = min(int(req.log_level), int(LogLevel.DEBUG))
        self.log_per_s = req.log_per_s
        self._next_heartbeat = now + self.heartbeat_ms / 1000.0
        return m.TelemetryResponse(self.heartbeat_ms, self.log_level, self.log_per_s)

    def board_log(self, level: int, text: str, now: float) -> None:
        """Queue a log line (dropped and counted when the queue is full)."""
        if level > getattr(self, "log_level", LogLevel.INFO):
            return
        if len(self._logs) >= LOG_QUEUE:
            self._log_dropped += 1
            return
        self._logs.append((int(level), text[:LOG_TEXT_MAX], now))

    def error_flags(self) -> int:
        flags = self.heartbeat_extra_flags
        if self.fw.boot_state == BootState.TRIAL:
            flags |= ErrorFlag.TRIAL_IMAGE
            if getattr(self, "_selftest", None) == SelfTest.FAILED:
                flags |= ErrorFlag.SENSOR
        if self._log_dropped:
            flags |= ErrorFlag.LOG_DROPPED
        if getattr(self, "flash", None) is not None and self.flash.active() is None:
            flags |= ErrorFlag.DEFAULT_CONFIG
        return int(flags) & _MASK

    def telemetry_due(self, now: float, room: int = 1 << 30) -> list[Outgoing]:
        """HEARTBEAT and LOG frames due by ``now`` that fit ``room`` bytes of the transmit
        queue (a flood beyond it is lost on the board, as a full UART FIFO loses it)."""
        if self.version < 2 or self.silent:
            return []
        out: list[Outgoing] = []
        if self.log_flood > 0:  # a misbehaving firmware: lines past its own limit
            self._flood_next = max(self._flood_next, now - 0.05)  # no backlog beyond 50 ms
            while self._flood_next <= now and room > 4096:
                self._flood_next += 1.0 / self.log_flood
                room -= 160
                text = ("flood " * 20)[: self.max_payload - 15]
                line = m.LogMessage(LogLevel.WARNING, 0, self.clock_us(now), text)
                out.append(Outgoing(encode_message(line)))
        self._log_tokens = min(
            float(self.log_per_s), self._log_tokens + (now - self._log_refill) * self.log_per_s
        )
        self._log_refill = now
        while self._logs and self._log_tokens >= 1.0:
            level, text, _ = self._logs.popleft()
            self._log_tokens -= 1.0
            text = text.encode()[: self.max_payload - 15].decode("utf-8", "ignore")
            line = m.LogMessage(level, self._log_dropped, self.clock_us(now), text)
            self._log_dropped = 0
            out.append(Outgoing(encode_message(line)))
        if self.heartbeat_ms and now >= self._next_heartbeat:
            self._next_heartbeat = now + self.heartbeat_ms / 1000.0
            state = BoardState.STREAMING if self.streaming else BoardState.IDLE
            if self._fw_expect is not None:
                state = BoardState.UPDATING
            beat = m.Heartbeat(
                int((now - self._boot_time) * 1000) & _MASK,
                state,
                0,
                self.heartbeat_ms,
                self.error_flags(),
                self.boot_id,
                self.clock_us(now),
            )
            out.append(Outgoing(encode_message(beat)))
        return out

    def telemetry_next(self) -> float | None:
        if self.version < 2 or self.silent:
            return None
        times = []
        if self.heartbeat_ms:
            times.append(self._next_heartbeat)
        if self._logs:
            times.append(self._log_refill + 1.0 / max(self.log_per_s, 1))
        if self.log_flood > 0:
            times.append(self._flood_next)
        return min(times) if times else None

    # --- firmware update -------------------------------------------------------------------

    def _fw_info(self, req: m.Message, now: float) -> m.Message:
        fw = self.fw
        rec = fw.record()
        slots = []
        for slot in (0, 1):
            header = fw.header(slot)
            slots += [
                fw.slot_state(slot),
                header.version if header else "",
                fw.lengths[slot],
                crc32c(fw.image(slot)) if fw.lengths[slot] else 0,
            ]
        boot_state = fw.boot_state
        if rec.state == BootState.TEST_PENDING:
            boot_state = BootState.TEST_PENDING
        return m.FwInfo(
            fw.running, boot_state, rec.confirmed, self.selftest(now), fw.slot_size, TARGET, *slots
        )

    def _fw_begin(self, req: m.FwBegin, now: float) -> m.Message:
        fw = self.fw
        error = None
        if self.streaming:
            error = (ErrorCode.BAD_STATE, "stop the stream before a firmware update")
        elif fw.boot_state == BootState.TRIAL:
            error = (ErrorCode.BAD_STATE, "running a trial image: confirm it or reset first")
        elif len(req.sha256) != SHA256_SIZE:
            error = (ErrorCode.INVALID, f"sha256 must be {SHA256_SIZE} bytes")
        elif req.image_size > fw.slot_size:
            error = (
                ErrorCode.TOO_LARGE,
                f"image of {req.image_size} bytes does not fit the {fw.slot_size}-byte slot",
            )
        elif req.image_size < 96:
            error = (ErrorCode.INVALID, "an image is at least its 96-byte header")
        if error:
            return ErrorResponse(error[0], req.MSG_TYPE, error[1])
        slot = 0 if fw.running == NO_SLOT else 1 - fw.running
        if fw.record().state == BootState.TEST_PENDING:
            fw.test_cancel()
        self._fw_expect, self._fw_slot, self._fw_verified = None, None, False
        self._fw_verify_at = None
        fw.erase(slot)
        self._fw_expect = (req.image_size, req.image_crc, bytes(req.sha256))
        self._fw_slot = slot
        self.board_log(
            LogLevel.INFO, f"firmware upload of {req.image_size} bytes to slot {slot}", now
        )
        return m.FwBeginResponse(slot, fw.slot_size)

    def _fw_write(self, req: m.FwWrite, now: float) -> m.Message:
        if self._fw_expect is None or self._fw_slot is None:
            return ErrorResponse(ErrorCode.BAD_STATE, req.MSG_TYPE, "no upload: send FW_BEGIN")
        slot, written = self._fw_slot, self.fw.lengths[self._fw_slot]
        end = req.offset + len(req.data)
        if end > self._fw_expect[0]:
            return ErrorResponse(ErrorCode.TOO_LARGE, req.MSG_TYPE, "past the announced size")
        if end <= written and self.fw.image(slot)[req.offset : end] == req.data:
            return m.FwWriteResponse(written)  # a repeated chunk
        if req.offset != written:
            return ErrorResponse(
                ErrorCode.INVALID, req.MSG_TYPE, f"offset {req.offset}, expected {written}"
            )
        self._fw_verified, self._fw_verify_at = False, None
        self.fw.program(slot, req.offset, req.data)
        return m.FwWriteResponse(self.fw.lengths[slot])

    verify_s = 0.0  # how long an asynchronous FW_VERIFY's check takes (answered BUSY meanwhile)
    # the check blocks the board's loop, as the C core's one signature check does: after its
    # BUSY answer the board reads nothing until the check is done
    verify_blocks = False
    _blocked_until = 0.0

    def _fw_verify(self, req: m.FwVerify, now: float) -> m.Message:
        """FW_VERIFY: checked at once, or (the ASYNC flag, as the C core does) BUSY first and
        until ``verify_s`` passed, then the result, until the upload changes."""
        if not req.flags & FwVerifyFlag.ASYNC:
            self._fw_verify_at = None
            return self._fw_check(req, now)
        if self._fw_verify_at is None:
            self._fw_verify_at = now + self.verify_s
            if self.verify_blocks:
                self._blocked_until = self._fw_verify_at
        elif now >= self._fw_verify_at:
            return self._fw_check(req, now)
        return ErrorResponse(ErrorCode.BUSY, req.MSG_TYPE, "checking the image: ask again")

    def _fw_check(self, req: m.Message, now: float) -> m.Message:
        if self._fw_expect is None or self._fw_slot is None:
            return ErrorResponse(ErrorCode.BAD_STATE, req.MSG_TYPE, "no upload: send FW_BEGIN")
        size, crc, sha = self._fw_expect
        slot = self._fw_slot
        image = self.fw.image(slot)
        error = None
        if len(image) != size:
            error = (ErrorCode.BAD_STATE, f"image incomplete: {len(image)} of {size} bytes")
        elif crc32c(image) != crc:
            error = (ErrorCode.CORRUPT, "CRC-32C of the slot differs from FW_BEGIN's")
        elif hashlib.sha256(image).digest() != sha:
            error = (ErrorCode.CORRUPT, "SHA-256 of the slot differs from FW_BEGIN's")
        else:
            try:
                header = parse_image(image)
                verify_image(image, self.fw.public_key, self.fw.record().security_counter)
            except ImageRefused as exc:  # unsigned, another key, tampered, a downgrade
                error = (exc.code, str(exc))
            except ImageError as exc:
                error = (ErrorCode.INVALID, str(exc))
            else:
                if header.target != TARGET:
                    error = (
                        ErrorCode.UNSUPPORTED,
                        f"image for {header.target!r}, board is {TARGET!r}",
                    )
                elif not header.speaks(1, self.max_version):
                    error = (
                        ErrorCode.UNSUPPORTED,
                        f"image speaks protocol {header.min_protocol}-{header.max_protocol}",
                    )
        if error:
            self.board_log(LogLevel.ERROR, f"firmware verify failed: {error[1]}", now)
            return ErrorResponse(error[0], req.MSG_TYPE, error[1])
        self._fw_verified = True
        return m.FwVerifyResponse(slot, len(image), crc32c(image), hashlib.sha256(image).digest())

    def _fw_test(self, req: m.FwTest, now: float) -> m.Message:
        if not self._fw_verified or self._fw_slot is None:
            return ErrorResponse(
                ErrorCode.BAD_STATE, req.MSG_TYPE, "no verified image: FW_VERIFY first"
            )
        slot = self._fw_slot
        self.fw.test(slot)
        self._fw_expect = None
        self.reboot_at = now + req.delay_ms / 1000.0
        return m.FwTestResponse(slot)

    def _fw_confirm(self, req: m.Message, now: float) -> m.Message:
        if self.fw.running == NO_SLOT:
            return ErrorResponse(ErrorCode.BAD_STATE, req.MSG_TYPE, "no image is running")
        was_trial = self.fw.boot_state == BootState.TRIAL
        test = self.selftest(now)
        if was_trial and test != SelfTest.PASSED:
            text = (
                "the self-test failed: the trial rolls back"
                if test == SelfTest.FAILED
                else "the self-test has not passed yet"
            )
            return ErrorResponse(ErrorCode.BAD_STATE, req.MSG_TYPE, text)
        self.fw.confirm()
        if was_trial:
            self.board_log(LogLevel.NOTICE, f"firmware {self.firmware_version} confirmed", now)
        return m.FwConfirmResponse(self.fw.running, self.fw.boot_state)
