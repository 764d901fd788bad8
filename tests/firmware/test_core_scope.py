"""The C core's scope, frozen (docs/reference-board.md): the virtual board in Python is the
executable specification, and the C core answers exactly the requests of PROTOCOL.md 12.1's
list, each under the protocol version the list gives it; every one of them is a request of
section 6's table, the transcript test (test_fw_transcript.py) sends each to both boards and
test_vectors.json holds a vector of each. A request added to the C core without the list (or
the list without the transcript) fails here."""

from __future__ import annotations

import json
import re

from spiel_edge.protocol import (
    ErrorResponse,
    FrameDecoder,
    Hello,
    decode_message,
    encode_frame,
    encode_message,
)
from spiel_edge.protocol import messages as m
from spiel_edge.protocol.errors import ErrorCode
from spiel_edge.sim.board import VirtualBoard
from spiel_edge.sim.scenes import ReplayScene
from tests.firmware import test_fw_transcript
from tests.firmware.firmware import FIRMWARE, PROTO

ROOT = FIRMWARE.parents[1]


def protocol_requests(text: str) -> dict[str, tuple[int, int]]:
    """PROTOCOL.md section 6's message table: NAME -> (msg_type, lowest version) of every row
    with a request (the host sends it; HEARTBEAT, LOG, STREAM_DATA and ERROR have none)."""
    rows = re.findall(r"^\| (0x[0-9A-F]{4}) \| (\w+) \| ([^|]+)\|", text, re.M)
    return {
        name: (int(code, 16), 2 if "(v2" in request else 1)
        for code, name, request in rows
        if not request.strip().startswith("—")
    }


def c_request_table(device_c: str) -> dict[str, tuple[int, int]]:
    """device.c's request table: NAME -> (msg_type, min_version), every build's rows (those
    under #if SPIEL_FW_UPDATE included)."""
    codes = {
        name: int(code, 16)
        for name, code in re.findall(
            r"#define SP_MSG_(\w+)\s+(0x[0-9A-Fa-f]+)u", (PROTO / "spiel_registry.h").read_text()
        )
    }
    body = re.search(r"\} requests\[\] = \{(.*?)\n\};", device_c, re.S)
    assert body, "device.c has no request table"
    rows = re.findall(r"\{SP_MSG_(\w+), (\d), (\w+), (\w+)\}", body.group(1))
    return {name: (codes[name], int(version)) for name, version, _, _ in rows}


def scope_list(text: str) -> dict[str, int]:
    """PROTOCOL.md 12.1's table: NAME -> the version it is listed under."""
    part = text.split("<!-- c-reference-scope:", 1)[1].split("\n\n", 1)[0]
    return {
        name.strip(): int(version)
        for version, names in re.findall(r"^\| (\d) \| ([A-Z_, ]+) \|$", part, re.M)
        for name in names.split(",")
    }


def listed() -> dict[str, tuple[int, int]]:
    """The frozen scope: NAME -> (msg_type, version), from PROTOCOL.md 12.1 and section 6."""
    text = (ROOT / "firmware_protocol" / "PROTOCOL.md").read_text()
    requests = protocol_requests(text)
    return {name: (requests[name][0], version) for name, version in scope_list(text).items()}


def test_the_scope_is_requests_of_the_protocol_under_their_versions():
    text = (ROOT / "firmware_protocol" / "PROTOCOL.md").read_text()
    requests, scope = protocol_requests(text), scope_list(text)
    assert len(requests) == 19 and len(scope) == 19
    assert "HEARTBEAT" not in requests and "STREAM_DATA" not in requests
    for name, version in scope.items():
        assert name in requests, f"{name}: not a request of PROTOCOL.md section 6"
        assert requests[name][1] == version, f"{name}: section 6 gives another version"


def test_the_c_cores_request_table_is_the_protocols_list():
    device_c = (FIRMWARE / "core" / "device.c").read_text()
    assert c_request_table(device_c) == listed()


def test_a_row_added_to_the_c_table_is_seen():
    device_c = (FIRMWARE / "core" / "device.c").read_text()
    grown = device_c.replace(
        "    {SP_MSG_PING, 1, NEEDS_NOTHING, NULL},\n",
        "    {SP_MSG_PING, 1, NEEDS_NOTHING, NULL},\n    {SP_MSG_LOG, 2, NEEDS_NOTHING, NULL},\n",
    )
    assert grown != device_c and c_request_table(grown) != listed()


def test_the_transcript_sends_every_listed_request_to_both_boards():
    sent = {
        type(step).MSG_TYPE for step in test_fw_transcript.script() if isinstance(step, m.Message)
    }
    assert {code for code, _ in listed().values()} <= sent


def test_every_listed_request_has_a_test_vector():
    vectors = json.loads((ROOT / "firmware_protocol" / "test_vectors.json").read_text())
    requests = {v["msg_type"] for v in vectors["messages"] if not v["response"]}
    assert {code for code, _ in listed().values()} <= requests


def test_the_virtual_boards_request_table_holds_the_list():
    """The specification's table (sim/board.py REQUESTS) holds every row of the C core's, under
    the same version: one shape on both sides. It may hold more (a request newer than the
    frozen scope lives in the virtual board first)."""
    from spiel_edge.sim.board import REQUESTS

    table = {cls.MSG_TYPE: version for cls, (_, version) in REQUESTS.items()}
    assert {code: table.get(code) for code, _ in listed().values()} == dict(listed().values())
    for cls, (name, _) in REQUESTS.items():
        assert callable(getattr(VirtualBoard, name, None)), (cls.__name__, name)


def _answer(board: VirtualBoard, msg_type: int, seq: int) -> object:
    out = board.receive(encode_frame(msg_type, b"", seq=seq), 1.0)
    frames = [f for o in out for f in FrameDecoder().feed(o.wire) if f.seq == seq]
    return decode_message(frames[0])


def test_the_virtual_board_answers_the_list_and_nothing_else():
    """The executable specification handles each listed request (an empty payload may be
    refused as INVALID, never as a request it does not know) and refuses one not listed."""
    board = VirtualBoard(ReplayScene(), now=0.0)
    board.receive(encode_message(Hello(1, 2, 8256, 0), seq=1), 0.5)
    for n, (name, (code, _)) in enumerate(sorted(listed().items()), start=2):
        answer = _answer(board, code, n)
        assert not (isinstance(answer, ErrorResponse) and answer.code == ErrorCode.UNSUPPORTED), (
            name,
            answer,
        )
        if name == "REBOOT":
            board = VirtualBoard(ReplayScene(), now=0.0)
            board.receive(encode_message(Hello(1, 2, 8256, 0), seq=1), 0.5)
    answer = _answer(board, 0x0007, 99)  # not in the list
    assert isinstance(answer, ErrorResponse) and answer.code == ErrorCode.UNSUPPORTED
