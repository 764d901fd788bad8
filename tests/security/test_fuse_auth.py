"""Boards that prove who they are to `fuse` (issue 38, item 3): each board's records carry an
HMAC-SHA256 tag with its own key (robot file ``auth_key_file``, ``run --zenoh-auth-key``);
records without it, with another key's, or replayed are counted and never fused. Zenoh on
loopback only."""

from __future__ import annotations

import json
import os
import socket
import threading
import time

import numpy as np
import pytest

from spiel_edge.errors import ConfigError
from spiel_edge.outputs import record_auth
from spiel_edge.robot.description import load_robot

SECRET = "5e" * 32


def _key(path, text=SECRET, mode=0o600):
    path.write_text(text + "\n")
    path.chmod(mode)
    return path


def _robot(tmp_path, signed=("front", "back")):
    (tmp_path / "keys").mkdir(exist_ok=True)
    text = '[robot]\nname = "sec"\n[trigger]\nperiod_ms = 25.0\nmax_range_m = 0.8\n'
    for i, name in enumerate(["front", "back"]):
        _key(tmp_path / "keys" / f"{name}.key", f"{i + 1:02x}" * 32)
        text += f'[[board]]\nname = "{name}"\nport = "sim://{name}"\nkey = "sec/{name}"\n'
        text += f"rotation_rpy_deg = [0.0, 90.0, {180 * i}.0]\n"
        if name in signed:
            text += f'auth_key_file = "keys/{name}.key"\n'
    path = tmp_path / "robot.toml"
    path.write_text(text)
    return path


def test_a_tag_binds_the_record_its_key_and_its_key_expression():
    key = bytes.fromhex(SECRET)
    payload = b'{"x": 1}'
    tag = record_auth.attachment(key, "robot/front", payload)
    v = record_auth.Verifier(key, "robot/front")
    assert v.check(payload, tag) is None
    assert v.check(payload, tag) == "replayed"
    assert v.check(payload + b" ", tag) == "forged"  # the record changed
    assert v.check(payload, None) == "forged"  # unsigned
    other = record_auth.attachment(key, "robot/back", payload)  # another board's key expression
    assert record_auth.Verifier(key, "robot/front").check(payload, other) == "forged"
    wrong = record_auth.attachment(b"\x01" * 32, "robot/front", payload)
    assert record_auth.Verifier(key, "robot/front").check(payload, wrong) == "forged"
    assert record_auth.Verifier(key, "robot/front").check(payload, tag[:-1]) == "forged"


@pytest.mark.parametrize(
    "text, mode, says",
    [
        (SECRET, 0o644, "readable by every user"),
        ("not-a-key-" + SECRET[:40], 0o600, "not a key"),
        ("ab" * 8, 0o600, "not a key"),  # 8 bytes: too short
        (None, 0o600, "cannot read"),
    ],
)
def test_a_bad_key_file_is_one_line_that_never_shows_its_content(tmp_path, text, mode, says):
    path = tmp_path / "k.key"
    if text is not None:
        _key(path, text, mode)
    with pytest.raises(ConfigError) as info:
        record_auth.load_key(path, "--zenoh-auth-key")
    msg = str(info.value)
    assert says in msg and "\n" not in msg
    assert SECRET[:16] not in msg and (text is None or text[:12] not in msg)


def test_the_cli_refuses_a_bad_key_before_it_starts(tmp_path, capsys):
    from spiel_edge.cli import main

    bad = _key(tmp_path / "k.key", "secretpassword" * 4, 0o600)
    args = ["run", "--port", "sim://", "--frames", "1", "--zenoh", "sec/x"]
    assert main([*args, "--zenoh-auth-key", str(bad)]) == 2
    err = capsys.readouterr().err
    # with an empty kernel cache the CLI first says so (before anything is read): not an error
    said = [ln for ln in err.strip().splitlines() if "no compiled kernels in the cache" not in ln]
    assert "not a key" in err and "secretpassword" not in err and len(said) == 1, err
    good = _key(tmp_path / "g.key")
    assert main([*args, "--zenoh-encoding", "cdr", "--zenoh-auth-key", str(good)]) == 2
    assert "tags JSON records" in capsys.readouterr().err


zenoh = pytest.importorskip("zenoh", reason="the 'zenoh' extra is not installed")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Collect:
    def __init__(self):
        self.records = []

    def write(self, record):
        self.records.append(json.loads(json.dumps(record)))


def _record(k: int, target_mm, n: int = 1) -> dict:
    return {
        "acquisition": k,
        "device_time_us": int((10.0 + 0.025 * k) * 1e6),
        "host_time": time.time(),
        "targets": [
            {
                "position_mm": list(target_mm),
                "covariance_mm2": (np.eye(3) * 16).tolist(),
                "score": 1.0,
            }
        ]
        * n,
    }


