"""UDP datagrams on loopback."""

from __future__ import annotations

import json
import socket

import pytest

from spiel_edge.errors import ConfigError
from spiel_edge.outputs.udp import UdpSink, parse_host_port


@pytest.fixture
def receiver():
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    sock.settimeout(2.0)
    yield sock
    sock.close()


def test_one_json_record_per_datagram(receiver):
    port = receiver.getsockname()[1]
    sink = UdpSink(f"127.0.0.1:{port}")
    records = [{"seq": i, "position_mm": [float(i), 2.0, 300.0], "reason": None} for i in range(5)]
    for record in records:
        sink.write(record)
    got = [json.loads(receiver.recv(65535)) for _ in records]
    sink.close()
    assert got == records and sink.sent == 5 and sink.failed == 0


def test_send_failures_are_counted_not_raised(receiver, monkeypatch):
    sink = UdpSink(f"127.0.0.1:{receiver.getsockname()[1]}")

    def refuse(*args):
        raise OSError(101, "Network is unreachable")

    monkeypatch.setattr(
        sink, "_sock", type("S", (), {"sendto": staticmethod(refuse), "close": lambda self: None})()
    )
    sink.write({"seq": 0})
    sink.write({"seq": 1})
    assert sink.failed == 2 and sink.sent == 0


def test_oversized_record_is_dropped(receiver):
    sink = UdpSink(f"127.0.0.1:{receiver.getsockname()[1]}")
    sink.write({"blob": "x" * 70000})
    sink.write({"seq": 1})
    assert json.loads(receiver.recv(65535)) == {"seq": 1}
    assert sink.failed == 1
    sink.close()


@pytest.mark.parametrize(
    "text,expected",
    [
        ("127.0.0.1:9870", ("127.0.0.1", 9870)),
        ("[::1]:9870", ("::1", 9870)),
        ("robot.local:1", ("robot.local", 1)),
    ],
)
def test_parse_host_port(text, expected):
    assert parse_host_port(text) == expected


def test_parse_port_only_needs_a_default_host():
    assert parse_host_port("8765", default_host="127.0.0.1") == ("127.0.0.1", 8765)
    assert parse_host_port("0.0.0.0:8765", default_host="127.0.0.1") == ("0.0.0.0", 8765)
    for bad in ("8765", "host:", "host:99999", "host:abc", ":1"):
        with pytest.raises(ConfigError, match="HOST:PORT"):
            parse_host_port(bad)
