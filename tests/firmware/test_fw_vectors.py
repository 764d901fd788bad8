"""The protocol's conformance vectors (firmware_protocol/test_vectors.json) against the C
device core, as tests/protocol checks them against Python: every invalid piece is dropped
and counted under its counter, the damaged stream gives the documented counters, every valid
frame is decoded, and every request vector is parsed and answered with its seq and type."""

from __future__ import annotations

import pytest

from spiel_edge.protocol import (
    ErrorCode,
    ErrorResponse,
    FrameDecoder,
    Hello,
    decode_message,
    encode_message,
    load_test_vectors,
)
from tests.firmware.firmware import CoreDriver

VECTORS = load_test_vectors()
COUNTERS = ("frames", "crc", "cobs", "length", "oversize", "version", "flags")


@pytest.fixture
def core(driver_exe, subset_scans):
    driver = CoreDriver(driver_exe, subset_scans)
    yield driver
    driver.close()


def counters(core) -> dict[str, int]:
    stats = core.stats()
    return {k: stats[k] for k in COUNTERS}


@pytest.mark.parametrize("v", VECTORS["invalid"], ids=lambda v: v["name"])
def test_invalid_pieces_are_dropped_and_counted(core, v):
    before = counters(core)
    assert core.feed(bytes.fromhex(v["wire_hex"])) == b""  # never answered
    after = counters(core)
    assert {k: after[k] - before[k] for k in COUNTERS} == {
        k: int(k == v["error"]) for k in COUNTERS
    }


def test_the_damaged_stream_gives_the_documented_counters(core):
    stream = VECTORS["stream"]
    out = core.feed(bytes.fromhex(stream["wire_hex"]))
    assert counters(core) == stream["stats"]
    requests = [f for f in stream["frames"] if not f["flags"] & 0x09]
    answers = list(FrameDecoder().feed(out))
    assert [a.seq for a in answers] == [f["seq"] for f in requests]


@pytest.mark.parametrize("v", VECTORS["frames"], ids=lambda v: v["name"])
def test_valid_frames_are_decoded(core, v):
    out = core.feed(bytes.fromhex(v["wire_hex"]))
    assert counters(core)["frames"] == 1
    answers = list(FrameDecoder().feed(out))
    if v["flags"] & 0x09:  # a response or stream frame is not a request: not answered
        assert answers == []
    else:
        [answer] = answers
        assert answer.seq == v["seq"] and answer.is_response


REQUESTS = [v for v in VECTORS["messages"] if not v["response"]]
# a request vector's fields may name state the fresh core lacks: these answers show it parsed
EXPECTED_ERRORS = {
    "ConfigRead": {ErrorCode.NOT_FOUND, ErrorCode.TOO_LARGE},
    "ConfigCommit": {ErrorCode.INVALID},  # nothing staged: total_length exceeds it
    "StreamStart": {ErrorCode.UNSUPPORTED, ErrorCode.TOO_LARGE},
}


# protocol version 2 (PROTOCOL.md 14): asked after a HELLO that chose version 2; HEARTBEAT/LOG
# are not requests. The core driver has erased image slots (slot 0 named as running): each
# FW_* vector alone is answered, or refused as its state says (no upload, nothing verified;
# an asynchronous FW_VERIFY first says BUSY)
V2_TYPES = {0x0006, 0x0030, 0x0031, 0x0032, *range(0x0040, 0x0046)}
EXPECTED_ERRORS.update(
    {name: {ErrorCode.UNSUPPORTED} for name in ("Heartbeat", "LogMessage")}
    | {name: {ErrorCode.BAD_STATE} for name in ("FwWrite", "FwTest")}
    | {"FwVerify": {ErrorCode.BAD_STATE, ErrorCode.BUSY}}
)


@pytest.mark.parametrize("v", REQUESTS, ids=lambda v: v["class"])
def test_request_vectors_are_parsed_and_answered(core, v):
    if v["msg_type"] in V2_TYPES:
        core.feed(encode_message(Hello(1, 2, 8256, 0), seq=0xFFFF))
    out = core.feed(bytes.fromhex(v["wire_hex"]))
    if v["class"] == "StreamData":  # device-originated (flag STREAM): never answered
        assert out == b"" and counters(core)["frames"] == 1
        return
    # the answer; a LOG line the request queued (FW_BEGIN's) is device-originated, not one
    [frame] = [f for f in FrameDecoder().feed(out) if f.is_response]
    assert frame.seq == v["seq"]
    answer = decode_message(frame)
    if isinstance(answer, ErrorResponse):
        assert answer.request_type == v["msg_type"]
        assert answer.code in EXPECTED_ERRORS.get(v["class"], set()), answer
    else:
        assert frame.msg_type == v["msg_type"]


def test_a_measurement_the_front_end_loses_is_skipped_not_invented(core):
    """hal_acq_read fails on channel 2 of acquisition 1: that acquisition is abandoned (an
    overrun, its index used), never sent with made-up samples; the stream goes on."""
    from spiel_edge.protocol import (
        AcquisitionAssembler,
        Hello,
        StreamData,
        StreamStart,
        encode_message,
    )

    core.feed(encode_message(Hello(1, 2, 8256, 0), seq=1))
    assert core.command("acqfail 6") == "ok"  # reads: 4 of acquisition 0, then ch 0, 1, *2*
    out = core.feed(encode_message(StreamStart(3, 0.0, 64, 0, 0), seq=2))
    for t_us in (3_000, 6_000):  # as fast as it can: one listening window (2.9 ms) apart
        core.set_time(t_us)
        out += core.poll(50)
    assembler, done, frames = AcquisitionAssembler(), [], 0
    for f in FrameDecoder().feed(out):
        if f.msg_type == StreamData.MSG_TYPE:
            frames += 1
            acq = assembler.feed(StreamData.unpack(f.payload), f.aux)
            if acq is not None:
                done.append(acq.index)
    assert done == [0, 2] and frames == 4 + 2 + 4
    assert core.stats()["overruns"] == 1


def test_as_fast_as_it_can_is_one_listening_window_apart(core):
    """Rate 0 with a front end that answers at once (here a frozen clock): one acquisition per
    listening window (64 samples at 22 kHz: 2909 us), each stamped with its own time, as the
    virtual board does (tests/live/test_sim_board.py); a burst with one stamp reads on the host
    as a clock that stood still."""
    from spiel_edge.protocol import Hello, StreamData, StreamStart, encode_message

    def stamps(wire: bytes) -> set[int]:
        frames = FrameDecoder().feed(wire)
        data = [StreamData.unpack(f.payload) for f in frames if f.msg_type == StreamData.MSG_TYPE]
        return {d.timestamp_us for d in data}

    core.feed(encode_message(Hello(1, 2, 8256, 0), seq=1))
    first = stamps(core.feed(encode_message(StreamStart(0, 0.0, 64, 0, 0), seq=2)))
    first |= stamps(core.poll(50))
    core.set_time(2_000)
    early = stamps(core.poll(50))
    core.set_time(2_950)
    later = stamps(core.poll(50))
    assert len(first) == 1 and early == set() and len(later) == 1
    assert min(later) - max(first) >= 2_909
