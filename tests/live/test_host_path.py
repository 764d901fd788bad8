"""The lean host path: a posix port read straight from its descriptor (bounded reads, an
unplug still an unplug), NDJSON held by a live run and flushed when it has caught up."""

from __future__ import annotations

import contextlib
import json
import os

import pytest

from spiel_edge.errors import DeviceDisconnectedError
from spiel_edge.link import serial_link
from spiel_edge.outputs import MultiSink
from spiel_edge.outputs.ndjson import NdjsonSink


@pytest.fixture
def pty_pair():
    master, slave = os.openpty()
    yield master, os.ttyname(slave)
    for fd in (master, slave):
        with contextlib.suppress(OSError):
            os.close(fd)


def test_a_pty_is_read_from_its_descriptor_in_bounded_pieces(pty_pair):
    master, path = pty_pair
    link = serial_link.open_serial(path, exclusive=False)
    try:
        assert link._fd is not None  # posix: no pyserial read loop
        assert link.read(0.01) == b""  # nothing there: the timeout, no error
        payload = bytes(range(256)) * 80  # 20480 bytes: more than one read may take
        written = 0
        got = b""
        while written < len(payload) or len(got) < len(payload):
            if written < len(payload):
                written += os.write(master, payload[written : written + 4096])
            piece = link.read(0.5)
            assert len(piece) <= serial_link.READ_MAX
            got += piece
        assert got == payload
    finally:
        link.close()


def test_a_vanished_pty_is_a_lost_link(pty_pair):
    master, path = pty_pair
    link = serial_link.open_serial(path, exclusive=False)
    try:
        os.close(master)  # the board's side goes away: the slave reads EIO
        with pytest.raises(DeviceDisconnectedError, match="link lost"):
            for _ in range(3):
                link.read(0.2)
    finally:
        link.close()


def test_held_ndjson_reaches_the_file_at_flush_and_at_close(tmp_path):
    target = tmp_path / "out.ndjson"
    sink = MultiSink([NdjsonSink(target)])
    sink.batch()
    records = [{"seq": i, "position_mm": [1.5, -2.25, 100.0]} for i in range(3)]
    for record in records:
        sink.write(record)
    assert target.read_text() == ""  # held: one flush per burst, not per record
    sink.flush()
    assert [json.loads(line) for line in target.read_text().splitlines()] == records
    sink.write({"seq": 3})
    sink.close()
    assert len(target.read_text().splitlines()) == 4


def test_an_unheld_ndjson_sink_flushes_each_record(tmp_path):
    target = tmp_path / "out.ndjson"
    sink = NdjsonSink(target)
    sink.write({"seq": 0})
    assert json.loads(target.read_text()) == {"seq": 0}
    sink.close()
