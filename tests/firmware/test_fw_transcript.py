"""One scripted request transcript against both virtual boards: the Python one
(spiel_edge.sim.board.VirtualBoard) and the C core (tests/firmware/core_driver.c, the same
recordings). Every response and stream frame must be the same, byte for byte, except the
fields that carry time or say which board it is (listed in IGNORED)."""

from __future__ import annotations

import hashlib
import math
from dataclasses import replace

import pytest
from crc32c import crc32c

from spiel_edge.board_config.schema import encode, from_profile
from spiel_edge.profile.schema import load_profile
from spiel_edge.protocol import (
    ConfigCommit,
    ConfigRead,
    ConfigSource,
    ConfigStatusRequest,
    ConfigWrite,
    DeviceInfoRequest,
    ErrorResponse,
    FrameDecoder,
    Hello,
    Ping,
    Reboot,
    StreamData,
    StreamStart,
    StreamStatusRequest,
    StreamStop,
    decode_message,
    encode_frame,
    encode_message,
)
from spiel_edge.protocol import messages as m
from spiel_edge.sim.board import VirtualBoard
from spiel_edge.sim.scenes import ReplayScene
from tests.firmware.firmware import CoreDriver

# fields that carry time, identity or what a board can do beyond this transcript
IGNORED = {
    m.HelloResponse: ("boot_id", "firmware_version", "serial", "capabilities", "max_samples"),
    m.DeviceInfo: ("uptime_ms", "temperature_cdeg", "board_name", "max_sample_rate_hz"),
    StreamData: ("timestamp_us",),
    ErrorResponse: ("text",),  # the code and request type must agree; the wording is free
    m.TimeSyncResponse: ("board_time_us", "boot_id"),
    # what the slots hold: the virtual board boots a factory image in slot 0, the driver's
    # slots start erased; the target name is each board's own
    m.FwInfo: (
        "target",
        *(f"slot{i}_{k}" for i in (0, 1) for k in ("state", "version", "size", "crc")),
    ),
}


TELEMETRY = (m.MsgType.HEARTBEAT, m.MsgType.LOG)


def blob() -> bytes:
    return encode(from_profile(load_profile("spiel-icra23"), "transcript"))


def script():
    """(seconds, wire) steps; ``None`` wire: only let time pass."""
    b = blob()
    good = crc32c(b)
    garbage = b"\x01\x02\x03\x00" + encode_message(Ping(b"x"), seq=99)[:-3] + b"\x55\x00"
    steps = [
        Hello(1, 2, 8256, 0),
        DeviceInfoRequest(),
        Ping(b"hello"),
        "retry",  # the same request, same seq: answered from the cache
        *version2_steps(),
        ConfigStatusRequest(),
        ConfigRead(0, 64, ConfigSource.ACTIVE),  # no config yet: NOT_FOUND
        ConfigRead(0, 64, ConfigSource.STAGING),  # empty staging: empty data
        ConfigWrite(10, b"abc"),  # a write past the end without a staging: a zero hole
        ConfigRead(0, 64, ConfigSource.STAGING),
        ConfigRead(0, 9000, ConfigSource.STAGING),  # more than max_payload - 6: TOO_LARGE
        ConfigRead(0, 8, 7),  # no such source
        ConfigWrite(0, b[:300]),  # offset 0: a new staging
        ConfigWrite(300, b[300:]),
        ConfigRead(250, 100, ConfigSource.STAGING),
        ConfigCommit(len(b), good ^ 1),  # CORRUPT, staging kept
        ConfigCommit(0, good),  # INVALID
        ConfigCommit(len(b) + 1, good),  # INVALID
        ConfigCommit(len(b), good),
        "retry",  # a retried commit is not executed twice
        ConfigStatusRequest(),
        ConfigRead(0, 200, ConfigSource.ACTIVE),
        ConfigRead(len(b) - 5, 64, ConfigSource.ACTIVE),  # shorter at the end
        ConfigRead(len(b) + 5, 64, ConfigSource.ACTIVE),  # empty past it
        StreamStart(3, 0.0, 0, 0, 0),  # three as fast as possible: two come before the stop,
        ("wait", 0.002),  # one listening window (2.9 ms) apart, whatever the host's pace
        ("wait", 0.002),
        StreamStatusRequest(),
        StreamStop(),  # idle: OK, nothing sent
        StreamStart(0, 100.0, 64, 0, 0),
        ("wait", 0.010),
        ("wait", 0.020),
        ConfigCommit(len(b), good),  # BAD_STATE while streaming
        StreamStart(0, 100.0, 64, 0, 0),  # BAD_STATE: already running
        ConfigWrite(0, b"while streaming is fine"),
        StreamStop(),
        StreamStart(0, 0.0, 0, 2, 0),  # F32: UNSUPPORTED
        StreamStart(0, math.nan, 0, 0, 0),  # INVALID
        StreamStart(0, 20000.0, 0, 0, 0),  # INVALID
        StreamStart(0, 0.0, 0, 0, 0x10),  # absent channel: INVALID
        StreamStart(2, 0.0, 64, 0, 0b1010),  # v2: a subset, physical channel ids
        StreamStatusRequest(),
        ("raw", encode_frame(0x0999, b"", seq=500)),  # unknown type: UNSUPPORTED
        ("raw", encode_frame(0x0021, b"\x00\x00\x00\x00\x09\x00ab", seq=501)),  # cut tail
        ("raw", garbage),  # dropped and counted
        StreamStatusRequest(),
        Hello(3, 4, 8256, 0),  # VERSION_TOO_NEW
        Hello(0, 0, 8256, 0),  # VERSION_TOO_OLD
        Hello(1, 2, 10, 0),  # max_payload below 64: INVALID
        Hello(1, 1, 8256, 0),  # a version-1 host
        StreamStart(1, 0.0, 64, 0, 0b0011),  # v1: subsets UNSUPPORTED
        StreamStart(2, 0.0, 64, 0, 0),  # v1: 16-byte answer
        Hello(1, 2, 256, 0),  # a small host: link max_payload 256
        ConfigRead(0, 251, ConfigSource.ACTIVE),  # TOO_LARGE
        ConfigRead(0, 250, ConfigSource.ACTIVE),
        Ping(bytes(255)),  # TOO_LARGE
        Reboot(0, 50),
    ]
    return steps