def test_forged_records_are_counted_and_never_fused(tmp_path, monkeypatch):
    """An unauthenticated peer publishes 20 targets as board 'front' (as in the issue), a
    second one signs with a key of its own, a third replays a record it captured; the boards'
    own tagged records are fused."""
    from spiel_edge.outputs.ros2 import ZenohSettings
    from spiel_edge.outputs.zenoh import ZenohSink
    from spiel_edge.robot.zenoh_fuse import ZenohFuse, zenoh_config

    monkeypatch.delenv("ZENOH_CONFIG", raising=False)
    robot = load_robot(_robot(tmp_path))
    endpoint = f"tcp/127.0.0.1:{_free_port()}"
    sink = Collect()
    fuse = ZenohFuse(robot, sink, config=zenoh_config(listen=[endpoint]))
    stop = threading.Event()
    worker = threading.Thread(target=fuse.run, args=(stop,), kwargs={"idle_s": 1.5})
    worker.start()
    boards = {
        b.name: ZenohSink(
            b.key,
            settings=ZenohSettings(
                connect=(endpoint,),
                auth_key=record_auth.load_key(robot.auth_key_path(b), "key"),
            ),
        )
        for b in robot.boards
    }
    attacker = zenoh.open(zenoh_config(connect=[endpoint]))
    captured = []
    spy = attacker.declare_subscriber(
        "sec/front", lambda s: captured.append((s.payload.to_bytes(), s.attachment.to_bytes()))
    )
    # BLOCK: every forged put must reach fuse for the count below (a put's default may drop)
    forger = attacker.declare_publisher(
        "sec/front", congestion_control=zenoh.CongestionControl.BLOCK
    )
    forged_at = [900.0, 0.0, 0.0]
    try:
        time.sleep(1.0)  # the peers connect
        for k in range(40):
            for b in boards.values():
                b.write(_record(k, [0.0, 0.0, 200.0]))
            if 10 <= k < 30:
                forged = json.dumps(_record(k, forged_at, n=1)).encode()
                forger.put(forged)  # unauthenticated: 20 forged targets
                forger.put(
                    forged, attachment=record_auth.attachment(b"\x07" * 32, "sec/front", forged)
                )
            if k == 35 and captured:
                forger.put(captured[5][0], attachment=captured[5][1])  # a replay
            time.sleep(0.025)
    finally:
        worker.join(timeout=20)
        stop.set()
        spy.undeclare()
        attacker.close()
        for b in boards.values():
            b.close()
        fuse.close()
    assert captured, "the spy heard nothing: the test proves nothing"
    fused = [t for r in sink.records for t in r["targets"]]
    assert fused and not any(abs(t["position_mm"][0]) > 500 for t in fused)  # none forged
    assert fuse.refused["front"]["forged"] == 40
    assert fuse.refused["front"]["replayed"] == 1
    assert not fuse.dropped and "back" not in fuse.refused
    front = sum(1 for r in sink.records if "front" in r["boards"])
    assert front >= 30
    assert "messages refused (forged 40, replayed 1)" in fuse.summary()


def test_run_zenoh_auth_key_records_are_fused_as_their_board(tmp_path, monkeypatch):
    """The CLI path end to end: `run --zenoh KEY --zenoh-auth-key FILE` on the virtual board,
    `fuse`'s session with the robot file's auth_key_file: every record accepted."""
    from spiel_edge.cli import main
    from spiel_edge.robot.zenoh_fuse import ZenohFuse, zenoh_config

    monkeypatch.delenv("ZENOH_CONFIG", raising=False)
    robot = load_robot(_robot(tmp_path, signed=("front",)))
    endpoint = f"tcp/127.0.0.1:{_free_port()}"
    sink = Collect()
    fuse = ZenohFuse(robot, sink, config=zenoh_config(listen=[endpoint]))
    stop = threading.Event()
    worker = threading.Thread(target=fuse.run, args=(stop,), kwargs={"idle_s": 2.0})
    worker.start()
    try:
        key = tmp_path / "keys" / "front.key"
        args = ["run", "--port", "sim://", "--frames", "60", "--rate", "40", "-o", os.devnull]
        zargs = ["--zenoh", "sec/front", "--zenoh-connect", endpoint, "--zenoh-auth-key", str(key)]
        assert main([*args, *zargs]) == 0
    finally:
        worker.join(timeout=30)
        stop.set()
        fuse.close()
    assert fuse.fuser.stats["front"]["reports"] >= 30, fuse.summary()
    assert "front" not in fuse.refused, fuse.refused


class _Bytes:
    def __init__(self, data):
        self.data = data

    def to_bytes(self):
        return self.data


class _Sample:
    def __init__(self, payload, attachment=None):
        self.payload = _Bytes(payload)
        self.attachment = None if attachment is None else _Bytes(attachment)


def test_a_flooding_board_costs_only_its_own_records(tmp_path, monkeypatch):
    """One board's peer puts 10,000 messages before fuse reads any: it gets its share of the
    queue, the rest of its messages are counted `flood`; the other board's still go in; a
    forged flood takes no place in the queue at all."""
    from spiel_edge.robot.zenoh_fuse import ZenohFuse

    monkeypatch.delenv("ZENOH_CONFIG", raising=False)
    robot = load_robot(_robot(tmp_path, signed=("back",)))
    fuse = ZenohFuse(robot, Collect())
    try:
        front, back = fuse._callback("front"), fuse._callback("back")
        record = json.dumps(_record(0, [0.0, 0.0, 200.0])).encode()
        for _ in range(10_000):
            front(_Sample(record))
            back(_Sample(record))  # unsigned: forged
        assert fuse.queue.qsize() == fuse.share  # front's share, nothing of the forgeries
        assert fuse.refused["front"]["flood"] == 10_000 - fuse.share
        assert fuse.refused["back"]["forged"] == 10_000
        key = record_auth.load_key(robot.auth_key_path(robot.boards[1]), "key")
        back(_Sample(record, record_auth.attachment(key, "sec/back", record)))
        assert fuse.queue.qsize() == fuse.share + 1  # back's own record still goes in
        assert fuse.overflow == 0
    finally:
        fuse.close()
