"""A firmware that lies: what the stream says, checked against the board's HELLO, its answer to
STREAM_START and the stream's own history. A contradiction is a firmware bug; it is reported
at once, in one line naming the board, instead of leaving the session waiting for
acquisitions that can never be assembled (docs/reliability.md, "A firmware that lies").

Pure (no I/O): the assembly feeds it every STREAM_DATA frame before the assembler sees it; the
session asks it whether the stream still makes progress.
"""

from __future__ import annotations

import dataclasses

from spiel_edge.errors import DeviceError
from spiel_edge.protocol import HelloResponse, StreamStartResponse
from spiel_edge.protocol.stream_data import STREAM_HEADER
from spiel_edge.safety.shown import escape

_MASK = 0xFFFFFFFF
MAX_CONTRADICTIONS = 3  # restarts or repeats of a counter before the stream is refused
MAX_BOARD_CONFIG_BYTES = 64 * 1024  # a board config is a few kB (a flash slot is 4 KiB)
CONFIG_READ_TIMEOUT_S = 10.0  # a whole config read, however many chunks


class FirmwareError(DeviceError):
    """The board contradicts itself (a firmware bug); reconnecting would not help."""


def sanitized_hello(hello: HelloResponse) -> HelloResponse:
    """HELLO with its strings (serial, firmware version) escaped: control characters or
    escape sequences from a board are shown as ``\\x1b``, never sent to a terminal."""
    serial, firmware = escape(hello.serial), escape(hello.firmware_version)
    if serial == hello.serial and firmware == hello.firmware_version:
        return hello
    return dataclasses.replace(hello, serial=serial, firmware_version=firmware)


def board_name(url: str, hello: HelloResponse | None) -> str:
    """``url (board SERIAL, firmware VERSION)``, the board's strings escaped."""
    if hello is None:
        return url
    return f"{url} (board {escape(hello.serial)}, firmware {escape(hello.firmware_version)})"


def _ahead(a: int, b: int) -> int:
    """How far ``a`` is ahead of ``b`` on a 32-bit wrapping counter (negative: behind)."""
    d = (a - b) & _MASK
    return d - (1 << 32) if d >= 1 << 31 else d


class StreamSanity:
    """Checks one stream; ``frame`` raises FirmwareError on a contradiction."""

    def __init__(self) -> None:
        self.who = ""
        self.n_channels: int | None = None
        self.board_channels = 0
        self.n_samples: int | None = None
        self.sample_format: int | None = None
        self.reset()

    def reset(self) -> None:
        self._last_index: int | None = None
        self._last_counter: int | None = None
        self._channels_seen: set[int] = set()
        self.restarts = 0  # the frame counter went back while the index advanced
        self.repeats = 0  # the index went back (or stayed) while the counter advanced

    def expect(self, who: str, hello: HelloResponse | None, answer: StreamStartResponse) -> None:
        """The stream the board promised; its answer checked against its HELLO."""
        self.who = who
        self.reset()
        # fewer is a channel subset (protocol version 2); more, or none, is a lie
        if hello is not None and not 1 <= answer.n_channels <= hello.n_channels:
            raise FirmwareError(
                f"{who}: STREAM_START answered {answer.n_channels} channels, its HELLO "
                f"{hello.n_channels}: a firmware bug; nothing was read"
            )
        if hello is not None and not 1 <= answer.n_samples <= hello.max_samples:
            raise FirmwareError(
                f"{who}: STREAM_START answered {answer.n_samples} samples per channel, its "
                f"HELLO allows 1-{hello.max_samples}: a firmware bug; nothing was read"
            )
        self.n_channels = answer.n_channels
        self.board_channels = hello.n_channels if hello is not None else answer.n_channels
        self.n_samples = answer.n_samples
        self.sample_format = answer.sample_format

    def payload(self, payload: bytes, counter: int | None) -> None:
        """One STREAM_DATA frame's payload (valid CRC), before assembly: its sub-header is
        read here (one struct unpack), whatever the assembler does with the samples."""
        if self.n_channels is None or len(payload) < STREAM_HEADER.size:
            return  # no stream promised yet, or too short: the assembler counts it
        index, channel, n_channels, sample_format, _, _, _, n_samples, _ = (
            STREAM_HEADER.unpack_from(payload)
        )
        problems = []
        if n_channels != self.n_channels:
            problems.append(f"{n_channels} channels (promised {self.n_channels})")
        if channel >= self.board_channels:  # ids are physical: a subset keeps its ids
            problems.append(f"channel {channel} of {self.board_channels}")
        if sample_format != self.sample_format:
            problems.append(f"sample format {sample_format} (promised {self.sample_format})")
        elif n_samples != self.n_samples:
            problems.append(f"{n_samples} samples (promised {self.n_samples})")
        if problems:
            raise FirmwareError(
                f"{self.who}: its stream says {', '.join(problems)}: a firmware bug; stopped"
            )
        self._history(index, channel, counter)

    def _history(self, index: int, channel: int, counter: int | None) -> None:
        last_index, last_counter = self._last_index, self._last_counter
        self._last_index = index
        if counter is not None:
            self._last_counter = counter
        again = index == last_index and channel in self._channels_seen
        if index != last_index:
            self._channels_seen = set()
        self._channels_seen.add(channel)
        if last_index is None or counter is None or last_counter is None:
            return
        index_step = _ahead(index, last_index)
        counter_step = _ahead(counter, last_counter)
        if index_step > 0 and counter_step <= 0:
            self.restarts += 1
        elif counter_step > 0 and (index_step < 0 or again):
            self.repeats += 1
        if self.restarts >= MAX_CONTRADICTIONS:
            raise FirmwareError(
                f"{self.who}: its frame counter goes back (to {counter}) while the acquisition "
                f"index advances (to {index}), {self.restarts} times: a firmware bug; stopped"
            )
        if self.repeats >= MAX_CONTRADICTIONS:
            raise FirmwareError(
                f"{self.who}: its acquisition index repeats ({index}) while the frame counter "
                f"advances, {self.repeats} times: a firmware bug; stopped"
            )
