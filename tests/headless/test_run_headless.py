"""`spiel-edge run` on the virtual board with the headless outputs, sd_notify and SIGTERM."""

from __future__ import annotations

import contextlib
import itertools
import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time

import pytest
from mcap.reader import make_reader

from spiel_edge.cli import main
from spiel_edge.recordings.mcap_reader import (
    ACQUISITION_TOPIC,
    POSITION_TOPIC,
    iter_mcap_recordings,
)

_names = itertools.count()


def board(query: str = "scene=model&seed=5") -> str:
    """A virtual board no other test uses (boards are per name within one process)."""
    return f"sim://headless{os.getpid()}x{next(_names)}?{query}"


def ndjson(path) -> list[dict]:
    return [json.loads(line) for line in path.read_text().splitlines()]


def test_every_output_at_once(tmp_path):
    receiver = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    receiver.bind(("127.0.0.1", 0))
    receiver.settimeout(5)
    out, rec = tmp_path / "out.ndjson", tmp_path / "run.mcap"
    try:
        argv = [
            "run",
            "--port",
            board(),
            "--frames",
            "25",
            "--rate",
            "400",
            "-o",
            str(out),
            "--record",
            str(rec),
            "--udp",
            f"127.0.0.1:{receiver.getsockname()[1]}",
        ]
        assert main(argv) == 0
        datagrams = [json.loads(receiver.recv(65535)) for _ in range(25)]
    finally:
        receiver.close()
    lines = ndjson(out)
    assert datagrams == lines and len(lines) == 25
    with open(rec, "rb") as fh:
        reader = make_reader(fh)
        counts = reader.get_summary().statistics.channel_message_counts
        topics = {c.id: c.topic for c in reader.get_summary().channels.values()}
        recorded = [json.loads(m.data) for _, _, m in reader.iter_messages(topics=[POSITION_TOPIC])]
    assert {topics[c]: n for c, n in counts.items() if topics[c] != "/spiel/background"} == {
        ACQUISITION_TOPIC: 25,
        POSITION_TOPIC: 25,
    }
    assert recorded == lines


def test_run_tells_systemd_ready_watchdog_stopping(tmp_path, monkeypatch):
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(str(tmp_path / "notify"))
    sock.settimeout(0.2)
    messages: list[str] = []
    done = threading.Event()

    def manager() -> None:  # reads as systemd does, all along
        while not done.is_set():
            with contextlib.suppress(TimeoutError):
                messages.append(sock.recv(4096).decode())

    reader = threading.Thread(target=manager, daemon=True)
    reader.start()
    monkeypatch.setenv("NOTIFY_SOCKET", str(tmp_path / "notify"))
    monkeypatch.setenv("WATCHDOG_USEC", "20000")  # ping at most every 10 ms
    monkeypatch.delenv("WATCHDOG_PID", raising=False)
    try:
        assert (
            main(["run", "--port", board(), "--frames", "40", "--rate", "200", "-o", os.devnull])
            == 0
        )
        time.sleep(0.3)
    finally:
        done.set()
        reader.join(2)
        sock.close()
    assert messages[0].startswith("READY=1")
    assert messages[-1] == "STOPPING=1"
    pings = messages.count("WATCHDOG=1")
    assert (
        3 <= pings <= 40
    )  # about one per 10 ms over a 200 ms stream, never more than one per record


_RUN = "import sys; from spiel_edge.cli import main; sys.exit(main())"


def test_sigterm_stops_run_with_a_finalized_recording(tmp_path):
    out, rec = tmp_path / "out.ndjson", tmp_path / "run.mcap"
    cmd = [
        sys.executable,
        "-c",
        _RUN,
        "run",
        "--port",
        board("scene=replay"),
        "--rate",
        "100",
        "-o",
        str(out),
        "--record",
        str(rec),
        "--no-status",
    ]
    proc = subprocess.Popen(cmd, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 60  # numba cache load or compile, then 100 Hz
        while time.monotonic() < deadline and (
            not out.exists() or out.read_text().count("\n") < 30
        ):
            assert proc.poll() is None, proc.stderr.read()
            time.sleep(0.05)
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=10)
    finally:
        proc.kill()
    assert proc.returncode == 0, err
    lines = ndjson(out)
    with open(rec, "rb") as fh:
        summary = make_reader(fh).get_summary()
    assert summary is not None  # footer and summary written
    recs = list(iter_mcap_recordings(rec))
    assert len(recs) == len(lines) >= 30 and all(r.error is None for r in recs)
    assert [r.source.rsplit("#", 1)[1] for r in recs] == [str(line["seq"]) for line in lines]


def test_run_with_a_missing_extra_or_bad_target_fails_before_streaming(tmp_path, capsys):
    assert main(["run", "--port", board(), "--frames", "1", "--udp", "nowhere"]) == 2
    assert "--udp 'nowhere' is not HOST:PORT" in capsys.readouterr().err
    assert (
        main(["run", "--port", board(), "--frames", "1", "--record", str(tmp_path / "x.txt")]) == 2
    )
    assert "must end in .mcap" in capsys.readouterr().err


@pytest.mark.parametrize("extra", ["foxglove"])
def test_run_with_foxglove_on_loopback(tmp_path, extra):
    pytest.importorskip(
        extra, reason=f"extra '{extra}' not installed (pip install 'spiel-edge[{extra}]')"
    )
    out = tmp_path / "out.ndjson"
    assert (
        main(
            [
                "run",
                "--port",
                board(),
                "--frames",
                "5",
                "--rate",
                "200",
                "-o",
                str(out),
                "--foxglove",
                "0",
            ]
        )
        == 0
    )
    assert len(ndjson(out)) == 5
