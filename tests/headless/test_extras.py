"""The optional live outputs on loopback: Foxglove WebSocket and Zenoh (skipped without the extra)."""

from __future__ import annotations

import json
import re
import socket
import struct
import time
from pathlib import Path

import pytest

from ._ws import MiniWebSocket

RECORD = {
    "seq": 3,
    "position_mm": [10.0, -20.0, 300.0],
    "reason": None,
    "residual_mm": 0.5,
    "echoes": [[12.0]] * 4,
    "matched": [0, 0, 0, 0],
    "targets": [
        {
            "position_mm": [10.0, -20.0, 300.0],
            "covariance_mm2": [[40.0, 5.0, 0.0], [5.0, 30.0, 0.0], [0.0, 0.0, 90.0]],
            "residual_mm": 0.5,
            "matched": [0, 0, 0, 0],
            "score": 1.0,
            "track_id": 4,
        },
        {
            "position_mm": [-60.0, 0.0, 200.0],
            "covariance_mm2": [[9.0, 0.0, 0.0], [0.0, 9.0, 0.0], [0.0, 0.0, 9.0]],
            "residual_mm": 1.5,
            "matched": [None, 1, 1, 1],
            "score": 0.5,
        },
    ],
    "tracks": [
        {
            "track_id": 4,
            "position_mm": [11.0, -20.0, 301.0],
            "velocity_mm_s": [100.0, 0.0, 0.0],
            "covariance_mm2": [[20.0, 0.0, 0.0], [0.0, 20.0, 0.0], [0.0, 0.0, 40.0]],
            "age": 12,
            "hits": 11,
        }
    ],
}


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_foxglove_serves_scene_and_records_on_localhost():
    pytest.importorskip(
        "foxglove", reason="extra 'foxglove' not installed (pip install 'spiel-edge[foxglove]')"
    )
    from spiel_edge.outputs.foxglove import POSITION_TOPIC, SCENE_TOPIC, FoxgloveSink

    sink = FoxgloveSink("0", receivers_mm=[[0, 0, 0], [75, 0, 0]])  # port only: localhost
    ws = MiniWebSocket("127.0.0.1", sink.port, "foxglove.sdk.v1")
    try:
        channels: dict[str, dict] = {}
        deadline = time.monotonic() + 5
        while len(channels) < 2 and time.monotonic() < deadline:
            message = json.loads(ws.recv()[1])
            if message["op"] == "advertise":
                channels.update({c["topic"]: c for c in message["channels"]})
        assert channels[SCENE_TOPIC]["schemaName"] == "foxglove.SceneUpdate"
        assert channels[POSITION_TOPIC]["encoding"] == "json"
        ws.send_json(
            {
                "op": "subscribe",
                "subscriptions": [
                    {"id": 1, "channelId": channels[POSITION_TOPIC]["id"]},
                    {"id": 2, "channelId": channels[SCENE_TOPIC]["id"]},
                ],
            }
        )
        got: dict[int, bytes] = {}
        while len(got) < 2 and time.monotonic() < deadline:
            sink.write(RECORD)  # until the subscription is in place
            frame = ws.recv(wait_s=0.1)
            if frame is None:
                continue
            opcode, payload = frame
            if opcode == 2 and payload[0] == 1:  # binary MessageData
                sub_id = struct.unpack_from("<I", payload, 1)[0]
                got[sub_id] = payload[13:]
        assert json.loads(got[1]) == RECORD
        scene = got[2]  # protobuf SceneUpdate: entity ids and the track's label
        assert b"target" in scene and b"target/1" in scene and b"receivers" in scene
        assert b"track/4" in scene
    finally:
        ws.close()
        sink.close()


def test_foxglove_binds_localhost_by_default():
    pytest.importorskip(
        "foxglove", reason="extra 'foxglove' not installed (pip install 'spiel-edge[foxglove]')"
    )
    from spiel_edge.outputs.foxglove import FoxgloveSink

    sink = FoxgloveSink("0")
    try:
        with socket.socket() as probe:
            probe.settimeout(2)
            probe.connect(("127.0.0.1", sink.port))  # reachable on loopback
        rows = [line.split() for line in Path("/proc/net/tcp").read_text().splitlines()[1:]]
        hosts = {
            r[1].rsplit(":", 1)[0]
            for r in rows
            if r[3] == "0A" and int(r[1].rsplit(":", 1)[1], 16) == sink.port
        }
        assert hosts == {"0100007F"}  # listening on 127.0.0.1 only
    finally:
        sink.close()


