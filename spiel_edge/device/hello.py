"""Checks of the board's HELLO answer (PROTOCOL.md section 5): the protocol version the board
chose must be one both sides speak, and its sizes must be ones the host can handle. A board
that fails them is refused with a message naming both sides, before any stream starts."""

from __future__ import annotations

from spiel_edge.errors import DeviceError
from spiel_edge.protocol import (
    MAX_PAYLOAD,
    MIN_PAYLOAD,
    MIN_PROTOCOL_VERSION,
    HelloResponse,
)
from spiel_edge.protocol import MAX_PROTOCOL_VERSION as PROTOCOL_VERSION
from spiel_edge.protocol.errors import ErrorCode

MAX_CHANNELS = 64  # channels one board may report
MAX_SAMPLES = 4096  # samples per channel (one channel fits MAX_PAYLOAD)


def link_payload(hello: HelloResponse) -> int:
    """The largest payload either side may send on this link: the smaller maximum."""
    return min(hello.max_payload, MAX_PAYLOAD)


def host_range() -> str:
    return _range(MIN_PROTOCOL_VERSION, PROTOCOL_VERSION)


def _range(low: int, high: int) -> str:
    return str(low) if low == high else f"{low}-{high}"


def version_refused(url: str, code: int) -> str:
    """The board answered HELLO with VERSION_TOO_OLD/NEW."""
    side = "update spiel-edge" if code == ErrorCode.VERSION_TOO_OLD else "update the firmware"
    older = "this host is older" if code == ErrorCode.VERSION_TOO_OLD else "the board is older"
    return (
        f"{url}: the board speaks none of this host's protocol versions ({host_range()}); "
        f"{older}: {side}"
    )


def check_hello(url: str, hello: HelloResponse) -> None:
    """DeviceError naming the field when the answer is not one the host can work with."""
    board = _range(hello.min_version, hello.max_version)
    if hello.min_version > hello.max_version:
        raise DeviceError(f"{url}: the board reports an empty protocol range {board}")
    if not MIN_PROTOCOL_VERSION <= hello.protocol_version <= PROTOCOL_VERSION or not (
        hello.min_version <= hello.protocol_version <= hello.max_version
    ):
        raise DeviceError(
            f"{url}: the board chose protocol version {hello.protocol_version}; the board speaks "
            f"{board}, this host {host_range()}"
            + (
                ": update spiel-edge"
                if hello.min_version > PROTOCOL_VERSION
                else ": update the firmware"
                if hello.max_version < MIN_PROTOCOL_VERSION
                else ""
            )
        )
    problems = []
    if not 1 <= hello.n_channels <= MAX_CHANNELS:
        problems.append(f"n_channels {hello.n_channels} (allowed 1-{MAX_CHANNELS})")
    if not 1 <= hello.max_samples <= MAX_SAMPLES:
        problems.append(f"max_samples {hello.max_samples} (allowed 1-{MAX_SAMPLES})")
    if hello.max_payload < MIN_PAYLOAD:  # larger than the host's: the host's limit applies
        problems.append(f"max_payload {hello.max_payload} (at least {MIN_PAYLOAD})")
    if problems:
        raise DeviceError(f"{url}: the board's HELLO is not usable: {', '.join(problems)}")
