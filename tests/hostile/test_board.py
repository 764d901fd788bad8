"""A hostile board over a pseudo-terminal: wrong protocol versions, absurd HELLO fields,
garbage and silence. The host refuses it with one clear line naming both sides (or the
decoder's counters), never a traceback or a hang."""

from __future__ import annotations

import os
import select
import threading
import tty

import pytest

from spiel_edge.device import DeviceSession
from spiel_edge.errors import DeviceError
from spiel_edge.protocol import FrameDecoder, Hello, HelloResponse, encode_message
from spiel_edge.protocol.errors import ErrorCode
from spiel_edge.protocol.messages import ErrorResponse

GOOD = {"protocol_version": 1, "min_version": 1, "max_version": 1, "n_channels": 4}


class HostileBoard:
    """Answers every frame it receives with ``answer(frame) -> bytes`` (or keeps silent)."""

    def __init__(self, answer) -> None:
        self.master, slave = os.openpty()
        tty.setraw(slave)
        self.path = os.ttyname(slave)
        self._slave = slave
        self._answer = answer
        self._decoder = FrameDecoder()  # loads the COBS kernels before the host says Hello
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._serve, daemon=True)
        self._thread.start()

    def _serve(self) -> None:
        decoder = self._decoder
        while not self._stop.is_set():
            ready, _, _ = select.select([self.master], [], [], 0.02)
            if not ready:
                continue
            try:
                data = os.read(self.master, 65536)
            except OSError:
                return
            for frame in decoder.feed(data):
                reply = self._answer(frame)
                if reply:
                    os.write(self.master, reply)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(1)
        for fd in (self.master, self._slave):
            os.close(fd)


@pytest.fixture
def board(monkeypatch):
    monkeypatch.setattr(Hello, "TIMEOUT_S", 0.1)  # no-answer cases end in 0.4 s, not 2 s
    made = []

    def make(answer):
        made.append(HostileBoard(answer))
        return made[-1].path

    yield make
    for b in made:
        b.close()


def hello(**fields):
    values = {**GOOD, **fields}
    return lambda frame: encode_message(HelloResponse(**values), seq=frame.seq)


CASES = {
    "chose-version-3": (hello(protocol_version=3, max_version=3), "protocol version 3"),
    "range-5-9": (hello(protocol_version=5, min_version=5, max_version=9), "5-9"),
    "empty-range": (hello(min_version=3, max_version=1), "empty protocol range"),
    "version-0": (hello(protocol_version=0, min_version=0, max_version=0), "update the firmware"),
    "channels-0": (hello(n_channels=0), "n_channels 0"),
    "channels-200": (hello(n_channels=200), "n_channels 200"),
    "samples-0": (hello(max_samples=0), "max_samples 0"),
    "samples-huge": (hello(max_samples=60000), "max_samples 60000"),
    "payload-tiny": (hello(max_payload=1), "max_payload 1"),
    "too-new": (
        lambda f: encode_message(ErrorResponse(ErrorCode.VERSION_TOO_NEW, f.msg_type), seq=f.seq),
        "update the firmware",
    ),
    "too-old": (
        lambda f: encode_message(ErrorResponse(ErrorCode.VERSION_TOO_OLD, f.msg_type), seq=f.seq),
        "update spiel-edge",
    ),
    "garbage": (lambda f: bytes(range(1, 256)) * 4 + b"\x00", "undecodable"),
    "silent": (lambda f: b"", "nothing was received"),
}


@pytest.mark.parametrize("kind", sorted(CASES))
def test_hostile_hello_is_refused_clearly(board, kind):
    answer, needle = CASES[kind]
    session = DeviceSession(board(answer), reconnect=False)
    with pytest.raises(DeviceError) as caught:
        session.open()
    message = str(caught.value)
    assert needle in message and "\n" not in message and len(message) < 400
    if kind.startswith(("chose", "range", "too")):
        assert "1" in message  # this host's range is named too
    session.close()


@pytest.mark.parametrize("kind", ["channels-200", "garbage", "range-5-9"])
def test_hostile_board_through_the_cli(cli, board, tmp_path, kind):
    ran = cli("run", "--port", board(CASES[kind][0]), "-o", tmp_path / "o.ndjson", "--frames", "1")
    assert ran.status == 2 and ran.err.startswith("error:") and ran.err.count("\n") <= 3