def test_zenoh_publishes_records_on_the_key():
    zenoh = pytest.importorskip(
        "zenoh", reason="extra 'zenoh' not installed (pip install 'spiel-edge[zenoh]')"
    )
    from spiel_edge.outputs.zenoh import ZenohSink

    port = _free_port()
    quiet = {"scouting": {"multicast": {"enabled": False}}}
    pub = zenoh.Config.from_json5(
        json.dumps({**quiet, "listen": {"endpoints": [f"tcp/127.0.0.1:{port}"]}})
    )
    sub = zenoh.Config.from_json5(
        json.dumps({**quiet, "connect": {"endpoints": [f"tcp/127.0.0.1:{port}"]}})
    )
    sink = ZenohSink("test/robot1/spiel", pub)
    received: list[tuple[str, str]] = []
    session = zenoh.open(sub)
    try:
        session.declare_subscriber(
            "test/*/spiel", lambda s: received.append((str(s.key_expr), s.payload.to_string()))
        )
        deadline = time.monotonic() + 10
        while not received and time.monotonic() < deadline:
            sink.write(RECORD)  # until the subscriber's declaration has reached the publisher
            time.sleep(0.02)
        assert received and received[0][0] == "test/robot1/spiel"
        assert json.loads(received[0][1]) == RECORD
    finally:
        session.close()
        sink.close()


@pytest.mark.parametrize(
    ("key", "words"),
    [
        ("robots//bad/", "empty chunk"),
        ("robot/*", "holds a wildcard"),
        ("robot/**", "holds a wildcard"),
        ("robot/$*a", "holds a wildcard"),
        ("", "is empty"),
    ],
)
def test_zenoh_rejects_a_bad_key(key, words):
    """A key records cannot go out on, wildcards included (a publisher on ``robot/*`` would
    reach every subscriber of every board's key)."""
    pytest.importorskip(
        "zenoh", reason="extra 'zenoh' not installed (pip install 'spiel-edge[zenoh]')"
    )
    from spiel_edge.errors import ConfigError
    from spiel_edge.outputs.zenoh import ZenohSink

    with pytest.raises(ConfigError, match=re.escape(words)):
        ZenohSink(key)


def test_zenoh_errors_lose_their_rust_source_location():
    from spiel_edge.outputs.zenoh import zenoh_reason

    text = "timeout at /root/.cargo/git/checkouts/zenoh-9/commons/orchestrator.rs:1253."
    assert zenoh_reason(RuntimeError(text)) == "timeout"
    assert zenoh_reason(RuntimeError("plain words")) == "plain words"
    assert zenoh_reason(RuntimeError(" at x.rs:1")) == "RuntimeError"


def test_a_zenoh_configuration_file_in_the_settings_is_used_under_them(tmp_path):
    """``fuse --zenoh-config`` reaches its own --zenoh output too: the file, with the mode
    and endpoints given on the command line over it."""
    pytest.importorskip("zenoh", reason="extra 'zenoh' not installed")
    from spiel_edge.outputs.ros2 import ZenohSettings
    from spiel_edge.outputs.zenoh import session_config

    path = tmp_path / "z.json5"
    path.write_text('{ mode: "client", connect: { endpoints: ["tcp/127.0.0.1:7999"] } }\n')
    cfg = session_config(None, ZenohSettings(mode="", config_file=str(path)))
    assert json.loads(cfg.get_json("mode")) == "client"
    assert json.loads(cfg.get_json("connect/endpoints")) == ["tcp/127.0.0.1:7999"]
    assert (
        json.loads(
            session_config(None, ZenohSettings(mode="peer", config_file=str(path))).get_json("mode")
        )
        == "peer"
    )


# --- the Zenoh output's key and endpoint checks, its settings, a failing put -------------------