def version2_steps():
    """TIME_SYNC, TELEMETRY and each FW_* request (PROTOCOL.md 14.1-14.3): the answers and the
    refusals both boards owe, without a signed image (the posix and QEMU tests upload those)."""
    body = bytes(range(104))
    return [
        m.TimeSync(123456789),  # the board's clock and boot id are its own (IGNORED)
        m.Telemetry(0, 2, 5),  # no heartbeat, log level WARNING, 5 lines a second
        m.Telemetry(20, 9, 0),  # heartbeat raised to 50 ms, level capped at DEBUG
        m.Telemetry(0, 1, 20),
        m.FwInfoRequest(),
        m.FwWrite(0, bytes(8)),  # no upload: BAD_STATE
        m.FwVerify(0),  # no upload: BAD_STATE
        m.FwTest(50),  # nothing verified: BAD_STATE
        m.FwBegin(1 << 20, 0, bytes(32)),  # larger than the 64 KiB slot: TOO_LARGE
        m.FwBegin(50, 0, bytes(32)),  # shorter than an image header: INVALID
        m.FwBegin(len(body), crc32c(body), hashlib.sha256(body).digest()),  # slot 1
        m.FwWrite(0, body[:64]),
        "retry",  # a repeated chunk: written stays 64
        m.FwWrite(80, body[80:]),  # a gap: INVALID
        m.FwWrite(64, body[64:]),
        m.FwVerify(0),  # the bytes match FW_BEGIN's digest but are no image: INVALID
        m.FwTest(50),  # not verified: BAD_STATE
        m.FwInfoRequest(),
        m.FwConfirm(),  # the running slot, already confirmed: OK
    ]


def run(board_step, steps) -> list[tuple]:
    """Frames each board sends: (flags, msg_type, seq, aux, message or payload)."""
    out, seq, now, last = [], 0, 1.0, b""
    for step in steps:
        if isinstance(step, tuple) and step[0] == "wait":
            now += step[1]
            wire = b""
        elif isinstance(step, tuple):
            wire = step[1]
        elif step == "retry":
            wire = last
        else:
            seq += 1
            wire = last = encode_message(step, seq=seq)
        out.append([_frame(f) for f in FrameDecoder().feed(board_step(wire, now))])
    return out


def _frame(f):
    if f.msg_type >= 0x8000:  # the virtual board's annotations (vendor range)
        return None
    msg = decode_message(f)
    ignored = IGNORED.get(type(msg), ())
    if ignored:
        msg = replace(msg, **{k: type(getattr(msg, k))() for k in ignored})
    size = None if isinstance(msg, ErrorResponse) else len(f.payload)  # text is free
    return (f.flags, f.msg_type, f.seq, f.aux, size, msg)


def python_board(steps):
    board = VirtualBoard(ReplayScene(), now=0.0)

    def step(wire, now):
        sent = b"".join(o.wire for o in board.receive(wire, now))
        return sent + b"".join(o.wire for o in board.due(now, 1 << 20))

    return run(step, steps)


def c_board(driver_exe, scans, steps):
    driver = CoreDriver(driver_exe, scans)
    try:

        def step(wire, now):
            driver.set_time(int(round(now * 1e6)))
            return driver.feed(wire)

        return run(step, steps)
    finally:
        driver.close()


def test_both_virtual_boards_answer_the_transcript_identically(driver_exe, subset_scans):
    steps = script()
    py = python_board(steps)
    c = c_board(driver_exe, subset_scans, steps)
    for i, (step, a, b) in enumerate(zip(steps, py, c, strict=True)):
        # HEARTBEAT and LOG (protocol 2 telemetry) come on their own clock, not per request
        a = [f for f in a if f is not None and f[1] not in TELEMETRY]
        b = [f for f in b if f[1] not in TELEMETRY]
        assert a == b, f"step {i} {step!r}:\n python {a}\n C      {b}"
    # the transcript exercised what it claims to
    flat = [f[-1] for frames in c for f in frames]
    codes = {x.code for x in flat if isinstance(x, ErrorResponse)}
    assert codes >= {3, 5, 6, 7, 8, 9, 12, 13}
    assert sum(isinstance(x, StreamData) for x in flat) >= 4 * 3 + 4 * 2 + 2 * 2


@pytest.mark.parametrize("cut", [0, 1])
def test_the_transcript_is_not_a_tautology(driver_exe, subset_scans, cut):
    """The comparison sees a difference: a board answering one request differently fails."""
    steps = script()[:8]
    py = python_board(steps)
    changed = list(steps)
    changed[5 + cut] = ConfigRead(1, 64, ConfigSource.STAGING)
    c = c_board(driver_exe, subset_scans, changed)
    assert [[f for f in a if f] for a in py] != c
