"""Hostile firmware built into the virtual board: ``sim://?lie=MODE`` makes it contradict itself
the way a buggy firmware would, so the test suite keeps the host's checks of a lying board
(device/sanity.py, docs/reliability.md) honest. Each mode changes only what it names.

=================  ===========================================================================
mode               what the board does
=================  ===========================================================================
channels           its stream says one channel more than its HELLO and STREAM_START answer
fewer-channels     its stream says one channel fewer
samples            each frame carries half the samples STREAM_START promised
format             frames say sample format I16_RF after promising U16_ENVELOPE
channel-index      the last channel of each acquisition is numbered n_channels (out of range)
counter-restart    the frame counter restarts at 0 with every acquisition
index-repeat       every acquisition has index 0 (the frame counter advances)
incomplete         the last channel of every acquisition is never sent
mute-stream        STREAM_START succeeds, the board says it streams, nothing is ever sent
endless-config     every CONFIG_READ is answered with a full chunk: a config without end
oversized-config   CONFIG_READ answers twice the bytes that were asked
mute-config        CONFIG_READ is never answered
start-channels     STREAM_START answers one channel more than HELLO
hello-control      HELLO's serial and firmware version hold control characters / escapes
start-at-ignored   it offers START_AT and starts every stream at once, whatever time it is given
                   (never on the named grid: half a period later when at once would be)
=================  ===========================================================================
"""

from __future__ import annotations

import dataclasses

from spiel_edge.link.sim_options import LIES  # the names lie= takes
from spiel_edge.protocol import Flags, FrameDecoder, SampleFormat, StreamData, encode_message
from spiel_edge.protocol import messages as m
from spiel_edge.sim.faults import Outgoing

HOSTILE_SERIAL = "SIM\x1b[2J\x07\n"  # clear screen, bell, newline: 9 bytes (fits 16)
HOSTILE_FIRMWARE = "evil\r\x1b]0;x\x07"


def install(board, lie: str) -> None:
    """Make ``board`` (a VirtualBoard) lie as ``lie`` says (one of LIES; "" does nothing)."""
    if not lie:
        return
    if lie not in LIES:
        raise ValueError(lie)
    board.lie = lie
    if lie in ("endless-config", "oversized-config", "mute-config"):
        _config_lies(board, lie)
    elif lie in ("start-channels", "hello-control"):
        _answer_lies(board, lie)
    elif lie == "mute-stream":
        board.due = lambda now, room, limit=None: []
    elif lie == "start-at-ignored":
        board.first_due = ignoring_start_times(board.first_due)
    else:
        _stream_lies(board, lie)


IGNORED_START_OFF_S = 0.001  # "at once" this near the named grid would hide the lie


def ignoring_start_times(named_due):
    """``first_due`` of a firmware that starts every stream at once, whatever time it is
    given; never on the named grid by chance (half a period later then), so that a test of
    the lie sees it every time."""

    def first_due(start_at_us: int, period_s: float, now: float) -> float:
        named = named_due(start_at_us, period_s, now)
        if named is None or period_s <= 0 or start_at_us == 0:
            return now  # a plain start (no time named): at once, as any board
        off = (now - named) % period_s
        return now + period_s / 2 if min(off, period_s - off) < IGNORED_START_OFF_S else now

    return first_due


def _config_lies(board, lie: str) -> None:
    read = board._config_read
    if lie == "oversized-config":  # room in a frame for twice the chunk the host asks for
        board.board_max_payload = min(board.board_max_payload, 1024)

    def config_read(req: m.ConfigRead, now: float):
        if lie == "endless-config":
            return m.ConfigReadResponse(req.offset, b"#" * req.length)
        if lie == "oversized-config":
            return m.ConfigReadResponse(req.offset, b"#" * (2 * req.length))
        return read(req, now)

    board._config_read = config_read
    if lie == "mute-config":
        answer = board._answer

        def silent(frame, now):
            if frame.msg_type == m.MsgType.CONFIG_READ:
                return None
            return answer(frame, now)

        board._answer = silent


def _answer_lies(board, lie: str) -> None:
    hello, start = board._hello, board._stream_start

    def lying_hello(req, now):
        answer = hello(req, now)
        if lie == "hello-control" and isinstance(answer, m.HelloResponse):
            answer = dataclasses.replace(
                answer, serial=HOSTILE_SERIAL, firmware_version=HOSTILE_FIRMWARE
            )
        return answer

    def lying_start(req, now):
        answer = start(req, now)
        if lie == "start-channels" and isinstance(answer, m.StreamStartResponse):
            answer = dataclasses.replace(answer, n_channels=answer.n_channels + 1)
        return answer

    board._hello, board._stream_start = lying_hello, lying_start


def _stream_lies(board, lie: str) -> None:
    acquire = board._acquire

    def lying_acquire(stream):
        out = []
        for item in acquire(stream):
            if item.acquisition is None:
                out.append(item)
                continue
            changed = _lie_about(item.wire, lie)
            if changed is not None:
                out.append(Outgoing(changed, acquisition=item.acquisition))
        return out

    board._acquire = lying_acquire


def _lie_about(wire: bytes, lie: str) -> bytes | None:
    """One STREAM_DATA frame as the lying firmware sends it (None: not sent at all)."""
    (frame,) = FrameDecoder().feed(wire)
    msg = StreamData.unpack(frame.payload)
    aux, flags = frame.aux, frame.flags
    last = msg.channel == msg.n_channels - 1
    if lie == "channels":
        msg = dataclasses.replace(msg, n_channels=msg.n_channels + 1)
    elif lie == "fewer-channels":
        msg = dataclasses.replace(msg, n_channels=max(msg.n_channels - 1, 1))
    elif lie == "samples":
        msg = dataclasses.replace(msg, samples=msg.samples[: len(msg.samples) // 2 // 2 * 2])
    elif lie == "format":
        msg = dataclasses.replace(msg, sample_format=SampleFormat.I16_RF)
    elif lie == "channel-index" and last:
        msg = dataclasses.replace(msg, channel=msg.n_channels)
    elif lie == "counter-restart":
        aux = msg.channel
    elif lie == "index-repeat":
        msg = dataclasses.replace(msg, acquisition=0)
    elif lie == "incomplete" and last:
        return None
    flags &= ~(Flags.RESPONSE | Flags.STREAM)  # encode_message sets these itself
    return encode_message(msg, seq=frame.seq, flags=flags, aux=aux)