@pytest.mark.parametrize(
    ("key", "words"),
    [
        ("/robot/a", "empty chunk"),
        ("robot/a/", "empty chunk"),
        ("robot/a?x=1", "holds '?'"),
        ("robot/#", "holds '#'"),
        ("robot/a$b", "records go out on one concrete key"),  # '$' only starts a wildcard
        ("robot/a\tb", "white space"),
        ("robot/a\nb", "white space"),
    ],
)
def test_publish_key_problems(key, words):
    from spiel_edge.outputs.zenoh import publish_key_problem

    problem = publish_key_problem(key)
    assert problem is not None and words in problem
    assert publish_key_problem("robots/r1/spiel-edge_2/position") is None


@pytest.mark.parametrize(
    "endpoint",
    [
        "tcp/127.0.0.1:7447",
        "udp/10.0.0.1:7447",
        "quic/router.local:7447?rel=1",
        "tcp/[::1]:7447",
        "tcp/[fe80::1%eth0]:65535",
        "unixsock-stream//tmp/zenoh.sock",
    ],
)
def test_zenoh_endpoints_taken(endpoint):
    from spiel_edge.outputs.zenoh import check_endpoint

    assert check_endpoint(endpoint) == endpoint


@pytest.mark.parametrize(
    "endpoint", ["tcp/127.0.0.1:0", "tcp/127.0.0.1:7447 tcp/127.0.0.2:7447", "127.0.0.1:7447", ""]
)
def test_zenoh_endpoints_refused(endpoint):
    from spiel_edge.errors import ConfigError
    from spiel_edge.outputs.zenoh import check_endpoint

    with pytest.raises(ConfigError, match="--zenoh-connect"):
        check_endpoint(endpoint)


def test_zenoh_sessions_scout_no_multicast_and_listen_on_loopback_unless_asked(
    tmp_path, monkeypatch
):
    pytest.importorskip("zenoh", reason="extra 'zenoh' not installed")
    from spiel_edge.outputs.zenoh import session_config

    monkeypatch.delenv("ZENOH_CONFIG", raising=False)

    def multicast(cfg) -> bool | None:
        return json.loads(cfg.get_json("scouting/multicast/enabled"))

    def listen(cfg):
        return json.loads(cfg.get_json("listen/endpoints"))

    assert multicast(session_config(None, None, rmw_zenoh=True)) is False
    assert multicast(session_config(None, None)) is False  # every encoding (docs/security.md)
    assert listen(session_config(None, None)) == ["tcp/127.0.0.1:0"]
    path = tmp_path / "z.json5"
    path.write_text("{ scouting: { multicast: { enabled: true } } }\n")
    assert multicast(session_config(str(path), None, rmw_zenoh=True)) is True
    assert listen(session_config(str(path), None)) == ["tcp/127.0.0.1:0"]  # the file left it
    path.write_text('{ listen: { endpoints: ["tcp/0.0.0.0:7447"] } }\n')
    assert listen(session_config(str(path), None)) == ["tcp/0.0.0.0:7447"]
    assert multicast(session_config(str(path), None)) is False
    path.write_text("{ scouting: { multicast: { enabled: true } } }\n")
    monkeypatch.setenv("ZENOH_CONFIG", str(path))
    assert multicast(session_config(None, None, rmw_zenoh=True)) is True


def test_a_failing_or_unencodable_put_is_counted_and_the_run_goes_on():
    from spiel_edge.outputs.zenoh import ZenohSink

    class Publisher:
        def __init__(self, fail):
            self.fail, self.sent = fail, []

        def put(self, payload):
            if self.fail:
                raise RuntimeError("session closed")
            self.sent.append(payload)

    sink = object.__new__(ZenohSink)  # no session: only write()'s handling is under test
    sink.key_expr, sink.failed = "test/key", 0
    sink._publisher = Publisher(fail=True)
    sink.write(RECORD)
    sink.write(RECORD)
    assert sink.failed == 2
    sink._publisher = Publisher(fail=False)
    sink.write({"seq": 1, "residual_mm": float("nan")})  # not JSON: not sent as NaN
    sink.write(RECORD)
    assert sink.failed == 3 and [json.loads(p) for p in sink._publisher.sent] == [RECORD]
