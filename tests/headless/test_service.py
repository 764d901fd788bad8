"""sd_notify against a local AF_UNIX datagram socket, SIGTERM handling, journald log lines."""

from __future__ import annotations

import logging
import os
import signal
import socket
import time

import pytest

from spiel_edge.cli._signals import Terminated, terminate_raises
from spiel_edge.service.systemd import (
    JournalFormatter,
    Notifier,
    notify,
    stderr_is_journal,
    watchdog_interval_s,
)


@pytest.fixture
def notify_socket(tmp_path):
    path = tmp_path / "notify.sock"
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(str(path))
    sock.settimeout(2.0)
    yield sock, str(path)
    sock.close()


def test_notify_sends_the_state(notify_socket):
    sock, path = notify_socket
    assert notify("READY=1\nSTATUS=hi", {"NOTIFY_SOCKET": path})
    assert sock.recv(4096) == b"READY=1\nSTATUS=hi"


def test_notify_abstract_namespace():
    name = f"spiel-edge-test-{os.getpid()}"
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind("\0" + name)
    sock.settimeout(2.0)
    try:
        assert notify("WATCHDOG=1", {"NOTIFY_SOCKET": "@" + name})
        assert sock.recv(4096) == b"WATCHDOG=1"
    finally:
        sock.close()


def test_notify_outside_systemd_or_broken_socket_is_quiet(tmp_path):
    assert not notify("READY=1", {})
    assert not notify("READY=1", {"NOTIFY_SOCKET": str(tmp_path / "nobody-listens")})
    assert not notify("READY=1", {"NOTIFY_SOCKET": "relative/path"})


def test_notify_never_blocks_on_a_full_queue(notify_socket):
    _, path = notify_socket  # nobody reads: the kernel queue fills after a few datagrams
    start = time.monotonic()
    results = [notify("WATCHDOG=1", {"NOTIFY_SOCKET": path}) for _ in range(200)]
    assert time.monotonic() - start < 1.0
    assert results[0] and not all(
        results
    )  # the first went out; later ones were dropped, not waited on


def test_watchdog_interval_is_half_of_watchdog_sec():
    assert watchdog_interval_s({"WATCHDOG_USEC": "10000000"}) == 5.0
    assert watchdog_interval_s({"WATCHDOG_USEC": "10000000", "WATCHDOG_PID": "1"}, pid=2) is None
    assert watchdog_interval_s({"WATCHDOG_USEC": "10000000", "WATCHDOG_PID": "2"}, pid=2) == 5.0
    assert watchdog_interval_s({}) is None
    assert watchdog_interval_s({"WATCHDOG_USEC": "garbage"}) is None


def test_notifier_ready_then_rate_limited_watchdog(notify_socket):
    sock, path = notify_socket
    now = [100.0]
    notifier = Notifier({"NOTIFY_SOCKET": path, "WATCHDOG_USEC": "2000000"}, clock=lambda: now[0])
    assert notifier.interval_s == 1.0
    assert notifier.ready("running")
    assert sock.recv(4096) == b"READY=1\nSTATUS=running"
    sent = []
    for _ in range(12):  # 3 s of acquisitions at 4 Hz (steps exact in binary)
        now[0] += 0.25
        sent.append(notifier.ping())
    assert sum(sent) == 3
    assert [sock.recv(4096) for _ in range(3)] == [b"WATCHDOG=1"] * 3
    assert notifier.stopping() and sock.recv(4096) == b"STOPPING=1"


def test_notifier_without_systemd_does_nothing():
    notifier = Notifier({})
    assert not notifier.enabled and notifier.interval_s is None
    assert not notifier.ready() and not notifier.ping()


def test_sigterm_raises_terminated_inside_and_restores_after():
    before = signal.getsignal(signal.SIGTERM)
    with pytest.raises(Terminated), terminate_raises():
        os.kill(os.getpid(), signal.SIGTERM)
        for _ in range(10**6):  # the handler runs at the next bytecode boundary
            pass
    assert signal.getsignal(signal.SIGTERM) is before
    assert issubclass(Terminated, KeyboardInterrupt)  # the run loop's Ctrl-C path handles it


def test_journal_formatter_priorities_per_line():
    fmt = JournalFormatter()

    def line(level, msg):
        return fmt.format(logging.LogRecord("spiel_edge.x", level, __file__, 1, msg, None, None))

    assert line(logging.ERROR, "board gone") == "<3>spiel_edge.x: board gone"
    assert line(logging.WARNING, "w") == "<4>spiel_edge.x: w"
    assert line(logging.INFO, "i") == "<6>spiel_edge.x: i"
    assert line(logging.DEBUG, "d") == "<7>spiel_edge.x: d"
    assert line(logging.ERROR, "a\nb") == "<3>spiel_edge.x: a\n<3>b"


def test_stderr_is_journal_matches_the_stream(tmp_path):
    with open(tmp_path / "f", "w") as fh:
        st = os.fstat(fh.fileno())
        assert stderr_is_journal({"JOURNAL_STREAM": f"{st.st_dev}:{st.st_ino}"}, fd=fh.fileno())
        assert not stderr_is_journal(
            {"JOURNAL_STREAM": f"{st.st_dev}:{st.st_ino + 1}"}, fd=fh.fileno()
        )
    assert not stderr_is_journal({})


def test_cli_logging_uses_priority_prefixes_when_stderr_is_the_journal(tmp_path):
    import subprocess
    import sys

    script = (
        "import logging; from spiel_edge.cli import setup_logging; setup_logging(1); "
        "logging.getLogger('spiel_edge.t').warning('careful'); logging.getLogger('spiel_edge.t').info('fyi')"
    )
    log_file = tmp_path / "stderr"
    with open(log_file, "w") as err:
        st = os.fstat(err.fileno())
        env = {**os.environ, "JOURNAL_STREAM": f"{st.st_dev}:{st.st_ino}"}
        subprocess.run([sys.executable, "-c", script], stderr=err, env=env, timeout=60, check=True)
    assert log_file.read_text().splitlines() == ["<4>spiel_edge.t: careful", "<6>spiel_edge.t: fyi"]
