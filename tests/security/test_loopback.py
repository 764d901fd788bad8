"""Nothing of spiel-edge is reachable beyond this computer unless asked (issue 38, item 2):
every Zenoh session listens on loopback and does not scout by multicast by default; Foxglove
binds 127.0.0.1 and warns in one line when bound wider. Sockets are read from /proc."""

from __future__ import annotations

import logging
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from spiel_edge.errors import ConfigError
from tests.security._sockets import beyond_loopback, reachable

pytestmark = pytest.mark.skipif(not Path("/proc/self/net/tcp").exists(), reason="needs /proc")


def _new_sockets(before):
    return [s for s in reachable(os.getpid()) if s not in before]


@pytest.fixture
def no_zenoh_config(monkeypatch):
    pytest.importorskip("zenoh", reason="extra 'zenoh' not installed")
    monkeypatch.delenv("ZENOH_CONFIG", raising=False)


@pytest.mark.parametrize("encoding", ["json", "cdr", "rmw_zenoh"])
def test_run_zenoh_sessions_listen_on_loopback_only(no_zenoh_config, encoding):
    from spiel_edge.outputs.rmw_zenoh.sink import RmwZenohSink
    from spiel_edge.outputs.zenoh import ZenohSink
    from spiel_edge.outputs.zenoh_ros2 import ZenohRos2Sink

    before = reachable(os.getpid())
    open_sink = {
        "json": lambda: ZenohSink("sec/test/json"),
        "cdr": lambda: ZenohRos2Sink("sec/test/cdr"),
        "rmw_zenoh": lambda: RmwZenohSink("sec_test"),
    }[encoding]
    sink = open_sink()
    try:
        time.sleep(0.5)
        new = _new_sockets(before)
    finally:
        sink.close()
    assert all(s[1] in ("127.0.0.1", "::1") for s in new), new
    assert not any(s[0].startswith("udp") for s in new), new  # no multicast scouting
    if encoding != "rmw_zenoh":  # a peer listens (rmw_zenoh's may be a client of its router)
        assert any(s[0].startswith("tcp") for s in new), new


def test_fuse_session_listens_on_loopback_only(no_zenoh_config):
    from spiel_edge.robot.description import load_robot
    from spiel_edge.robot.zenoh_fuse import ZenohFuse

    class Null:
        def write(self, record):
            pass

    before = reachable(os.getpid())
    fuse = ZenohFuse(load_robot("virtual-4"), Null())
    try:
        time.sleep(0.5)
        new = _new_sockets(before)
    finally:
        fuse.close()
    assert new and all(s[1] == "127.0.0.1" and s[0] == "tcp" for s in new), new


def test_asked_for_endpoints_are_kept(no_zenoh_config):
    import json

    from spiel_edge.robot.zenoh_fuse import zenoh_config

    cfg = zenoh_config(listen=["tcp/127.0.0.1:7999"])
    assert json.loads(cfg.get_json("listen/endpoints")) == ["tcp/127.0.0.1:7999"]
    assert json.loads(cfg.get_json("scouting/multicast/enabled")) is False


def test_foxglove_binds_loopback_by_default_and_warns_once_when_wider(monkeypatch, caplog):
    pytest.importorskip("foxglove", reason="extra 'foxglove' not installed")
    import foxglove

    from spiel_edge.outputs.foxglove import FoxgloveSink, is_loopback

    assert all(map(is_loopback, ["127.0.0.1", "127.0.0.2", "::1", "localhost"]))
    assert not any(map(is_loopback, ["0.0.0.0", "::", "192.168.1.7", "robot.local"]))
    before = reachable(os.getpid())
    with caplog.at_level(logging.WARNING, logger="spiel_edge"):
        sink = FoxgloveSink("0")
        try:
            new = _new_sockets(before)
        finally:
            sink.close()
    assert new == [("tcp", "127.0.0.1", sink.port)]
    assert not caplog.records
    seen = []

    def refuse(**kw):  # no socket opened wider than loopback in a test
        seen.append(kw["host"])
        raise OSError("not here")

    monkeypatch.setattr(foxglove, "start_server", refuse)
    with caplog.at_level(logging.WARNING, logger="spiel_edge"), pytest.raises(ConfigError):
        FoxgloveSink("0.0.0.0:0")
    (line,) = [r.getMessage() for r in caplog.records]
    assert seen == ["0.0.0.0"] and "reachable from other computers" in line and "\n" not in line


def _wait_for_listeners(proc, count: int, timeout_s: float = 120.0):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline and proc.poll() is None:
        socks = [s for s in reachable(proc.pid) if s[0].startswith("tcp")]
        if len(socks) >= count:
            time.sleep(0.5)  # anything opened right after
            return reachable(proc.pid)
        time.sleep(0.2)
    raise AssertionError(f"no {count} listeners; exit {proc.poll()}")


@pytest.mark.parametrize(
    "args, listeners",
    [
        (["run", "--port", "sim://", "--zenoh", "sec/front", "--foxglove", "0"], 2),
        (["fuse", "--robot", "virtual-4", "--zenoh", "sec/fused"], 1),
        (["run", "--robot", "virtual-4", "--zenoh", "sec/robot", "--odom", "sec/odom"], 2),
    ],
)
def test_the_commands_with_default_options_listen_on_loopback_only(
    no_zenoh_config, tmp_path, args, listeners
):
    pytest.importorskip("foxglove", reason="extra 'foxglove' not installed")
    cmd = [
        str(Path(sys.executable).with_name("spiel-edge")),
        *args,
        "-o",
        str(tmp_path / "out.ndjson"),
    ]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, cwd=tmp_path)
    try:
        socks = _wait_for_listeners(proc, listeners)
        assert not beyond_loopback(proc.pid), socks
        assert not [s for s in socks if s[0].startswith("udp")], socks
    finally:
        proc.terminate()
        proc.wait(timeout=20)
